"""The compensator contract: one actuator channel, stepped once per loop step.

Every compensator (those of :mod:`rths_hil.compensators` and a lab's own) is a
:class:`Compensator`: :meth:`~Compensator.reset` on (re-)arming, :meth:`~Compensator.step` once per
loop step with the target, optionally :meth:`~Compensator.observe` with the command sent and the
displacement measured, and an ``alpha`` attribute (the equivalent inverse-compensation α,
``1 + lead·fs``) that the record and the console show. All are configured in physical units
(``compensation.delay`` in s), so a change of ``loop.fs`` keeps the same compensation.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from ..errors import InputError
from ..keys import Key

__all__ = ["Compensator"]


class Compensator:
    """Base class of every compensator: one actuator channel, stepped once per loop step.

    Subclasses implement :meth:`step` (and :meth:`reset` when they keep history); those that
    learn from the reply also implement :meth:`observe`. Each call must do O(1) work with no
    allocation worth mentioning: it runs between the reply of step k and the send of step k+1.

    Attributes
    ----------
    alpha : float
        Equivalent inverse-compensation α, ``1 + lead·fs`` with ``lead`` the delay (s) the
        compensator currently compensates. The loop records it every step (column ``alpha``)
        and the console shows it; a method that adapts its lead keeps it current.
    enabled : bool
        False: the command is the target.
    KEYS : mapping of str to Key
        The ``compensation.*`` keys of the method besides those every method shares
        (``enabled``, ``method``, ``delay``, ``alpha``, ``amplitude``, ``options``): name →
        :class:`~rths_hil.keys.Key`. The schema's ``compensation`` section is the shared keys
        and the keys of each built-in method (:data:`rths_hil.compensators.BUILTIN`); a lab's
        method takes its own keys from ``compensation.options``.
    ARGUMENTS : mapping of str to str
        A built-in method's constructor arguments and the ``compensation.*`` key each comes
        from, read by the default :meth:`from_config` (with ``fs``); empty for a lab's method.
    """

    KEYS: ClassVar[Mapping[str, Key]] = {}
    ARGUMENTS: ClassVar[Mapping[str, str]] = {}
    alpha: float = 1.0
    enabled: bool = True

    @classmethod
    def from_config(cls, c: Mapping[str, Any], fs: float) -> Compensator:
        """Build from a channel's resolved ``compensation`` section at loop rate ``fs`` (Hz).

        The default passes ``fs`` and, as :attr:`ARGUMENTS` names them, the built-in method's
        keys or else the keys of ``compensation.options`` (a lab's own compensator) to the
        constructor.
        """
        # a lab's compensator declares its own constructor (fs and its options)
        make: Callable[..., Compensator] = cls
        if cls.ARGUMENTS:
            return make(fs=fs, **cls.config_arguments(c))
        opts = dict(c.get("options") or {})
        try:
            return make(fs=fs, **opts)
        except TypeError as exc:
            raise InputError(f"compensation.options: {exc}") from None

    @classmethod
    def config_arguments(cls, c: Mapping[str, Any]) -> dict[str, Any]:
        """The constructor's keyword arguments from the ``compensation`` section ``c``.

        Parameters
        ----------
        c : mapping
            A channel's resolved ``compensation`` section.

        Returns
        -------
        dict
            ``{argument: c[key]}`` for each ``argument: key`` of :attr:`ARGUMENTS`.
        """
        return {arg: c[key] for arg, key in cls.ARGUMENTS.items()}

    def reset(self, target: float = 0.0) -> None:
        """Forget the history: the target has been ``target`` (m) forever (on re-arm)."""

    def step(self, target: float) -> float:
        """Return the command (m) for this step's target ``target`` (m)."""
        raise NotImplementedError

    def observe(self, target: float, command: float, measured: float) -> None:
        """The reply of a step: its target, the command sent and the measured displacement (m).

        Called once per step after the reply, when the subclass overrides it (the base does
        nothing and is not called).
        """

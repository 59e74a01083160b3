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
    KEYS : tuple of str
        The ``compensation.*`` keys the method reads besides ``enabled`` and ``method``
        (documentation; a lab's method takes its own keys from ``compensation.options``).
    """

    KEYS: ClassVar[tuple[str, ...]] = ()
    alpha: float = 1.0
    enabled: bool = True

    @classmethod
    def from_config(cls, c: Mapping[str, Any], fs: float) -> Compensator:
        """Build from a channel's resolved ``compensation`` section at loop rate ``fs`` (Hz).

        The default passes ``fs`` and the keys of ``compensation.options`` to the constructor
        (a lab's own compensator); the built-in methods read their documented keys.
        """
        opts = dict(c.get("options") or {})
        # a lab's compensator declares its own constructor (fs and its options)
        make: Callable[..., Compensator] = cls
        try:
            return make(fs=fs, **opts)
        except TypeError as exc:
            raise InputError(f"compensation.options: {exc}") from None

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

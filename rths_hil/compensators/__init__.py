"""Compensator registry: the built-in methods and a lab's own, chosen per channel.

``compensation.method`` names the compensator of a channel (``[compensation]`` for every channel,
``[actuators.compensation]`` for one). Two sources, as for drivers and twins:

* :data:`BUILTIN` — the methods shipped here, by name → ``"module:Class"``, imported only when
  asked for: ``inverse`` (:class:`rths_hil.compensators.inverse.InverseCompensator`), ``polynomial``
  (:class:`~rths_hil.compensators.polynomial.PolynomialCompensator`), ``ats``
  (:class:`~rths_hil.compensators.ats.ATSCompensator`) and ``model``
  (:class:`~rths_hil.compensators.model.ModelCompensator`);
* the ``rths_hil.compensators`` entry-point group — a lab's package declares in its
  ``pyproject.toml``::

      [project.entry-points."rths_hil.compensators"]
      mylab = "mylab_comp:MyCompensator"

The class must subclass :class:`rths_hil.compensators.base.Compensator`; it is built with
:meth:`~rths_hil.compensators.base.Compensator.from_config`
(by default ``cls(fs=…, **options)`` with the
keys of ``compensation.options``). An entry point with a built-in name replaces the built-in.
See ``docs/compensation.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..errors import InputError
from ..plugins import load_target
from ..plugins import targets as plugin_targets
from .base import Compensator
from .inverse import InverseCompensator, alpha_for_delay

__all__ = ["BUILTIN", "ENTRY_POINT_GROUP", "available", "build_compensator", "compensator_class"]

ENTRY_POINT_GROUP = "rths_hil.compensators"

#: The compensators shipped with rths_hil: name → ``"module:Class"``.
BUILTIN: dict[str, str] = {
    "inverse": "rths_hil.compensators.inverse:InverseCompensator",
    "polynomial": "rths_hil.compensators.polynomial:PolynomialCompensator",
    "ats": "rths_hil.compensators.ats:ATSCompensator",
    "model": "rths_hil.compensators.model:ModelCompensator",
}


def available() -> dict[str, str]:
    """Map every known compensator name to its ``module:Class`` target."""
    return plugin_targets(ENTRY_POINT_GROUP, BUILTIN)


def compensator_class(name: str) -> type[Compensator]:
    """Return the compensator class registered under ``name``.

    Raises
    ------
    InputError
        No compensator of that name, or the target is not a Compensator subclass.
    """
    targets = available()
    if name not in targets:
        raise InputError(f"unknown compensator {name!r}; available: {', '.join(sorted(targets))}")
    cls: type[Compensator] = load_target(
        targets[name], Compensator, f"compensator {name!r}: entry point"
    )
    return cls


def build_compensator(c: Mapping[str, Any], fs: float) -> Compensator:
    """The compensator of a channel from its resolved ``compensation`` section at ``fs`` (Hz).

    ``enabled = false`` gives the pass-through (command = target; ``alpha`` still shows the
    configured ``1 + delay·fs``).

    Raises
    ------
    InputError
        Unknown method, or a key the method rejects (the message names the key).
    """
    if not c["enabled"]:
        return InverseCompensator(alpha_for_delay(c["delay"], 1.0 / fs), c["amplitude"], False)
    cls = compensator_class(c["method"])
    comp = cls.from_config(c, fs)
    if not isinstance(comp, Compensator):
        raise InputError(f"compensator {c['method']!r}: from_config did not return a Compensator")
    return comp

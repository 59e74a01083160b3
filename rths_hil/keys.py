"""One configuration key (:class:`Key`: kind, default, unit, range, doc) and the ranges several
sections share.

The keys of the run configuration (:mod:`rths_hil.config`) and those a plug-in declares for
itself (a driver's connection, a compensator's method keys, a profile's or a model file's
tables) are :class:`Key` objects, read by :func:`rths_hil.config.check_table`. This module sits
outside :mod:`rths_hil.config` and imports nothing of the project, so that a plug-in whose keys
the schema collects (the compensators) declares them without importing the configuration.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass
from typing import Any, Final


class _Required:
    """The default of a key a table must give (:data:`REQUIRED`)."""

    def __repr__(self) -> str:
        return "REQUIRED"


#: The default of a key that has none: :func:`rths_hil.config.check_table` refuses a table
#: without it (profiles and model files; every run configuration key has a default).
REQUIRED: Final = _Required()

__all__ = ["CONTROL_MODES", "MASS_RANGE", "REQUIRED", "STIFFNESS_RANGE", "Key", "seconds", "steps"]


@dataclass(frozen=True)
class Key:
    """One configuration key.

    Attributes
    ----------
    kind : str
        ``float`` (a quantity in ``unit``), ``int``, ``bool``, ``str``, ``str|int`` (a name or
        a number, as given: a CAN channel, an object index), ``choice``, ``window``
        (seconds or natural periods), ``array`` (a list of quantities in ``unit``),
        ``schedule`` (a list of ``[t, value]`` pairs, ``t`` in s non-decreasing from 0, the
        value in the second unit of ``unit``), ``table`` (free-form, checked by its
        consumer) or ``tables`` (an array of tables, each checked by its consumer).
    default : Any
        Default value (already in SI units); :data:`REQUIRED` for a key that must be given,
        ``None`` for an optional one without a value.
    unit : str
        SI unit of the value (``s``, ``m``, ``Hz``, ``N``, ``kg``, ``N/m``, ``m/s``, ``m/s²``,
        ``1/s``, ``-``, ``steps``, ``windows``).
    doc : str
        One-line description.
    lo, hi : float or None
        Allowed range; ``lo_open``/``hi_open`` make the bound exclusive.
    choices : tuple of str
        Allowed values of a ``choice`` key.
    """

    kind: str
    default: Any
    _: KW_ONLY
    unit: str = "-"
    doc: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()


def seconds(default: float, doc: str = "", *, positive: bool = False, **range_: Any) -> Key:
    """A duration key: a float in s, ≥ 0 (> 0 with ``positive``); ``range_`` gives an upper
    bound (``hi``, ``hi_open``)."""
    return Key("float", default, unit="s", doc=doc, lo=0, lo_open=positive, **range_)


def steps(default: int, doc: str = "", *, lo: int = 0) -> Key:
    """A count of loop steps: an integer ≥ ``lo``."""
    return Key("int", default, unit="steps", doc=doc, lo=lo)


#: A channel's control modes (``control.mode``): what its actuator follows.
CONTROL_MODES = ("displacement", "force", "load")

#: The schema: section → key → :class:`Key`. The defaults form the embedded NEES-711 setup.
#: Physically plausible masses (kg) of a numerical substructure: 1 g (a bench model's storey)
#: to 10 Mt (ten times a 100-storey tower's floor). Beyond them the structure's matrices are
#: numerically singular (1e-300 kg) or its response overflows: refused with the key and value.
MASS_RANGE = (1e-3, 1e10)
#: Physically plausible storey stiffnesses (N/m): 1 mN/m to 1 TN/m (a stiff concrete core
#: storey is of order 1e10 N/m).
STIFFNESS_RANGE = (1e-3, 1e12)

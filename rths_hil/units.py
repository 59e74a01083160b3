"""Parsing of quantities with units as given on the command line and in configs.

All values are returned in SI units (s, m, m/s², Hz, N) or as plain fractions. Errors raise
:class:`rths_hil.errors.InputError` with a message naming the offending text and the units
accepted. Lengths take ``m``, ``mm``, ``cm``, ``um``/``µm``, ``in`` and ``ft``; forces ``N``,
``kN``, ``MN``, ``lbf`` and ``kip``; velocities any length unit per ``s``. US customary units
are exact by definition (1 in = 25.4 mm, 1 lbf = 4.4482216152605 N, 1 kip = 1000 lbf).

The table is written out rather than taken from ``pint``: importing pint and building its unit
registry took 2.3 s on the development machine, against 0.17 s for all of
:mod:`rths_hil.config`, and the command line reads units at every start.
"""

from __future__ import annotations

import math
import re
from typing import Any

from .errors import InputError

G = 9.80665
"""Standard gravity in m/s²."""

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
NUMBER = _NUM
"""The number syntax every reader of a value with a unit accepts (a regular expression)."""
_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "min": 60.0}
_LENGTH_UNITS = {
    "m": 1.0,
    "mm": 1e-3,
    "cm": 1e-2,
    "um": 1e-6,
    "µm": 1e-6,
    "in": 0.0254,
    "ft": 0.3048,
}
LBF = 4.4482216152605
"""One pound-force in newtons (exact: 0.45359237 kg × 9.80665 m/s²)."""
_FORCE_UNITS = {"N": 1.0, "kN": 1e3, "MN": 1e6, "lbf": LBF, "kip": 1e3 * LBF}
_LENGTHS = "m, mm, cm, um, in or ft"
_FORCES = "N, kN, MN, lbf or kip"


def _split(text: str, what: str) -> tuple[float, str]:
    m = re.fullmatch(rf"\s*({_NUM})\s*([A-Za-zµ%/²]*)\s*", str(text))
    if not m:
        raise InputError(f"cannot read {what} {text!r}: expected a number with an optional unit")
    return float(m.group(1)), m.group(2)


def _scaled(
    text: str | float, what: str, units: dict[str, float], default: str, names: str
) -> float:
    """``text`` (a number, or a number and one of ``units``) times its unit's scale."""
    if isinstance(text, int | float):
        return float(text) * units[default]
    value, unit = _split(text, what)
    unit = unit or default
    if unit not in units:
        raise InputError(f"cannot read {what} {text!r}: unknown unit {unit!r} (use {names})")
    return value * units[unit]


def parse_time(text: str | float, what: str = "time", default_unit: str = "s") -> float:
    """Parse a duration such as ``5ms``, ``0.005``, ``3s`` into seconds."""
    return _scaled(text, what, _TIME_UNITS, default_unit, "s or ms")


def parse_length(text: str | float, what: str = "length") -> float:
    """Parse a length such as ``10mm`` or ``0.01`` (metres) into metres."""
    return _scaled(text, what, _LENGTH_UNITS, "m", _LENGTHS)


def parse_force(text: str | float, what: str = "force") -> float:
    """Parse a force such as ``100kN``, ``20 kip`` or ``1e5`` (newtons) into newtons."""
    return _scaled(text, what, _FORCE_UNITS, "N", _FORCES)


def parse_velocity(text: str | float, what: str = "velocity") -> float:
    """Parse a velocity such as ``0.2``, ``200mm/s`` or ``8 in/s`` into m/s.

    A unit is a length unit per second.
    """
    if isinstance(text, int | float):
        return float(text)
    value, unit = _split(text, what)
    unit = unit or "m/s"
    length, sep, per = unit.partition("/")
    if not sep or per != "s" or length not in _LENGTH_UNITS:
        raise InputError(
            f"cannot read {what} {text!r}: unknown unit {unit!r} (use m/s, mm/s, cm/s, in/s …)"
        )
    return value * _LENGTH_UNITS[length]


def parse_accel(text: str | float, what: str = "acceleration") -> float:
    """Parse an acceleration: ``0.322`` (m/s²) or ``0.0528g`` (multiples of g) into m/s²."""
    if isinstance(text, int | float):
        return float(text)
    value, unit = _split(text, what)
    if unit in ("", "m/s2", "m/s²"):
        return value
    if unit == "g":
        return value * G
    raise InputError(f"cannot read {what} {text!r}: use m/s² (plain number) or a 'g' suffix")


def parse_fraction(text: str | float, what: str = "fraction") -> float:
    """Parse ``1%`` or ``0.01`` into a fraction (0.01)."""
    if isinstance(text, int | float):
        return float(text)
    value, unit = _split(text, what)
    if unit == "%":
        return value / 100.0
    if unit == "":
        return value
    raise InputError(f"cannot read {what} {text!r}: use a fraction (0.01) or a percentage (1%)")


def parse_window(text: str | float, fn: float | None = None) -> float:
    """Parse a window length: ``3s``, ``3000ms`` or ``3T`` (3 natural periods, needs ``fn``)."""
    if isinstance(text, int | float):
        return float(text)
    value, unit = _split(text, "window")
    if unit == "T":
        if fn is None or fn <= 0:
            raise InputError(f"window {text!r} is in natural periods: give --fn (Hz, > 0)")
        return value / fn
    return parse_time(text, "window")


def parse_range(text: str, what: str = "range", max_points: int = 1000) -> list[float]:
    """Parse ``start:stop:step`` (stop exclusive, like numpy.arange) or ``a,b,c`` into a list.

    More than ``max_points`` values (each one a trial run where ranges are used) is refused
    before the list is built.
    """
    s = str(text).strip()
    try:
        if ":" in s:
            parts = [float(p) for p in s.split(":")]
            if len(parts) != 3 or parts[2] <= 0 or not all(math.isfinite(p) for p in parts):
                raise ValueError
            start, stop, step = parts
            count = (stop - start) / step
            if not (math.isfinite(count) and count <= max_points):
                raise InputError(
                    f"{what} {text!r}: {count:.3g} values, more than {max_points} (each value "
                    "is a run)"
                )
            n = round(count)
            vals = [round(start + i * step, 12) for i in range(max(n, 0))]
            if not vals:
                raise ValueError
            return vals
        return [float(p) for p in s.split(",") if p.strip()]
    except InputError:
        raise
    except ValueError:
        raise InputError(f"cannot read {what} {text!r}: use start:stop:step or a,b,c") from None


def positive_number(value: Any, what: str, allow_zero: bool = False) -> float:
    """``value`` as a finite float > 0 (≥ 0 with ``allow_zero``), or an input error.

    The :class:`~rths_hil.errors.InputError` is one line naming ``what``.

    The one check of a positive number in the package (limits, tolerances, steps, rates).
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and (v > 0 or (allow_zero and v == 0))):
        bound = "≥ 0" if allow_zero else "> 0"
        raise InputError(f"{what} must be a finite number {bound}, got {value!r}")
    return v

"""Coercion of one configuration value to its key's type, unit and range, and of one table
to its declared keys (:func:`check_table`: the validator of the run configuration, controller
profiles and twin model files).

Numbers with units are read by :mod:`rths_hil.units` (same number syntax); a value that fails
raises :class:`~rths_hil.errors.InputError` naming the key path.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from ..errors import InputError
from ..keys import REQUIRED, Key
from ..units import (
    NUMBER,
    parse_accel,
    parse_force,
    parse_fraction,
    parse_length,
    parse_time,
    parse_velocity,
    parse_window,
)

__all__ = ["check_range", "check_table", "coerce", "describe", "quantity", "unknown_key"]

_NUM_RE = re.compile(rf"\s*({NUMBER})\s*(\S*)\s*")
_PREFIX = {"": 1.0, "k": 1e3, "M": 1e6}
#: The reader of a quantity in each unit that :mod:`rths_hil.units` reads.
_PARSERS: dict[str, Callable[[str, str], float]] = {
    "s": parse_time,
    "m": parse_length,
    "N": parse_force,
    "m/s": parse_velocity,
    "m/s²": parse_accel,
    "-": parse_fraction,
}


def describe(v: Any) -> str:
    """A value as a message shows it (strings quoted and cut to one line, TOML words)."""
    if isinstance(v, str):
        if len(v) > 60:  # a message stays one readable line
            return f"{v[:40]!r}… ({len(v)} characters)"
        return repr(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, list):
        return "an array"
    return repr(v)


def quantity(value: Any, unit: str, path: str) -> float:
    """Read a float in ``unit`` from a number or a string with a unit."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        what = "a number" if unit in ("", "-") else f"a number in {unit}"
        raise InputError(f"{path}: expected {what}, got {describe(value)}")
    if isinstance(value, int | float):
        return float(value)
    parse = _PARSERS.get(unit)
    if parse is not None:
        try:
            return parse(value, "value")
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
    m = _NUM_RE.fullmatch(value)
    if m:
        num, u = float(m.group(1)), m.group(2)
        if u in ("", unit):
            return num
        for p, f in _PREFIX.items():
            if p and u == p + unit:
                return num * f
    raise InputError(f"{path}: cannot read {value!r} as a quantity in {unit}")


def _bare(value: Any) -> bool:
    """A number given without a unit (``25`` or ``"25"``)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return True
    m = _NUM_RE.fullmatch(value) if isinstance(value, str) else None
    return m is not None and not m.group(2)


def check_range(key: Key, v: float, path: str) -> None:
    """Raise unless ``v`` is finite and within ``key``'s range (``path`` names the key)."""
    if not math.isfinite(v):
        raise InputError(f"{path}: must be a finite number, got {v!r}")
    unit = "" if key.unit in ("-", "steps", "windows") else f" {key.unit}"
    if key.lo is not None and (v < key.lo or (key.lo_open and v == key.lo)):
        op = ">" if key.lo_open else "≥"
        raise InputError(f"{path}: must be {op} {key.lo:g}{unit}, got {v:g}")
    if key.hi is not None and (v > key.hi or (key.hi_open and v == key.hi)):
        op = "<" if key.hi_open else "≤"
        raise InputError(f"{path}: must be {op} {key.hi:g}{unit}, got {v:g}")


def coerce(key: Key, value: Any, path: str) -> Any:
    """``value`` as ``key`` takes it: type checked, units read to SI, range checked.

    Parameters
    ----------
    key : Key
        The schema entry (:data:`rths_hil.config.SCHEMA`).
    value : Any
        As read from TOML or ``--set``.
    path : str
        Key path for messages (``loop.fs``, ``actuators[0].fei.window``).

    Returns
    -------
    Any
        The value in SI units (a float, int, bool, str, list of floats or a copied table; an
        ``"nT"`` window stays a string until ``structure.fn`` resolves it).

    Raises
    ------
    InputError
        Wrong type, unit or range, naming ``path``.
    """
    return _KINDS[key.kind](key, value, path)


def _int(key: Key, value: Any, path: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"{path}: expected an integer, got {describe(value)}")
    check_range(key, value, path)
    return int(value)


def _bool(key: Key, value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise InputError(f"{path}: expected true or false, got {describe(value)}")
    return value


def _str(key: Key, value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise InputError(f"{path}: expected a string, got {describe(value)}")
    return value


def _str_or_int(key: Key, value: Any, path: str) -> str | int:
    """A name or a number (a CAN channel, an object index): either, as given."""
    if isinstance(value, bool) or not isinstance(value, str | int):
        raise InputError(f"{path}: expected a string or an integer, got {describe(value)}")
    return value


def _choice(key: Key, value: Any, path: str) -> str:
    if not isinstance(value, str) or value not in key.choices:
        raise InputError(f"{path}: must be one of {', '.join(key.choices)}, got {describe(value)}")
    return value


def _table(key: Key, value: Any, path: str) -> dict[str, Any]:
    """A table checked by its consumer (a copy)."""
    if not isinstance(value, dict):
        raise InputError(f"{path}: expected a table, got {describe(value)}")
    return copy.deepcopy(value)


def _tables(key: Key, value: Any, path: str) -> list[dict[str, Any]]:
    """An array of tables, each checked by its consumer (a copy)."""
    if not isinstance(value, list):
        raise InputError(f"{path}: expected an array of tables, got {describe(value)}")
    return [_table(key, item, f"{path}[{i}]") for i, item in enumerate(value)]


def _float(key: Key, value: Any, path: str) -> float:
    """A number in the key's unit (SI), range checked."""
    v = quantity(value, key.unit, path)
    try:
        check_range(key, v, path)
    except InputError as exc:
        if key.unit == "s" and key.hi is not None and v > key.hi and _bare(value):
            raise InputError(
                f'{exc} (a bare number is in seconds: write e.g. "{value} ms" for milliseconds)'
            ) from None
        raise
    return v


def _window(key: Key, value: Any, path: str) -> float | str:
    """A window: a duration (s) or a number of periods ``"nT"`` (kept as text)."""
    if isinstance(value, str) and value.strip().endswith("T"):
        try:
            parse_window(value, 1.0)  # syntax check; resolved with structure.fn later
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
        return value.strip()
    v = quantity(value, "s", path)
    check_range(key, v, path)
    return v


def _array(key: Key, value: Any, path: str) -> list[float]:
    """An array of numbers in the key's unit (SI), each range checked."""
    if not isinstance(value, list):
        raise InputError(f"{path}: expected an array of numbers, got {describe(value)}")
    out = []
    for i, item in enumerate(value):
        v = quantity(item, key.unit, f"{path}[{i}]")
        check_range(key, v, f"{path}[{i}]")
        out.append(v)
    return out


def _schedule(key: Key, value: Any, path: str) -> list[list[float]]:
    """``[[t, v], …]``: times in s from 0, non-decreasing; values in the key's second unit."""
    unit = key.unit.split(",")[-1].strip()
    if not isinstance(value, list):
        raise InputError(f"{path}: expected an array of [time, value] pairs, got {describe(value)}")
    out: list[list[float]] = []
    for i, pair in enumerate(value):
        where = f"{path}[{i}]"
        if not isinstance(pair, list) or len(pair) != 2:
            raise InputError(f"{where}: expected a pair [time, value], got {describe(pair)}")
        t = quantity(pair[0], "s", f"{where}[0]")
        v = quantity(pair[1], unit, f"{where}[1]")
        if not math.isfinite(t) or t < 0:
            raise InputError(f"{where}[0]: the time must be a finite number ≥ 0 s, got {t!r}")
        if not math.isfinite(v):
            raise InputError(f"{where}[1]: must be a finite number, got {v!r}")
        if out and t < out[-1][0]:
            raise InputError(
                f"{where}[0]: the times must not decrease ({t:g} s after {out[-1][0]:g} s)"
            )
        out.append([t, v])
    return out


#: The reader of each :attr:`Key.kind`.
_KINDS: dict[str, Callable[[Key, Any, str], Any]] = {
    "float": _float,
    "int": _int,
    "bool": _bool,
    "str": _str,
    "str|int": _str_or_int,
    "choice": _choice,
    "window": _window,
    "array": _array,
    "schedule": _schedule,
    "table": _table,
    "tables": _tables,
}


def unknown_key(path: str, name: str, known: Iterable[str]) -> InputError:
    """The error for an unknown key ``name`` at ``path``: the closest known key, then all."""
    known = list(known)
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.5)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return InputError(f"{path}: unknown key{hint}; known keys: {', '.join(known)}")


def check_table(
    table: Any,
    keys: Mapping[str, Key],
    where: str = "",
    path: str = "",
    *,
    defaults: bool = True,
    missing: str = "missing",
) -> dict[str, Any]:
    """``table`` checked against its declared ``keys``: the one validator of configuration
    sections, profile tables and model-file tables.

    Parameters
    ----------
    table : Any
        As read from TOML (a table is a dict).
    keys : mapping of str to Key
        The keys the table may hold; a key whose default is :data:`~rths_hil.config.REQUIRED`
        must be given.
    where : str
        The source, first in every message (``run.toml``, ``profile lab.toml``); empty for none.
    path : str
        The table's key path (``loop``, ``roles.setpoint``, ``actuator.effects[0]``); empty
        for a document's top level.
    defaults : bool
        Fill the keys not given with their defaults (``False``: only the keys given, for a
        source merged over others).
    missing : str
        What a message says of a required key not given (``"required by model 'servo_lag'"``),
        followed by the key's doc and unit.

    Returns
    -------
    dict
        Each key given, coerced to its type and SI unit and range checked (:func:`coerce`), in
        the table's order; then, with ``defaults``, the others with their defaults (copied).

    Raises
    ------
    InputError
        One line ``where: path.key: what is wrong``: not a table, an unknown key (with the
        closest known one), a wrong type, unit or range, a required key not given.
    """
    pre = f"{where}: " if where else ""
    if not isinstance(table, Mapping):
        raise InputError(f"{pre}{path or 'document'}: expected a table, got {describe(table)}")
    out: dict[str, Any] = {}
    for name, value in table.items():
        kp = f"{path}.{name}" if path else str(name)
        if name not in keys:
            raise InputError(f"{pre}{unknown_key(kp, str(name), keys)}")
        try:
            out[name] = coerce(keys[name], value, kp)
        except InputError as exc:
            raise InputError(f"{pre}{exc}") from None
    for name, key in keys.items():
        if name in out:
            continue
        if key.default is REQUIRED:
            what = ", ".join(w for w in (key.doc, "" if key.unit == "-" else key.unit) if w)
            raise InputError(
                f"{pre}{f'{path}.{name}' if path else name}: {missing}"
                + (f" ({what})" if what else "")
            )
        if defaults:
            out[name] = copy.deepcopy(key.default)
    return out

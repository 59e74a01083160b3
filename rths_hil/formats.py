"""The text formats' shared readers and writers: TOML files and JSON-safe values.

* :func:`read_toml` — a configuration, model file or controller profile read with
  :mod:`tomllib`: one regular file, bounded in size, UTF-8, and one
  :class:`~rths_hil.errors.InputError` line naming the file for anything wrong.
* :func:`toml_value`, :func:`toml_key` — one value or key as TOML text, written by ``tomli_w``
  (strings with newlines, quotes or control characters escaped as TOML requires), numpy scalars
  as their Python value, tables inline. The NaN rule: TOML has ``nan`` and ``inf``, so a
  non-finite float is written as such and reads back unchanged.
* :func:`json_safe` — a JSON-safe copy of a value (numpy scalars and arrays as Python values,
  paths as strings). JSON has no NaN: a non-finite float becomes ``null`` (``nonfinite="null"``,
  a value that is absent: summaries, reports) or its name ``"nan"``, ``"inf"``, ``"-inf"``
  (``nonfinite="name"``, a value that was read as such: events and run metadata).
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import tomli_w

from .errors import InputError, check_regular_file

__all__ = ["json_safe", "json_text", "read_toml", "toml_key", "toml_value"]

#: Largest TOML file read whole into memory (bytes).
MAX_TOML_BYTES = 1 << 20


def read_toml(
    path: str | Path, what: str, label: str | None = None, max_bytes: int = MAX_TOML_BYTES
) -> dict[str, Any]:
    """The tables of TOML file ``path``.

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file is, for messages (``"config"``, ``"model file"``, ``"profile"``).
    label : str, optional
        How messages name the file (default: ``path``).
    max_bytes : int
        Largest file accepted.

    Raises
    ------
    InputError
        Not a regular file, too large, unreadable, not UTF-8, or invalid TOML; one line that
        starts with ``label``.
    """
    name = str(path) if label is None else label
    check_regular_file(path, f"a {what}", max_bytes=max_bytes)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{name}: cannot read {what} ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputError(f"{name}: not a UTF-8 text file") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{name}: invalid TOML (TOML syntax error): {exc}") from None


def toml_key(key: str) -> str:
    """``key`` as a TOML key: bare when it may be, else quoted by ``tomli_w``."""
    return tomli_w.dumps({key: 0}).rstrip("\n").rsplit(" = ", 1)[0]


def toml_value(value: Any) -> str:
    """One value as TOML text (tables inline, as a one-key-a-line layout needs).

    Raises
    ------
    TypeError
        A value TOML cannot hold (``None``, an object).
    """
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, Mapping):
        return (
            "{" + ", ".join(f"{toml_key(str(k))} = {toml_value(x)}" for k, x in value.items()) + "}"
        )
    if isinstance(value, list | tuple | np.ndarray):
        return "[" + ", ".join(toml_value(x) for x in value) + "]"
    if isinstance(value, float):
        value = float(value)  # a float subclass is written as its value
    text = tomli_w.dumps({"v": value})  # 'v = <value>\n'
    return text[len("v = ") :].rstrip("\n")


def json_safe(value: Any, nonfinite: Literal["null", "name"] = "null") -> Any:
    """A copy of ``value`` that :func:`json.dumps` writes with ``allow_nan=False``.

    Dicts (keys as strings), lists, tuples and arrays recursively; numpy scalars as Python
    values; paths as strings; a non-finite float as ``None`` (``nonfinite="null"``) or as
    ``"nan"``, ``"inf"``, ``"-inf"`` (``nonfinite="name"``). Other values are returned as they
    are (``json.dumps`` decides).
    """
    if isinstance(value, Mapping):
        return {str(k): json_safe(v, nonfinite) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v, nonfinite) for v in value]
    if isinstance(value, np.ndarray):
        return [json_safe(v, nonfinite) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        v = float(value)
        if math.isfinite(v):
            return v
        return None if nonfinite == "null" else repr(v)
    if isinstance(value, Path):
        return str(value)
    return value


def json_text(
    value: Any, nonfinite: Literal["null", "name"] = "null", indent: int | None = 2
) -> str:
    """``value`` as JSON text ending in a newline (:func:`json_safe` first; strict JSON)."""
    return json.dumps(json_safe(value, nonfinite), indent=indent, allow_nan=False) + "\n"

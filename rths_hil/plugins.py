"""Plug-ins: the one reader of entry points and ``"module:attr"`` targets.

Drivers (``rths_hil.drivers``), twins (``rths_hil.twins``) and compensators
(``rths_hil.compensators``) are found the same way: the built-in table of each registry, then
the entry points other installed distributions declare in that group (one of the same name
replaces the built-in). Scanning the installed distributions costs tens of milliseconds and a
run asks about ten times, so the scan is done once per ``sys.path`` (a distribution installed
while the process runs, on an unchanged path, is seen by the next process).
"""

from __future__ import annotations

import functools
import importlib
import sys
from collections.abc import Mapping
from importlib.metadata import distributions
from typing import Any

from .errors import InputError

__all__ = ["load_target", "targets"]


@functools.lru_cache(maxsize=8)
def _scan(path: tuple[str, ...]) -> dict[str, dict[str, str]]:
    """Every entry point of the distributions on ``path``: group → {name: target}."""
    groups: dict[str, dict[str, str]] = {}
    seen: set[str] = set()
    for dist in distributions():  # as importlib.metadata.entry_points: the first of a name
        name = (dist.metadata["Name"] or "").lower().replace("-", "_")
        if name in seen:
            continue
        seen.add(name)
        for ep in dist.entry_points:
            groups.setdefault(ep.group, {})[ep.name] = ep.value
    return groups


def targets(group: str, builtin: Mapping[str, str]) -> dict[str, str]:
    """Every known name of a plug-in ``group`` → its ``module:attr`` target.

    Parameters
    ----------
    group : str
        The entry-point group (e.g. ``"rths_hil.drivers"``).
    builtin : Mapping[str, str]
        The registry's own table; an entry point of the same name replaces its target.
    """
    found = dict(builtin)
    found.update(_scan(tuple(sys.path)).get(group, {}))
    return found


def load_target(target: str, base: type | None = None, what: str = "plug-in") -> Any:
    """Import ``module:attr`` and return the object.

    Parameters
    ----------
    target : str
        ``"package.module:Name"``.
    base : type, optional
        When given, the object must be a subclass of it.
    what : str
        What the target is, for the message (``"driver entry point"``).

    Raises
    ------
    InputError
        The module or attribute cannot be imported, or the object is not a subclass of
        ``base`` (one line naming the target).
    """
    module, _, attr = target.partition(":")
    try:
        obj = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"{what} {target!r}: cannot load it ({exc})") from None
    if base is not None and not (isinstance(obj, type) and issubclass(obj, base)):
        raise InputError(
            f"{what} {target!r} is not a {base.__module__}.{base.__qualname__} subclass"
        )
    return obj

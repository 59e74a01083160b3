"""Reading a configuration: TOML files over the defaults, ``[[actuators]]`` entries and
``--set`` overrides."""

from __future__ import annotations

import copy
import re
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ..errors import InputError
from ..formats import read_toml
from ..keys import REQUIRED, Key
from .checks import cross_check
from .coerce import check_table, coerce, describe, unknown_key
from .model import Config, default_config
from .schema import (
    CHANNEL_KEYS,
    CHANNEL_SECTIONS,
    SCHEMA,
    STEP_KEYS,
    STEP_PAIR,
    derive_steps,
    steps_to_time,
)

__all__ = [
    "MAX_CONFIG_BYTES",
    "MAX_INCLUDE_DEPTH",
    "apply_overrides",
    "load_config",
    "merge",
    "parse_override",
]

_NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}\Z")


#: The keys of an ``[[actuators]]`` entry: its name, where it acts (a storey, or a row of the
#: transformation T: displacement = T·u) and the sections it overrides.
ENTRY_KEYS: dict[str, Key] = {
    "name": Key("str", REQUIRED),
    "dof": Key("int", None, lo=1, doc="the storey / DOF the actuator drives"),
    "transform": Key("array", None, doc="a row of T (displacement = T·u), instead of dof"),
    **{section: Key("table", None) for section in CHANNEL_SECTIONS},
}


def _actuator(entry: Any, i: int, where: str) -> dict[str, Any]:
    """Validate one ``[[actuators]]`` entry (its own keys, not the cross-channel rules)."""
    path = f"actuators[{i}]"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: {path}: expected a table [[actuators]], got {describe(entry)}")
    if isinstance(entry.get("control"), str):  # control = "load"
        entry = {**entry, "control": {"mode": entry["control"]}}
    missing = "every [[actuators]] entry needs a name"
    out = check_table(entry, ENTRY_KEYS, where, path, defaults=False, missing=missing)
    if not _NAME_RE.match(out["name"]):
        raise InputError(
            f"{where}: {path}.name: expected a name of 1 to 32 letters, digits and _ starting "
            f"with a letter, got {describe(out['name'])}"
        )
    if out.get("transform") == []:
        raise InputError(f"{where}: {path}.transform: expected a non-empty array (a row of T)")
    for section in CHANNEL_SECTIONS:
        if section in out:
            keys = SCHEMA[section]
            out[section] = check_table(
                out[section], keys, where, f"{path}.{section}", defaults=False
            )
    if "dof" in out and "transform" in out:
        raise InputError(f"{where}: {path}.transform: give dof or transform, not both")
    return out


def merge(cfg: Config, data: Mapping[str, Any], where: str) -> None:
    """Merge ``data`` (a parsed TOML document) into ``cfg`` key by key, coercing each value.

    The step keys of this source (``compensation.alpha``, …) are read at this source's
    ``loop.fs``. ``where`` names the source in messages. Cross-key rules are not checked here
    (:func:`rths_hil.config.cross_check`).
    """
    for section, table in data.items():
        if section == "actuators":
            if not isinstance(table, list):
                raise InputError(
                    f"{where}: actuators: expected an array of tables [[actuators]], "
                    f"got {describe(table)}"
                )
            cfg["actuators"] = [_actuator(e, i, where) for i, e in enumerate(table)]
            continue
        if section not in SCHEMA:
            raise InputError(f"{where}: {unknown_key(section, section, SCHEMA)}")
        if section == "control" and isinstance(table, str):  # control = "force"
            table = {"mode": table}
        if not isinstance(table, dict):
            raise InputError(
                f"{where}: {section}: expected a table [{section}], got {describe(table)}"
            )
        cfg[section].update(check_table(table, SCHEMA[section], where, section, defaults=False))
    # α and the other step keys of this source are read at this source's loop rate
    fs = cfg["loop"]["fs"]
    comp = data.get("compensation")
    if isinstance(comp, dict):
        steps_to_time(cfg["compensation"], {k: cfg["compensation"][k] for k in comp}, fs, where)
    for entry in cfg.get("actuators") or []:
        own = entry.get("compensation")
        if own:
            steps_to_time(own, own, fs, f"{where}: actuators.{entry['name']}")
            for sk in STEP_KEYS:
                own.pop(sk, None)


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``section.key=value`` into the key path and the value (TOML, else a string).

    Raises
    ------
    InputError
        No ``=`` or an empty key.
    """
    name, sep, raw = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise InputError(f"--set {text}: expected section.key=value")
    parts = name.split(".")
    if parts == ["control"] or (
        len(parts) == 3 and parts[0] == "actuators" and parts[2] == "control"
    ):
        parts.append("mode")  # --set control=force is control.mode
    if any(not p for p in parts) or len(parts) < 2:
        raise InputError(f"--set {text}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return parts, value


def _apply_channel_override(cfg: Config, parts: list[str], value: Any, where: str) -> None:
    """``--set actuators.NAME.key=value`` or ``--set actuators.NAME.section.key=value``."""
    chans = cfg.get("actuators") or []
    names = [c["name"] for c in chans]
    if len(parts) < 3:
        raise InputError(f"{where}: expected actuators.NAME.key=value")
    name = parts[1]
    if name not in names:
        known = ", ".join(names) if names else "none: the configuration has no [[actuators]]"
        raise InputError(f"{where}: actuators.{name}: no channel of that name (channels: {known})")
    i = names.index(name)
    entry = dict(chans[i])
    key = parts[2]
    if key in ("dof", "transform"):
        if len(parts) != 3:
            raise InputError(f"{where}: actuators.{name}.{key} is not a table")
        entry[key] = value
        entry.pop("transform" if key == "dof" else "dof", None)
    elif key in CHANNEL_SECTIONS:
        if len(parts) < 4:
            raise InputError(f"{where}: expected actuators.{name}.{key}.KEY=value")
        sec = copy.deepcopy(entry.get(key, {}))
        kname = parts[3]
        if kname not in SCHEMA[key]:
            raise InputError(
                f"{where}: {unknown_key(f'actuators.{name}.{key}.{kname}', kname, SCHEMA[key])}"
            )
        if len(parts) > 4:
            if SCHEMA[key][kname].kind != "table":
                raise InputError(f"{where}: actuators.{name}.{key}.{kname} is not a table")
            node = sec.setdefault(kname, copy.deepcopy(cfg[key][kname]))
            for p in parts[4:-1]:
                node = node.setdefault(p, {})
                if not isinstance(node, dict):
                    raise InputError(f"{where}: {'.'.join(parts[:-1])} is not a table")
            node[parts[-1]] = value
        else:
            sec[kname] = value
        entry[key] = sec
    else:
        allowed = (*CHANNEL_KEYS[1:], *CHANNEL_SECTIONS)
        raise InputError(f"{where}: {unknown_key(f'actuators.{name}.{key}', key, allowed)}")
    chans[i] = _actuator(entry, i, where)


def _apply_override(cfg: Config, text: str, where: str | None = None) -> None:
    parts, value = parse_override(text)
    where = where or f"--set {text}"
    section, name = parts[0], parts[1]
    if section == "actuators":
        _apply_channel_override(cfg, parts, value, where)
        return
    if section in CHANNEL_SECTIONS and len(parts) == 2:
        # a top-level --set applies to every channel: the channels' own values give way
        # (driver.connection is merged key by key: the channels keep their node / unit id)
        if (section, name) != ("driver", "connection"):
            names = [name]
            if section == "compensation" and name in STEP_PAIR:
                names = [STEP_PAIR[name], STEP_KEYS[STEP_PAIR[name]][0]]  # α and delay alike
            for entry in cfg.get("actuators") or []:
                for n in names:
                    entry.get(section, {}).pop(n, None)
    if section not in SCHEMA:
        raise InputError(f"{where}: {unknown_key(section, section, SCHEMA)}")
    keys = SCHEMA[section]
    if name not in keys:
        raise InputError(f"{where}: {unknown_key(section + '.' + name, name, keys)}")
    key = keys[name]
    cfg.origins[f"{section}.{name}"] = where
    if len(parts) > 2:
        if key.kind != "table":
            raise InputError(f"{where}: {section}.{name} is not a table")
        node = cfg[section][name]
        for p in parts[2:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise InputError(f"{where}: {'.'.join(parts[:-1])} is not a table")
        node[parts[-1]] = value
        return
    try:
        cfg[section][name] = coerce(key, value, f"{section}.{name}")
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


#: Largest configuration file read (bytes): a real one is a few kB.
MAX_CONFIG_BYTES = 1 << 20
#: Deepest chain of ``include`` (a file that includes one that includes one …).
MAX_INCLUDE_DEPTH = 8


def _resolved(path: Path, where: str) -> Path:
    try:
        return path.resolve(strict=False)
    except (OSError, RuntimeError) as exc:  # a symlink loop
        raise InputError(f"{where}: cannot resolve the path ({exc})") from None


def _sources(
    path: Path, label: str, chain: tuple[Path, ...]
) -> list[tuple[dict[str, Any], str, bool]]:
    """The TOML documents to merge for ``path``, in order: everything its ``include`` names
    (recursively, each before its includer's own keys), then its own; each with its label and
    whether it is the top file."""
    data = read_toml(path, "config", label, max_bytes=MAX_CONFIG_BYTES)
    me = _resolved(path, label)
    inc = data.pop("include", [])
    if isinstance(inc, str):
        inc = [inc]
    if not isinstance(inc, list) or not all(isinstance(i, str) and i.strip() for i in inc):
        raise InputError(
            f"{label}: include: expected an array of file paths (strings), got {describe(inc)}"
        )
    out: list[tuple[dict[str, Any], str, bool]] = []
    for raw in inc:
        p = Path(raw).expanduser()
        if not p.is_absolute():
            p = path.parent / p
        where = f"{label}: include {raw!r}"
        target = _resolved(p, where)
        if target == me or target in chain:
            names = " → ".join(c.name for c in (*chain, me, target))
            raise InputError(f"{where}: an include cycle ({names})")
        if len(chain) + 1 >= MAX_INCLUDE_DEPTH:
            raise InputError(f"{where}: includes nested deeper than {MAX_INCLUDE_DEPTH} files")
        if not p.exists() and not p.is_symlink():
            raise InputError(f"{where}: no such file ({p})")
        try:
            sub = _sources(p, f"{where} ({p})", (*chain, me))
        except InputError as exc:  # name the include in every message about its file
            if str(exc).startswith(where):
                raise
            raise InputError(f"{where}: {exc}") from None
        out += [(d, w, False) for d, w, _ in sub]
    out.append((data, label, not chain))
    return out


def _merge_channels(cfg: Config, data: dict[str, Any], where: str) -> dict[str, Any]:
    """A source's ``[[actuators]]`` over those an earlier source (an include) gave: entries of
    the same name merged section by section, this source's keys winning. Returns ``data``
    without its actuators when they were merged here."""
    before = cfg.get("actuators") or []
    own = data.get("actuators")
    if not before or not isinstance(own, list):
        return data
    entries = [_actuator(e, i, where) for i, e in enumerate(own)]
    names = {e["name"] for e in entries}
    for e in before:
        if e["name"] not in names:
            raise InputError(
                f"{where}: actuators: an included file sets channel {e['name']!r}, "
                "which this file's [[actuators]] does not have"
            )
    old = {e["name"]: e for e in before}
    merged = []
    for e in entries:
        base = copy.deepcopy(old.get(e["name"], {}))
        for key, value in e.items():
            if key in CHANNEL_SECTIONS and isinstance(base.get(key), dict):
                base[key].update(value)
            else:
                base[key] = value
        if "dof" in e:
            base.pop("transform", None)
        elif "transform" in e:
            base.pop("dof", None)
        merged.append(base)
    cfg["actuators"] = merged
    return {k: v for k, v in data.items() if k != "actuators"}


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> Config:
    """Read a configuration file over the defaults, then apply ``--set`` overrides.

    A top-level ``include = ["a.toml", …]`` (paths relative to the including file) merges
    those files first, in order, then the file's own keys over them (``docs/config.md``);
    an included file may include others. Channels (``[[actuators]]``) of the same name are
    merged section by section.

    Parameters
    ----------
    path : str or Path, optional
        TOML file. ``None`` gives the embedded default.
    overrides : iterable of str
        ``section.key=value`` items, applied in order.

    Returns
    -------
    Config
        The defaults, then the file (after what it includes), then the overrides, every rule
        relating keys checked (:func:`rths_hil.config.cross_check`).

    Raises
    ------
    InputError
        Unreadable file, TOML syntax error, unknown key, wrong type, unit or range — naming
        the file (or ``--set`` item) and the key path; a missing included file or an include
        cycle.
    """
    cfg = default_config()
    if path is not None:
        p = Path(path)
        sources = _sources(p, str(path), ())
        cfg.source = str(path)
        cfg.base_dir = _resolved(p, str(path)).parent
        for data, where, _ in sources:
            merge(cfg, _merge_channels(cfg, data, where), where)
    else:
        cfg.base_dir = Path.cwd()
    return apply_overrides(cfg, overrides)


def apply_overrides(cfg: Config, overrides: Iterable[str], where: str | None = None) -> Config:
    """Apply ``section.key=value`` items to ``cfg`` in place as ``--set`` does (α read at the
    final loop rate), then cross-check; ``where`` labels errors (default ``--set ITEM``)."""
    overrides = list(overrides)
    # (channel name or None, step key) → the key of the pair the last --set gave
    last: dict[tuple[str | None, str], str] = {}
    for item in overrides:
        _apply_override(cfg, item, where)
        parts = parse_override(item)[0]
        if parts[0] == "compensation" and len(parts) == 2 and parts[1] in STEP_PAIR:
            sk = STEP_PAIR[parts[1]]
            last = {k: v for k, v in last.items() if k[1] != sk}  # the channels' gave way
            last[(None, sk)] = parts[1]
        elif parts[0] == "actuators" and len(parts) == 4 and parts[2] == "compensation":
            if parts[3] in STEP_PAIR:
                last[(parts[1], STEP_PAIR[parts[3]])] = parts[3]
    # a --set α is read at the final loop rate; the time keys carry over a change of rate
    fs = cfg["loop"]["fs"]
    for (chan, sk), key in last.items():
        tk, off = STEP_KEYS[sk]
        if chan is None:
            sec = cfg["compensation"]
        else:
            sec = next(e for e in cfg["actuators"] if e["name"] == chan)["compensation"]
        if key == sk:
            sec[tk] = (sec[sk] - off) / fs
        if chan is not None:
            sec.pop(sk, None)
    derive_steps(cfg["compensation"], fs)
    cross_check(cfg, " (with --set overrides)" if overrides else "")
    return cfg

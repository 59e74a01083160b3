"""The resolved configuration: :class:`Config` and its channels."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..units import parse_window
from .schema import (
    CHANNEL_SECTIONS,
    SCHEMA,
    STEP_KEYS,
    check_compensation_units,
    derive_steps,
    steps_to_time,
)

__all__ = [
    "ChannelConfig",
    "Config",
    "default_config",
    "resolve_channel",
]


class Config(dict):
    """A resolved configuration: ``cfg["loop"]["fs"]``, all values in SI units.

    Attributes
    ----------
    source : str
        Where it came from (a file path or ``<embedded default>``).
    origins : dict of str to str
        The keys (``section.name``) a ``--set`` item (or a caller's ``where``) set last, each
        with that item: what :meth:`where` names instead of :attr:`source`.
    base_dir : Path
        Directory relative paths in the configuration are resolved against.
    """

    source: str = "<embedded default>"
    base_dir: Path = Path(".")

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.origins: dict[str, str] = {}

    def where(self, key: str) -> str:
        """Where ``key`` (``section.name``) was last set: its ``--set`` item, else the source
        (an error about its value names what the user wrote)."""
        return self.origins.get(key, self.source)

    @property
    def window_s(self) -> float:
        """The FEI window in seconds (natural periods resolved with ``structure.fn``)."""
        w = self["fei"]["window"]
        return parse_window(w, self["structure"]["fn"]) if isinstance(w, str) else float(w)

    def resolve_path(self, text: str) -> Path:
        """A path from the configuration, relative to the config file's directory."""
        p = Path(text).expanduser()
        return p if p.is_absolute() else self.base_dir / p

    def as_dict(self) -> dict:
        """A plain nested dict (JSON-ready)."""
        return copy.deepcopy(dict(self))

    def channels(self) -> list[ChannelConfig]:
        """The test's channels, each with its sections resolved (see :func:`resolve_channel`).

        No ``[[actuators]]`` entry: one unnamed channel on DOF 1 with the top-level sections
        (the single-actuator test).
        """
        entries = self.get("actuators") or [{"name": ""}]
        return [resolve_channel(self, e) for e in entries]


@dataclass
class ChannelConfig:
    """One channel (``[[actuators]]`` entry) with its sections resolved.

    Attributes
    ----------
    name : str
        Channel name (``""`` for the implicit single channel).
    dof : int or None
        1-based degree of freedom the actuator acts on (``None`` when ``transform`` is given).
    transform : list of float or None
        Row of the transformation matrix: actuator displacement = T·u, force returned as Tᵀ·f.
    config : Config
        A full configuration whose channel sections (:data:`CHANNEL_SECTIONS`) are this
        channel's: the top-level values overridden by the channel's own.
    """

    name: str
    dof: int | None
    transform: list[float] | None
    config: Config


def resolve_channel(cfg: Config, entry: Mapping[str, Any]) -> ChannelConfig:
    """A channel's configuration: the top-level sections with the channel's keys over them.

    A key the channel sets replaces the top-level value (tables too: a channel's
    ``twin.actuator`` is its whole actuator model), except ``driver.connection``, which is
    merged key by key so that a channel can set only its ``node`` or ``device_id`` (a channel
    on another driver than the top-level one starts from an empty connection).
    """
    out = Config(copy.deepcopy({k: v for k, v in cfg.items() if k != "actuators"}))
    out.source, out.base_dir, out.origins = cfg.source, cfg.base_dir, dict(cfg.origins)
    own_driver = entry.get("driver", {}).get("name")
    if own_driver is not None and own_driver != cfg["driver"]["name"]:
        out["driver"]["connection"] = {}
    for section in CHANNEL_SECTIONS:
        for key, value in entry.get(section, {}).items():
            if section == "driver" and key == "connection":
                out[section][key] = {**out[section][key], **copy.deepcopy(value)}
            else:
                out[section][key] = copy.deepcopy(value)
    check_compensation_units(cfg)
    fs = out["loop"]["fs"]
    own = entry.get("compensation", {})
    steps_to_time(out["compensation"], {k: v for k, v in own.items() if k in STEP_KEYS}, fs, "")
    derive_steps(out["compensation"], fs)
    return ChannelConfig(
        name=entry.get("name", ""),
        dof=entry.get("dof"),
        transform=copy.deepcopy(entry.get("transform")),
        config=out,
    )


def default_config() -> Config:
    """The embedded default configuration (the FEI paper's NEES-711 setup, see module docstring)."""
    cfg = Config(
        {
            s: {k: copy.deepcopy(key.default) for k, key in keys.items()}
            for s, keys in SCHEMA.items()
        }
    )
    cfg["actuators"] = []
    return cfg

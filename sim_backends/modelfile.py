"""The twin model file (TOML): one format for ``twin serve``, ``simulate`` and ``twin calibrate``.

Format (all values SI; times and lengths may also be strings with units, ``"12ms"``, ``"0.2mm"``)::

    [actuator]
    delay = 0.012              # s, transport delay (the FEI paper, Fig. 4.1), default 0
    gain = 0.98                # amplitude gain, default 1
    model = "servo_lag"        # optional: "delay_gain" (default), "servo_lag", "benchmark"
    time_constant = 0.008      # the model's parameters, in the same table

    [[actuator.effects]]       # optional, applied in order after the model
    kind = "backlash"          # a catalogue name (rths_hil.sim_backends.effects.EFFECTS)
    width = 2e-4               # that effect's parameters

    [specimen]                 # optional; default: the benchmark's spring-dashpot
    model = "kelvin_voigt"     # optional, the only model
    stiffness = 1.19e6         # N/m
    damping = 114.6            # N·s/m
    mass = 0.0                 # kg

    [sensor]                   # optional; default: no noise, no quantisation
    displacement_noise = 1e-5  # m (std)
    force_noise = 2.0          # N (std)
    displacement_resolution = 1e-6   # m (quantisation step)
    force_resolution = 0.1     # N
    seed = 0

Unknown tables, keys, models or effect kinds raise :class:`~rths_hil.errors.InputError` naming
the file and the key path, e.g. ``twin.toml: actuator.effects[1].kind: unknown effect 'foo'
(known: offset, drift, …)`` (effects are numbered from 0 as in the file's order).

``force_feedback`` effects without ``specimen_stiffness``/``specimen_damping`` take them from
``[specimen]`` (or its defaults); the ``benchmark`` model takes ``specimen_stiffness``,
``specimen_damping`` and ``specimen_mass`` from the keys given in ``[specimen]`` unless set in
``[actuator]``, so one specimen loads the actuator and produces the measured force.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rths_hil.errors import InputError
from rths_hil.formats import read_toml, toml_key, toml_value
from rths_hil.units import parse_force, parse_length, parse_time, parse_velocity

from .effects import EFFECTS, FORCE_REFUSED, FORCE_UNITS, make_effect, validate_params
from .models import make_model
from .plant import Sensor, TwinPlant
from .registry import MODELS, model_entry
from .specimen import SPECIMEN_DEFAULTS, KelvinVoigt

__all__ = [
    "ActuatorSpec",
    "EffectSpec",
    "ModelSpec",
    "SpecimenSpec",
    "build_plant",
    "dump_model",
    "load_model",
    "load_plant",
    "model_to_toml",
]

_SENSOR_KEYS = ("displacement_noise", "force_noise", "displacement_resolution", "force_resolution")
_SPECIMEN_KEYS = ("stiffness", "damping", "mass")
_UNITS = {"delay": "s", "time_constant": "s"}


@dataclass
class EffectSpec:
    """One ``[[actuator.effects]]`` table: catalogue ``kind`` and its parameters (SI)."""

    kind: str
    params: dict[str, float] = field(default_factory=dict)


@dataclass
class ActuatorSpec:
    """The ``[actuator]`` table."""

    delay: float = 0.0
    gain: float = 1.0
    model: str = "delay_gain"
    params: dict[str, float] = field(default_factory=dict)
    effects: list[EffectSpec] = field(default_factory=list)


@dataclass
class SpecimenSpec:
    """The ``[specimen]`` table (Kelvin–Voigt)."""

    stiffness: float = SPECIMEN_DEFAULTS["stiffness"]
    damping: float = SPECIMEN_DEFAULTS["damping"]
    mass: float = SPECIMEN_DEFAULTS["mass"]
    model: str = "kelvin_voigt"


@dataclass
class ModelSpec:
    """A validated model file.

    Attributes
    ----------
    actuator : ActuatorSpec
    specimen : SpecimenSpec or None
        ``None`` when the file has no ``[specimen]`` table (the default specimen is used).
    sensor : Sensor
    source : str
        Where the spec came from (file name), used in messages.
    """

    actuator: ActuatorSpec = field(default_factory=ActuatorSpec)
    specimen: SpecimenSpec | None = None
    sensor: Sensor = field(default_factory=Sensor)
    source: str = "model"

    def build(self, dt: float) -> TwinPlant:
        """Build the :class:`~rths_hil.sim_backends.plant.TwinPlant` at step ``dt`` (s)."""
        a = self.actuator
        actuator = make_model(a.model, dt, delay=a.delay, gain=a.gain, **a.params)
        effects = [make_effect(e.kind, dt, **e.params) for e in a.effects]
        sp = self.specimen or SpecimenSpec()
        specimen = KelvinVoigt(sp.stiffness, sp.damping, dt, mass=sp.mass)
        return TwinPlant(actuator, effects, specimen, self.sensor)

    def to_dict(self) -> dict[str, Any]:
        """The spec as the nested dict a TOML file holds (SI numbers)."""
        a = self.actuator
        act: dict[str, Any] = {"delay": a.delay, "gain": a.gain}
        if a.model != "delay_gain":
            act["model"] = a.model
        act.update(a.params)
        if a.effects:
            act["effects"] = [{"kind": e.kind, **e.params} for e in a.effects]
        out: dict[str, Any] = {"actuator": act}
        if self.specimen is not None:
            s = self.specimen
            out["specimen"] = {"stiffness": s.stiffness, "damping": s.damping, "mass": s.mass}
        sensor = {k: getattr(self.sensor, k) for k in _SENSOR_KEYS}
        if any(sensor.values()) or self.sensor.seed:
            out["sensor"] = {**sensor, "seed": int(self.sensor.seed)}
        return out


def _number(value: Any, where: str, unit: str = "") -> float:
    """A finite float from a TOML value.

    With ``unit`` 's', 'm', 'N' or 'm/s' a string with units is read too (:mod:`rths_hil.units`).
    """
    parsers = {"s": parse_time, "m": parse_length, "N": parse_force, "m/s": parse_velocity}
    # "N/s" (a force twin's drift rate) is a number
    if isinstance(value, str) and unit in parsers:
        parse = parsers[unit]
        try:
            out = parse(value, "value")
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    elif isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"{where}: must be a number{f' in {unit}' if unit else ''}, got {value!r}")
    else:
        out = float(value)
    if not math.isfinite(out):
        raise InputError(f"{where}: must be finite, got {value!r}")
    return out


def _table(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise InputError(f"{where}: must be a table, got {type(value).__name__}")
    return value


def _unknown(table: Mapping[str, Any], known: Any, where: str) -> None:
    for key in table:
        if key not in known:
            raise InputError(f"{where}{key}: unknown key (known: {', '.join(known)})")


def _read_specimen(data: Mapping[str, Any], p: str) -> tuple[SpecimenSpec | None, dict[str, float]]:
    """The ``[specimen]`` table (None without one) and the keys it gives."""
    specimen = None
    specimen_given: dict[str, float] = {}
    if "specimen" in data:
        st = _table(data["specimen"], f"{p}specimen")
        _unknown(st, ("model", *_SPECIMEN_KEYS), f"{p}specimen.")
        model = st.get("model", "kelvin_voigt")
        if model not in ("kelvin_voigt", "spring_dashpot"):
            raise InputError(
                f"{p}specimen.model: unknown specimen model {model!r} (known: kelvin_voigt)"
            )
        for key in _SPECIMEN_KEYS:
            if key in st:
                v = _number(st[key], f"{p}specimen.{key}")
                if v < 0:
                    raise InputError(f"{p}specimen.{key}: must be ≥ 0, got {v!r}")
                specimen_given[key] = v
        values = {**SPECIMEN_DEFAULTS, **specimen_given}
        specimen = SpecimenSpec(
            stiffness=values["stiffness"], damping=values["damping"], mass=values["mass"]
        )
    return specimen, specimen_given


def _read_actuator(
    at: Mapping[str, Any], p: str, specimen_given: dict[str, float]
) -> tuple[str, float, float, dict[str, float]]:
    """The ``[actuator]`` table's model, delay (s), gain and parameters (checked by a build)."""
    model = at.get("model", "delay_gain")
    if not isinstance(model, str):
        raise InputError(
            f"{p}actuator.model: unknown actuator model {model!r} (known: {', '.join(MODELS)})"
        )
    try:
        model, entry = model_entry(model)
    except InputError as exc:
        raise InputError(f"{p}actuator.model: {exc}") from None
    model_params = entry.params
    _unknown(at, ("delay", "gain", "model", "effects", *model_params), f"{p}actuator.")
    delay = _number(at.get("delay", 0.0), f"{p}actuator.delay", "s")
    if delay < 0:
        raise InputError(f"{p}actuator.delay: must be ≥ 0 s, got {delay!r}")
    gain = _number(at.get("gain", 1.0), f"{p}actuator.gain")
    params: dict[str, float] = {}
    for key, (default, unit) in model_params.items():
        if key in at:
            params[key] = _number(at[key], f"{p}actuator.{key}", _UNITS.get(key, unit))
        elif default is None:
            raise InputError(f"{p}actuator.{key}: required by model {model!r}")
    if entry.uses_specimen:
        for key in _SPECIMEN_KEYS:
            if f"specimen_{key}" not in params and key in specimen_given:
                params[f"specimen_{key}"] = specimen_given[key]
    try:  # the model's own range checks (e.g. time_constant > 0, stable benchmark plant)
        make_model(model, 1.0 / 1024.0, delay=delay, gain=gain, **params)
    except InputError as exc:
        raise InputError(f"{p}actuator.{exc}") from None
    return model, delay, gain, params


def _read_effects(
    at: Mapping[str, Any], p: str, control: str, spec_values: dict[str, float]
) -> list[EffectSpec]:
    """The ``[[actuator.effects]]`` of a twin of ``control`` (force: its refusals, units)."""
    effects: list[EffectSpec] = []
    raw_effects = at.get("effects", [])
    if not isinstance(raw_effects, list):
        raise InputError(f"{p}actuator.effects: must be an array of tables [[actuator.effects]]")
    for i, raw in enumerate(raw_effects):
        where = f"{p}actuator.effects[{i}]."
        et = dict(_table(raw, where[:-1]))
        if "kind" not in et:
            raise InputError(f"{where}kind: missing (known: {', '.join(EFFECTS)})")
        kind = et.pop("kind")
        if not isinstance(kind, str) or kind not in EFFECTS:
            raise InputError(f"{where}kind: unknown effect {kind!r} (known: {', '.join(EFFECTS)})")
        if control == "force" and kind in FORCE_REFUSED:
            raise InputError(
                f"{where}kind: a force-controlled twin does not take {kind!r} "
                f"({FORCE_REFUSED[kind]})"
            )
        if kind == "force_feedback":
            et.setdefault("specimen_stiffness", spec_values["stiffness"])
            et.setdefault("specimen_damping", spec_values["damping"])
        units = {q.name: q.unit for q in EFFECTS[kind].PARAMS}
        if control == "force":
            units.update(FORCE_UNITS.get(kind, {}))
        values = {}
        for key, value in et.items():
            if key in units:
                values[key] = _number(value, f"{where}{key}", units[key])
            else:
                values[key] = value  # validate_params names the unknown key
        effects.append(EffectSpec(kind, validate_params(kind, values, where)))
    return effects


def _read_sensor(data: Mapping[str, Any], p: str) -> Sensor:
    """The ``[sensor]`` table (noise, resolution, seed; defaults without one)."""
    sensor = Sensor()
    if "sensor" in data:
        stab = _table(data["sensor"], f"{p}sensor")
        _unknown(stab, (*_SENSOR_KEYS, "seed"), f"{p}sensor.")
        kwargs: dict[str, Any] = {}
        for key in _SENSOR_KEYS:
            if key in stab:
                unit = "m" if key.startswith("displacement") else ""
                v = _number(stab[key], f"{p}sensor.{key}", unit)
                if v < 0:
                    raise InputError(f"{p}sensor.{key}: must be ≥ 0, got {v!r}")
                kwargs[key] = v
        if "seed" in stab:
            seed = stab["seed"]
            if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
                raise InputError(f"{p}sensor.seed: must be a non-negative integer, got {seed!r}")
            kwargs["seed"] = seed
        sensor = Sensor(**kwargs)
    return sensor


def load_model(
    source: str | Path | Mapping[str, Any], name: str | None = None, control: str = "displacement"
) -> ModelSpec:
    """Read and validate a model file (path) or an already-parsed dict.

    Parameters
    ----------
    source : str, Path or mapping
        A TOML file, or its content as a dict (e.g. a table of a larger configuration).
    name : str, optional
        Prefix of error messages (default: the file name; none for a dict, so that a caller
        can prefix its own key path, e.g. ``run.toml: twin.actuator.delay: …``).
    control : {"displacement", "force"}
        The twin the file is for. ``"force"`` (the force-controlled twin,
        :mod:`rths_hil.sim_backends.force`): effects it does not take are refused naming why,
        and ``offset`` and ``drift`` are read in N and N/s.

    Returns
    -------
    ModelSpec

    Raises
    ------
    InputError
        Unreadable file, invalid TOML, unknown or badly typed key, unknown model or effect,
        out-of-range value — the message names the file and the key path.
    """
    if isinstance(source, Mapping):
        data = source
    else:
        name = str(source) if name is None else name
        data = read_toml(source, "model file", name)
    p = f"{name}: " if name else ""
    _unknown(data, ("actuator", "specimen", "sensor"), p)
    if "actuator" not in data:
        raise InputError(f"{p}actuator: missing table [actuator]")

    specimen, specimen_given = _read_specimen(data, p)
    spec_values = {**SPECIMEN_DEFAULTS, **specimen_given}

    at = _table(data["actuator"], f"{p}actuator")
    model, delay, gain, params = _read_actuator(at, p, specimen_given)
    effects = _read_effects(at, p, control, spec_values)
    sensor = _read_sensor(data, p)

    actuator = ActuatorSpec(delay, gain, model, params, effects)
    return ModelSpec(actuator, specimen, sensor, name or "model")


def load_plant(source: str | Path | Mapping[str, Any] | ModelSpec, dt: float) -> TwinPlant:
    """Load a model file (or dict, or spec) and build its :class:`TwinPlant` at step ``dt``."""
    spec = source if isinstance(source, ModelSpec) else load_model(source)
    return spec.build(dt)


def build_plant(
    twin: Mapping[str, Any] | str | os.PathLike[str], dt: float, base_dir: str | None = None
) -> TwinPlant:
    """Build a twin's plant from a configuration's ``[twin]`` section (or a model file).

    Parameters
    ----------
    twin : mapping or str
        Either a path to a model file (TOML), or a mapping with the model file's tables:
        ``actuator`` (required: ``model``, ``delay``, ``gain``, the model's parameters,
        ``effects``), ``specimen`` and ``sensor`` (optional), or a ``[twin]`` section with a
        ``model`` key naming a model file (then the other tables are ignored). Empty tables
        count as absent.
    dt : float
        Step of the plant (s).
    base_dir : str, optional
        Directory a relative model-file path is resolved against.

    Returns
    -------
    rths_hil.sim_backends.plant.TwinPlant

    Raises
    ------
    InputError
        Unknown model or effect, a bad parameter, or an unreadable model file; the message
        names the key.
    """
    if isinstance(twin, str | os.PathLike):
        path = os.fspath(twin)
        if base_dir is not None and not os.path.isabs(path):
            path = os.path.join(base_dir, path)
        return load_plant(path, dt)
    model = twin.get("model")
    if isinstance(model, str) and model:
        return build_plant(model, dt, base_dir)
    spec = {k: dict(twin[k]) for k in ("actuator", "specimen", "sensor") if twin.get(k)}
    return load_plant(spec, dt)


def _comment_text(line: str) -> str:
    r"""``line`` as TOML comment text: control characters (not allowed there) as ``\xNN``."""
    return "".join(c if c == "\t" or c.isprintable() else f"\\x{ord(c):02x}" for c in line)


def model_to_toml(spec: ModelSpec | Mapping[str, Any], header: str = "") -> str:
    """Format a model spec as TOML text (``header`` becomes leading ``#`` comment lines)."""
    if not isinstance(spec, ModelSpec):
        spec = load_model(spec)
    data = spec.to_dict()
    lines = [f"# {_comment_text(line)}".rstrip() for line in header.splitlines()]
    if lines:
        lines.append("")
    act = dict(data["actuator"])
    effects = act.pop("effects", [])
    lines.append("[actuator]")
    lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in act.items()]
    for eff in effects:
        lines += ["", "[[actuator.effects]]"]
        lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in eff.items()]
    for table in ("specimen", "sensor"):
        if table in data:
            lines += ["", f"[{table}]"]
            lines += [f"{toml_key(k)} = {toml_value(v)}" for k, v in data[table].items()]
    return "\n".join(lines) + "\n"


def dump_model(spec: ModelSpec | Mapping[str, Any], path: str | Path, header: str = "") -> None:
    """Write a model spec (or a dict in the file's layout, validated first) as a TOML file."""
    text = model_to_toml(spec, header)
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{path}: cannot write model file ({exc.strerror})") from None

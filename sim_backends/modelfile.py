"""The twin model file (TOML): one format for ``twin serve``, ``simulate`` and ``twin calibrate``.

Format (all values SI; a quantity may also be a string with a unit as in the run configuration,
``"12ms"``, ``"0.2mm"``, ``"1.19 MN/m"``)::

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

Each table's keys are declared (:data:`FILE_KEYS`, :data:`ACTUATOR_KEYS` with the model's
parameters, each effect's ``PARAMS``, :data:`SPECIMEN_KEYS`, :data:`SENSOR_KEYS`) and checked by
:func:`rths_hil.config.check_table`, the validator of the run configuration. Unknown tables,
keys, models or effect kinds raise :class:`~rths_hil.errors.InputError` naming the file and the
key path, e.g. ``twin.toml: actuator.effects[1].kind: unknown effect 'foo'
(known: offset, drift, …)`` (effects are numbered from 0 as in the file's order).

``force_feedback`` effects without ``specimen_stiffness``/``specimen_damping`` take them from
``[specimen]`` (or its defaults); the ``benchmark`` model takes ``specimen_stiffness``,
``specimen_damping`` and ``specimen_mass`` from the keys given in ``[specimen]`` unless set in
``[actuator]``, so one specimen loads the actuator and produces the measured force.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rths_hil.config import REQUIRED, Key, check_table
from rths_hil.errors import InputError
from rths_hil.formats import read_toml, toml_key, toml_value

from .effects import EFFECTS, FORCE_REFUSED, FORCE_UNITS, make_effect, validate_params
from .models import make_model
from .plant import Sensor, TwinPlant
from .registry import MODELS, model_entry
from .specimen import SPECIMEN_DEFAULTS, KelvinVoigt

__all__ = [
    "ACTUATOR_KEYS",
    "FILE_KEYS",
    "SENSOR_KEYS",
    "SPECIMEN_KEYS",
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

#: The tables of a model file.
FILE_KEYS = {
    "actuator": Key("table", REQUIRED),  # the actuator model, its parameters and effects
    "specimen": Key("table", None, doc="the specimen (default: the benchmark's)"),
    "sensor": Key("table", None, doc="the measurement chain (default: no noise)"),
}
#: ``[actuator]``'s own keys (an actuator model adds its parameters).
ACTUATOR_KEYS = {
    "delay": Key("float", 0.0, unit="s", lo=0, doc="transport delay (the FEI paper, Fig. 4.1)"),
    "gain": Key("float", 1.0, doc="amplitude gain"),
    "model": Key("str", "delay_gain", doc="actuator model (sim_backends.registry.MODELS)"),
    "effects": Key("tables", [], doc="[[actuator.effects]], applied in order after the model"),
}
#: ``[specimen]``: a Kelvin–Voigt spring, dashpot and mass (defaults: SPECIMEN_DEFAULTS).
SPECIMEN_KEYS = {
    "model": Key("choice", "kelvin_voigt", choices=("kelvin_voigt", "spring_dashpot")),
    "stiffness": Key("float", None, unit="N/m", lo=0, doc="spring stiffness"),
    "damping": Key("float", None, unit="N·s/m", lo=0, doc="dashpot coefficient"),
    "mass": Key("float", None, unit="kg", lo=0, doc="specimen mass"),
}
#: ``[sensor]``: white noise (std) and quantisation step of each channel, the noise's seed.
SENSOR_KEYS = {
    "displacement_noise": Key("float", 0.0, unit="m", lo=0, doc="displacement noise (std)"),
    "force_noise": Key("float", 0.0, unit="N", lo=0, doc="force noise (std)"),
    "displacement_resolution": Key("float", 0.0, unit="m", lo=0, doc="quantisation step"),
    "force_resolution": Key("float", 0.0, unit="N", lo=0, doc="quantisation step"),
    "seed": Key("int", 0, lo=0, doc="seed of the noise generator"),
}


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


def _model_keys(params: Mapping[str, tuple[float | None, str]]) -> dict[str, Key]:
    """``[actuator]``'s keys with an actuator model's parameters (name → default, unit)."""
    keys = dict(ACTUATOR_KEYS)
    for name, (default, unit) in params.items():
        given_unit = _UNITS.get(name, unit) or "-"
        keys[name] = Key("float", REQUIRED if default is None else default, unit=given_unit)
    return keys


def _read_specimen(
    table: Mapping[str, Any] | None, where: str
) -> tuple[SpecimenSpec | None, dict[str, float]]:
    """The ``[specimen]`` table (None without one) and the keys it gives."""
    if table is None:
        return None, {}
    given = check_table(table, SPECIMEN_KEYS, where, "specimen")
    specimen_given = {k: given[k] for k in _SPECIMEN_KEYS if given[k] is not None}
    values = {**SPECIMEN_DEFAULTS, **specimen_given}
    specimen = SpecimenSpec(
        stiffness=values["stiffness"], damping=values["damping"], mass=values["mass"]
    )
    return specimen, specimen_given


def _read_actuator(
    at: Mapping[str, Any], where: str, specimen_given: dict[str, float]
) -> tuple[str, float, float, dict[str, float], list[dict[str, Any]]]:
    """The ``[actuator]`` table: model, delay (s), gain, parameters, effect tables."""
    p = f"{where}: " if where else ""
    model = at.get("model", "delay_gain")
    if not isinstance(model, str):
        raise InputError(
            f"{p}actuator.model: unknown actuator model {model!r} (known: {', '.join(MODELS)})"
        )
    try:
        model, entry = model_entry(model)
    except InputError as exc:
        raise InputError(f"{p}actuator.model: {exc}") from None
    missing = f"required by model {model!r}"
    values = check_table(at, _model_keys(entry.params), where, "actuator", missing=missing)
    delay, gain = values["delay"], values["gain"]
    params = {k: values[k] for k in entry.params if k in at}
    if entry.uses_specimen:
        for key in _SPECIMEN_KEYS:
            if f"specimen_{key}" not in params and key in specimen_given:
                params[f"specimen_{key}"] = specimen_given[key]
    try:  # the model's own range checks (e.g. time_constant > 0, stable benchmark plant)
        make_model(model, 1.0 / 1024.0, delay=delay, gain=gain, **params)
    except InputError as exc:
        raise InputError(f"{p}actuator.{exc}") from None
    return model, delay, gain, params, values["effects"]


def _read_effects(
    raw_effects: list[dict[str, Any]], where: str, control: str, spec_values: dict[str, float]
) -> list[EffectSpec]:
    """The ``[[actuator.effects]]`` of a twin of ``control`` (force: its refusals, units)."""
    p = f"{where}: " if where else ""
    effects: list[EffectSpec] = []
    for i, et in enumerate(raw_effects):
        path = f"actuator.effects[{i}]"
        if "kind" not in et:
            raise InputError(f"{p}{path}.kind: missing (known: {', '.join(EFFECTS)})")
        kind = et.pop("kind")
        if not isinstance(kind, str) or kind not in EFFECTS:
            raise InputError(
                f"{p}{path}.kind: unknown effect {kind!r} (known: {', '.join(EFFECTS)})"
            )
        if control == "force" and kind in FORCE_REFUSED:
            raise InputError(
                f"{p}{path}.kind: a force-controlled twin does not take {kind!r} "
                f"({FORCE_REFUSED[kind]})"
            )
        if kind == "force_feedback":
            et.setdefault("specimen_stiffness", spec_values["stiffness"])
            et.setdefault("specimen_damping", spec_values["damping"])
        units = FORCE_UNITS.get(kind, {}) if control == "force" else {}
        effects.append(EffectSpec(kind, validate_params(kind, et, where, path, units=units)))
    return effects


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
    where = name or ""
    top = check_table(data, FILE_KEYS, where, missing="missing table [actuator]")
    specimen, specimen_given = _read_specimen(top["specimen"], where)
    spec_values = {**SPECIMEN_DEFAULTS, **specimen_given}

    model, delay, gain, params, raw = _read_actuator(top["actuator"], where, specimen_given)
    effects = _read_effects(raw, where, control, spec_values)
    sensor = Sensor(**check_table(top["sensor"] or {}, SENSOR_KEYS, where, "sensor"))

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

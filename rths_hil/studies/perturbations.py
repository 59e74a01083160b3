"""Perturbations of an inline-twin configuration for the robustness study (``docs/studies.md``).

:class:`Perturbation` is one varied parameter (a configuration key or a twin model key, its range
and distribution); :func:`parse_vary` reads and checks ``--vary KEY=LOW:HIGH[:normal]``;
:func:`default_perturbations` gives the RTHS benchmark's spread; :func:`inline_twin` and
:func:`channel_suffixes` describe the twins a configuration runs.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from rths_hil.sim_backends.modelfile import load_model
from rths_hil.sim_backends.models import BENCHMARK_NOMINAL
from rths_hil.sim_backends.registry import MODEL_ALIASES, MODELS

from ..config import SCHEMA, Config, coerce, cross_check, resolve_channel, set_compensation
from ..errors import InputError
from ..records.columns import channel_suffix
from ..units import parse_accel, parse_force, parse_length, parse_time, parse_velocity

#: Physical domain of the twin parameters that can be varied: (lower bound, bound is open).
_TWIN_DOMAIN: dict[str, tuple[float, bool]] = {
    "actuator.delay": (0.0, False),
    "actuator.gain": (0.0, True),
    "actuator.time_constant": (0.0, True),
    "actuator.plant_gain": (0.0, True),
    "actuator.a1b0": (0.0, True),
    "actuator.a2": (0.0, True),
    "actuator.a3": (0.0, True),
    "actuator.beta1": (0.0, True),
    "actuator.beta2": (0.0, True),
    "actuator.specimen_mass": (0.0, True),
    "actuator.specimen_damping": (0.0, False),
    "actuator.specimen_stiffness": (0.0, True),
    "specimen.stiffness": (0.0, True),
    "specimen.damping": (0.0, False),
    "specimen.mass": (0.0, False),
    "sensor.displacement_noise": (0.0, False),
    "sensor.force_noise": (0.0, False),
    "sensor.displacement_resolution": (0.0, False),
    "sensor.force_resolution": (0.0, False),
}
#: Units of the twin parameters (the rest are plain numbers in SI units).
_TWIN_UNITS = {"delay": "s", "time_constant": "s", "displacement_noise": "m"}
#: Configuration sections whose float keys may be varied.
_CONFIG_SECTIONS = ("structure", "ground_motion", "compensation")


@dataclass(frozen=True)
class Perturbation:
    """One varied key: uniform on [low, high], or normal with mean (low + high)/2 and
    σ = (high − low)/4 (low … high is the ±2σ range), redrawn outside the physical domain.

    Attributes
    ----------
    key : str
        Configuration path, e.g. ``twin.actuator.delay`` or ``twin.specimen.stiffness``.
    low, high : float
        Range in SI units.
    dist : {"uniform", "normal"}
    """

    key: str
    low: float
    high: float
    dist: str = "uniform"

    @property
    def text(self) -> str:
        """The ``--vary`` form (SI numbers)."""
        tail = ":normal" if self.dist == "normal" else ""
        return f"{self.key}={self.low:.6g}:{self.high:.6g}{tail}"

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` values (a normal is truncated to the key's physical domain by redrawing)."""
        if self.dist == "uniform":
            return rng.uniform(self.low, self.high, n)
        mean, sigma = 0.5 * (self.low + self.high), 0.25 * (self.high - self.low)
        out = mean + sigma * rng.standard_normal(n)
        lo, open_ = _domain(self.key)
        for _ in range(1000):
            bad = (out <= lo) if open_ else (out < lo)
            if not bad.any():
                break
            out[bad] = mean + sigma * rng.standard_normal(int(bad.sum()))
        return out


def _twin_key(key: str) -> str | None:
    """``twin.actuator.delay`` for ``twin.actuator.delay`` and for
    ``actuators.NAME.twin.actuator.delay`` (one channel's twin); None for other keys."""
    if key.startswith("twin."):
        return key
    parts = key.split(".")
    if len(parts) == 5 and parts[0] == "actuators" and parts[2] == "twin":
        return ".".join(parts[2:])
    return None


def _domain(key: str) -> tuple[float, bool]:
    tk = _twin_key(key)
    if tk is not None:
        return _TWIN_DOMAIN.get(tk[5:], (-math.inf, False))
    return (-math.inf, False)  # the schema's own range is checked by the configuration


def _channel_names(cfg) -> list[str]:
    """Names of the ``[[actuators]]`` channels (empty for the implicit single channel)."""
    return [a["name"] for a in (cfg.get("actuators") or [])]


def _record_channels(cfg) -> list[str | None]:
    """The channels as the record names them: ``[None]`` for one channel (unsuffixed columns),
    else the channel names (docs/channels.md)."""
    names = _channel_names(cfg)
    return list(names) if len(names) > 1 else [None]


def channel_suffixes(cfg) -> list[str]:
    """Record-column suffixes of the channels: ``[""]`` for one channel, else ``_<name>``
    (:func:`rths_hil.records.columns.channel_suffix`)."""
    return [channel_suffix(ch) for ch in _record_channels(cfg)]


def _set_value(cfg, key: str, value: float) -> None:
    """Set ``key`` (a checked path) to ``value`` in a Config, in place.

    ``twin.*`` sets the top-level twin and, in a configuration with ``[[actuators]]`` (whose
    twins :func:`inline_twin` made explicit), every channel's twin;
    ``actuators.NAME.twin.*`` sets one channel's twin.
    """
    parts = key.split(".")
    if parts[0] == "twin":
        cfg["twin"][parts[1]][parts[2]] = float(value)
        for entry in cfg.get("actuators") or []:
            if "twin" in entry:
                entry["twin"][parts[1]][parts[2]] = float(value)
    elif parts[0] == "actuators":
        entry = next(a for a in cfg["actuators"] if a["name"] == parts[1])
        entry["twin"][parts[3]][parts[4]] = float(value)
    elif parts[0] == "compensation":  # α and delay (and the other pairs) kept together
        set_compensation(cfg["compensation"], parts[1], value, cfg["loop"]["fs"])
    else:
        cfg[parts[0]][parts[1]] = float(value)


def inline_twin(cfg):
    """A copy of ``cfg`` whose twin is given by inline tables (a ``twin.model`` file is read)."""

    out = copy.deepcopy(cfg)
    if not isinstance(out, Config):
        raise InputError("expected a Config")
    kind = out["structure"].get("kind", "sdof")
    if kind not in ("sdof", "shear_building", "matrices"):
        raise InputError(
            f"{cfg.source}: structure.kind = {kind!r}: a robustness study re-runs the numerical "
            "substructure in every trial, so it needs one the bridge integrates (sdof, "
            "shear_building, matrices)"
        )

    def inline(tw: dict, where: str) -> dict:
        if not tw["enabled"]:
            raise InputError(
                f"{cfg.source}: {where}.enabled = false: robustness studies run on the twin, "
                "never on the real actuator"
            )
        if tw["model"]:
            path = cfg.resolve_path(tw["model"])
            try:
                data = load_model(path).to_dict()
            except InputError as exc:
                raise InputError(f"{cfg.source}: {where}.model: {exc}") from None
            return {
                "model": "",
                "actuator": data["actuator"],
                "specimen": data.get("specimen", {}),
                "sensor": data.get("sensor", {}),
            }
        return {
            "model": "",
            "actuator": dict(tw["actuator"]),
            "specimen": dict(tw["specimen"] or {}),
            "sensor": dict(tw["sensor"] or {}),
        }

    out["twin"].update(inline(out["twin"], "twin"))
    # each channel's twin made explicit (its own, or the top-level one it inherits), so that
    # one channel's twin can be varied without touching the others
    for entry in out.get("actuators") or []:
        own = resolve_channel(cfg, entry).config["twin"]
        entry["twin"] = {**entry.get("twin", {}), **inline(own, f"actuators.{entry['name']}.twin")}
    return out


def _twin_spec(cfg, channel: str | None = None):
    """The validated :class:`~sim_backends.modelfile.ModelSpec` of an inline-twin Config
    (of channel ``channel``'s twin when given)."""

    tw = cfg["twin"]
    if channel is not None:
        tw = next(a for a in cfg["actuators"] if a["name"] == channel)["twin"]
    data: dict = {"actuator": tw["actuator"]}
    if tw["specimen"]:
        data["specimen"] = tw["specimen"]
    if tw["sensor"]:
        data["sensor"] = tw["sensor"]
    return load_model(data)


def _twin_keys(tw: dict, prefix: str) -> list[str]:

    model = tw["actuator"].get("model", "delay_gain")
    model = MODEL_ALIASES.get(model, model)
    params = MODELS[model].params if model in MODELS else {}
    keys = [f"{prefix}twin.actuator.{k}" for k in ("delay", "gain", *params)]
    keys += [f"{prefix}twin.specimen.{k}" for k in ("stiffness", "damping", "mass")]
    keys += [f"{prefix}twin.{k}" for k in _TWIN_DOMAIN if k.startswith("sensor.")]
    return keys


def _varyable_keys(cfg) -> list[str]:

    chans = cfg.get("actuators") or []
    if chans:
        # top-level twin.* keys apply to every channel, so only those all channels' models have
        per = [_twin_keys(a["twin"], "") for a in chans]
        keys = [k for k in per[0] if all(k in p for p in per)]
        for a in chans:
            keys += _twin_keys(a["twin"], f"actuators.{a['name']}.")
    else:
        keys = _twin_keys(cfg["twin"], "")
    for section in _CONFIG_SECTIONS:
        keys += [f"{section}.{k}" for k, key in SCHEMA[section].items() if key.kind == "float"]
    return keys


_PARSERS = {
    "s": parse_time,
    "m": parse_length,
    "m/s²": parse_accel,
    "N": parse_force,
    "m/s": parse_velocity,
}


def _vary_value(p: str, unit: str | None, key: str, where: str) -> float:
    """One end of a ``--vary`` range, in ``unit`` (SI; a plain number without a unit)."""
    parse = _PARSERS.get(unit) if unit else None
    try:
        v = parse(p, key) if parse is not None else float(p)
    except (InputError, ValueError):
        what = f"a number in {unit}" if unit else "a number"
        raise InputError(f"{where}: {p!r} is not {what}") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {p!r} is not finite")
    return float(v)


def parse_vary(text: str, cfg) -> Perturbation:
    """Parse and check ``KEY=LOW:HIGH[:normal]`` against an inline-twin Config.

    Values may carry units where the key has one (``twin.actuator.delay=15ms:35ms``). The key
    must be one the configuration or the twin's model knows; ``low ≤ high``; both ends must be
    physical (e.g. a delay ≥ 0, a gain or time constant > 0, a stiffness > 0) and give a valid
    configuration and a stable twin.

    Raises
    ------
    InputError
        One line naming the ``--vary`` argument and what is wrong.
    """

    where = f"--vary {text}"
    key, sep, rng_text = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise InputError(f"{where}: expected KEY=LOW:HIGH[:normal]")
    known = _varyable_keys(cfg)
    if key not in known:
        near = [k for k in known if k.split(".")[-1] == key.split(".")[-1]]
        hint = f"; did you mean {near[0]}?" if near else ""
        raise InputError(
            f"{where}: unknown key {key!r} for this configuration (e.g. "
            f"{', '.join(known[:4])}, …){hint}"
        )
    parts = [p.strip() for p in rng_text.split(":")]
    dist = "uniform"
    if len(parts) == 3 and parts[2].lower() in ("normal", "uniform"):
        dist = parts.pop().lower()
    if len(parts) != 2 or not all(parts):
        raise InputError(f"{where}: expected LOW:HIGH or LOW:HIGH:normal")
    name = key.split(".")[-1]
    unit = _TWIN_UNITS.get(name) if _twin_key(key) else None
    if not _twin_key(key):
        unit = SCHEMA[key.split(".")[0]][name].unit
    values = [_vary_value(p, unit, key, where) for p in parts]
    low, high = values
    if low > high:
        raise InputError(f"{where}: low ({parts[0]}) is above high ({parts[1]})")
    lo, open_ = _domain(key)
    for v, p in ((low, parts[0]), (high, parts[1])):
        if (v <= lo) if open_ else (v < lo):
            rel = ">" if open_ else "≥"
            raise InputError(f"{where}: {p} is not physical ({key} must be {rel} {lo:g})")
    for v in (low, high):
        _check_values(cfg, {key: v}, where)
    return Perturbation(key, low, high, dist)


def _check_values(cfg, values: dict[str, float], where: str) -> None:
    """Raise InputError when ``values`` make an invalid configuration or twin."""

    trial = copy.deepcopy(cfg)
    for key, v in values.items():
        parts = key.split(".")
        if _twin_key(key) is None:
            try:
                coerce(SCHEMA[parts[0]][parts[1]], v, key)
            except InputError as exc:
                raise InputError(f"{where}: {exc}") from None
        _set_value(trial, key, v)
    try:
        cross_check(trial)
        names: list[str | None] = [*_channel_names(trial)] or [None]
        for name in names:
            _twin_spec(trial, name).build(1.0 / float(trial["loop"]["fs"]))
    except InputError as exc:
        msg = str(exc).removeprefix(f"{trial.source}: ")
        raise InputError(f"{where}: {msg}") from None


def default_perturbations(cfg) -> list[Perturbation]:
    """Benchmark-style perturbations of an inline-twin Config (``docs/studies.md``).

    The RTHS benchmark draws, for every perturbed trial, normal values with the σ of its
    ``F1_input_file.m`` (lines 67 and 119–121; the paper's Table 2): specimen stiffness σ =
    50e3 N/m (4.2 % of 1.19e6), a3 σ = 1.3, β1 σ = 3.3, β2 σ = 3.3e3. For the ``benchmark``
    actuator model these are used as they are, around the configuration's values. For the other
    models the same plant spread is carried over: across those draws the benchmark plant's
    equivalent delay at 1 Hz has σ = 3.4 % and its amplitude σ = 0.73 %, so the time constant
    (or the transport delay of a pure ``delay_gain``) gets σ = 3.4 %, the gain σ = 0.73 %, and
    the specimen stiffness σ = 4.2 %. Each is a ``normal`` perturbation over ±2σ.
    """
    chans = cfg.get("actuators") or []
    if chans:
        # several channels: each channel's twin drawn independently over the same ranges
        out_all: list[Perturbation] = []
        for a in chans:
            one = copy.deepcopy(cfg)
            one["actuators"] = []
            one["twin"].update(copy.deepcopy(a["twin"]))
            for p in default_perturbations(one):
                key = f"actuators.{a['name']}.{p.key}"
                out_all.append(Perturbation(key, p.low, p.high, p.dist))
        return out_all
    act = cfg["twin"]["actuator"]
    spec = _twin_spec(cfg)
    model = act.get("model", "delay_gain")
    out: list[Perturbation] = []

    def normal(key: str, mean: float, sigma: float) -> None:
        if mean > 0 and sigma > 0:
            out.append(Perturbation(key, mean - 2 * sigma, mean + 2 * sigma, "normal"))

    def rel(key: str, value: float, sigma: float) -> None:
        normal(key, value, sigma * value)

    k = spec.specimen.stiffness if spec.specimen is not None else None
    if model == "benchmark":
        nominal = {**BENCHMARK_NOMINAL, **spec.actuator.params}
        for name, sigma in (("a3", 1.3), ("beta1", 3.3), ("beta2", 3.3e3)):
            normal(f"twin.actuator.{name}", nominal[name], sigma)
        if "specimen_stiffness" in spec.actuator.params or k is None:
            normal("twin.actuator.specimen_stiffness", nominal["specimen_stiffness"], 50e3)
        else:
            rel("twin.specimen.stiffness", k, _SIGMA_STIFFNESS)
        return out
    if model in ("servo_lag", "first_order"):
        rel("twin.actuator.time_constant", spec.actuator.params["time_constant"], _SIGMA_DELAY)
    elif spec.actuator.delay > 0:
        rel("twin.actuator.delay", spec.actuator.delay, _SIGMA_DELAY)
    rel("twin.actuator.gain", spec.actuator.gain, _SIGMA_GAIN)
    rel("twin.specimen.stiffness", k if k is not None else 1.19e6, _SIGMA_STIFFNESS)
    return out


#: Relative σ of the benchmark-style perturbations (:func:`default_perturbations`).
_SIGMA_DELAY = 0.034
_SIGMA_GAIN = 0.0073
_SIGMA_STIFFNESS = 50e3 / 1.19e6

"""Robustness study (``docs/studies.md``): perturbed twins in lockstep through the full chain.

:func:`robustness_study` draws perturbed twins (:class:`Perturbation`, :func:`parse_vary`,
benchmark-style :func:`default_perturbations`), runs each in lockstep through
:func:`rths_hil.hybrid.run` (:func:`robustness_trial`) and evaluates it against the reference
structure (:func:`reference_response`) with J1–J9 as the RTHS benchmark's paper and evaluation
script define them (:mod:`rths_hil.metrics`), the whole-record FEI and the MWO extremes.

Trials run through an executor (:mod:`rths_hil.studies.executors`).
"""

from __future__ import annotations

import copy
import csv
import logging
import math
import os
import shutil
import tempfile
import threading
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rths_hil.sim_backends.modelfile import load_model
from rths_hil.sim_backends.models import BENCHMARK_NOMINAL
from rths_hil.sim_backends.registry import MODEL_ALIASES, MODELS
from rths_hil.sim_backends.specimen import SPECIMEN_DEFAULTS, KelvinVoigt

from ..config import SCHEMA, Config, coerce, cross_check, resolve_channel, set_compensation
from ..errors import InputError
from ..fei import fei
from ..hybrid import build_ground_motion, run
from ..metrics import benchmark_criteria, criteria
from ..plotting import save_figure
from ..records.columns import channel_suffix, column_name
from ..records.recorder import read_run
from ..structures.sdof import BoucWenParams, CRStepper
from ..units import parse_accel, parse_force, parse_length, parse_time, parse_velocity
from .executors import run_cases
from .paper import format_value

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# robustness study: perturbed twins in lockstep through the full chain

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


@dataclass
class TrialSpec:
    """Everything one robustness trial needs (self-contained: runs on any worker).

    Attributes
    ----------
    index : int
        Trial (plant draw) number, from 0.
    alpha : float
        Inverse-compensation α of this run (NaN: the configuration's).
    values : dict
        The drawn value of each varied key (SI).
    cfg : Config
        The trial's configuration: inline twin, drawn values and α applied.
    record : tuple of (str, bytes), optional
        The ground-motion file (name, content) when it is a file of the client's: written
        into the trial's scratch directory, so that workers need not share a file system.
    duration : float, optional
        Seconds of the record (None: the configuration's).
    """

    index: int
    alpha: float
    values: dict[str, float]
    cfg: Any
    record: tuple[str, bytes] | None = None
    duration: float | None = None


#: One trial at a time in a worker process: the twins' in-process buses and the loop's
#: garbage-collector pause are per process.
_TRIAL_LOCK = threading.Lock()

#: Scratch directory of one trial: ``<tmp>/rths-trial-<pid>-<random>`` (the pid of the worker
#: process that runs it, so that a dead worker's scratch can be recognised and removed).
_SCRATCH_PREFIX = "rths-trial-"


def _sweep_dead_scratch(tmp: str | None = None) -> int:
    """Remove trial scratch directories left by worker processes that no longer exist.

    A worker killed during a trial (SIGKILL, out of memory) cannot remove its scratch
    directory; the next trial on this machine does. Returns how many were removed.
    """

    root = Path(tmp or tempfile.gettempdir())
    removed = 0
    for d in root.glob(_SCRATCH_PREFIX + "*"):
        pid = d.name[len(_SCRATCH_PREFIX) :].split("-", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # its worker is alive (maybe running a trial now)
        except ProcessLookupError:
            pass
        except PermissionError:  # another user's live process
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed += 1
        log.info("removed %s, the scratch of a worker that died", d)
    return removed


def reference_response(cfg, n: int | None = None) -> np.ndarray:
    """The reference structure's displacement: the same test with an ideal transfer system.

    The numerical substructure of ``cfg`` (the loop's CR integrator, Chen & Ricles 2008, with
    the same parameters and record) coupled to the twin's specimen (Kelvin–Voigt, the force
    the twin would measure without noise) through an actuator that achieves every command
    exactly and no compensation: what the hybrid test would give with perfect tracking, the
    ``x_r`` of Silva et al. (2020) Eqs. 15 and 18 for an SDOF structure. Equal to a lockstep
    run of :func:`rths_hil.hybrid.run` with such a plant (``tests/studies/test_robustness.py``).

    Parameters
    ----------
    cfg : Config
        Resolved configuration with an inline twin (see :func:`parse_vary`).
    n : int, optional
        Steps (default: as the loop, from ``loop.duration`` or the record).
    """

    fs = float(cfg["loop"]["fs"])
    dt = 1.0 / fs
    ag = np.asarray(build_ground_motion(cfg).accel, dtype=float)
    if n is None:
        dur = float(cfg["loop"]["duration"])
        n = round(dur * fs) if dur > 0 else ag.size
    if n > ag.size:
        ag = np.concatenate([ag, np.zeros(n - ag.size)])
    s = cfg["structure"]
    k_struct = s["mass"] * (2.0 * math.pi * s["fn"]) ** 2
    bw = None
    if s["bouc_wen"]:
        bw = BoucWenParams(
            x_y=s["x_y"], k_a=k_struct, eta=s["eta"], beta=s["beta"], gamma=s["gamma"], q=s["q"]
        )
    st = CRStepper(
        s["mass"], s["damping"], k_struct, dt, bouc_wen=bw, k_specimen=s["k_specimen"], ag0=ag[0]
    )
    sp = _twin_spec(cfg).specimen
    values = SPECIMEN_DEFAULTS if sp is None else vars(sp)
    specimen = KelvinVoigt(values["stiffness"], values["damping"], dt, mass=values["mass"])
    out = np.empty(n)
    x_t = st.x
    step, force_at = st.step, specimen.step
    agl = ag.tolist()
    for k in range(n):  # the loop's order: impose x_t[k], measure, commit step k, next target
        out[k] = x_t
        f = force_at(x_t)
        x_t = step(agl[k], f) if k > 0 else st.x_next
    return out


def reference_by_loop(cfg, n: int, tmp: str | Path) -> dict[str, np.ndarray]:
    """Each channel's reference displacement x_r: the same test with ideal actuators.

    For any structure and any number of channels: a lockstep run of :func:`rths_hil.hybrid.run`
    in which every channel's twin keeps its specimen but achieves each command exactly
    (``delay_gain`` with zero delay and unit gain, no effects, no sensor noise) and
    compensation is off, so that the target each channel is given is x_r = T·u of the
    numerical substructure coupled to ideal actuators and the specimens (Silva et al. 2020,
    Eqs. 15 and 18). Returns ``{suffix: target}`` for the suffixes of
    :func:`channel_suffixes`.
    """

    ideal = copy.deepcopy(cfg)
    perfect = {"model": "delay_gain", "delay": 0.0, "gain": 1.0}
    for tw in [ideal["twin"], *(a["twin"] for a in ideal.get("actuators") or [])]:
        tw["actuator"] = dict(perfect)
        tw["sensor"] = {}
    for entry in ideal.get("actuators") or []:
        entry.get("compensation", {}).pop("enabled", None)
    ideal["compensation"]["enabled"] = False
    ideal["kalman"]["enabled"] = False
    ideal["fei"]["exact_hop"] = 0
    run_dir = Path(tmp) / "reference"
    run(ideal, run_dir=run_dir, mode="lockstep", duration=n / float(ideal["loop"]["fs"]))
    rec = read_run(run_dir).record
    return {
        channel_suffix(ch): np.asarray(rec[column_name("target", ch)], dtype=float)
        for ch in _record_channels(cfg)
    }


def _extremes(values: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    v = values[valid & np.isfinite(values)]
    return (float(v.min()), float(v.max())) if v.size else (math.nan, math.nan)


def preflight(cfg: Config, duration: float | None = None) -> None:
    """Refuse a study whose unperturbed configuration a run would refuse, before any trial.

    A trial that a run refuses (a drawn plant that is unstable) is a row of the study
    (``status = invalid``); a structure file, record or key that no trial can use (a missing,
    empty or garbage record, NaN in the matrices) would make every row one, so it is refused
    here in one line (:class:`InputError`) by the plan a run builds (no I/O is written).
    """
    from ..hybrid.plan import build_plan

    with tempfile.TemporaryDirectory(prefix=_SCRATCH_PREFIX) as tmp:
        build_plan(cfg, Path(tmp) / "run", mode="lockstep", duration=duration)


def robustness_trial(spec: TrialSpec) -> dict[str, Any]:
    """Run one perturbed trial in lockstep through :func:`rths_hil.hybrid.run`; return its row.

    The run's record goes to a scratch directory that is removed afterwards. The row has the
    trial's parameters, how it ended (``status``, the tripped rule, its time and reason), the
    whole-record FEI (the FEI paper's Eq. 2.1–2.5: A, d, f_eq), the extremes of the online
    moving-window FEI (MWO) over its valid windows, J1–J9 with the paper's numbering
    (:func:`rths_hil.metrics.criteria`, J1 in s) and as the benchmark's script computes them
    (:func:`rths_hil.metrics.benchmark_criteria`, ``bench_J1`` in ms), and the peaks.
    """

    _sweep_dead_scratch()
    scratch = tempfile.TemporaryDirectory(prefix=f"{_SCRATCH_PREFIX}{os.getpid()}-")
    with _TRIAL_LOCK, scratch as tmp:
        cfg = copy.deepcopy(spec.cfg)
        if spec.record is not None:
            path = Path(tmp) / Path(spec.record[0]).name
            path.write_bytes(spec.record[1])
            cfg["ground_motion"]["record"] = str(path)
        sfx_all = channel_suffixes(cfg)
        sdof = cfg["structure"].get("kind", "sdof") == "sdof" and not cfg.get("actuators")
        try:
            res = run(cfg, run_dir=Path(tmp) / "run", mode="lockstep", duration=spec.duration)
            rec = read_run(Path(tmp) / "run").record
            if sdof:
                references = {"": reference_response(cfg, res.planned_steps)}
            else:
                references = reference_by_loop(cfg, res.planned_steps, tmp)
        except InputError as exc:  # e.g. a drawn benchmark plant that is unstable
            log.warning("trial %d (α = %g): %s", spec.index, spec.alpha, exc)
            return _invalid_row(spec, str(exc))
    fs = float(cfg["loop"]["fs"])
    row: dict[str, Any] = {"trial": spec.index, "alpha": float(cfg["compensation"]["alpha"])}
    row.update({k: float(v) for k, v in spec.values.items()})
    trip = res.trip
    row.update(
        status=res.status,
        steps=int(res.steps),
        trip_rule=trip.rule if trip is not None else "",
        trip_time=float(trip.time) if trip is not None else math.nan,
        trip_reason=trip.reason if trip is not None else "",
    )
    if sfx_all != [""]:
        row["trip_channel"] = trip.channel if trip is not None else ""
        for sfx, entry in zip(sfx_all, cfg["actuators"], strict=True):
            comp = resolve_channel(cfg, entry).config["compensation"]
            row["alpha" + sfx] = float(comp["alpha"]) if comp["enabled"] else 1.0
    nan = math.nan
    for ch in _record_channels(cfg):
        sfx = channel_suffix(ch)
        target = np.asarray(rec[column_name("target", ch)], dtype=float)
        measured = np.asarray(rec[column_name("measured", ch)], dtype=float)
        n = target.size
        reference = references[sfx][:n]
        whole = fei(target, measured, fs) if n >= 8 else None
        row["fei_amplitude" + sfx] = whole.amplitude if whole is not None else nan
        row["fei_delay" + sfx] = whole.delay if whole is not None else nan
        row["fei_f_eq" + sfx] = whole.f_eq if whole is not None else nan
        valid = np.asarray(rec[column_name("fei_valid", ch)], dtype=bool)
        a_lo, a_hi = _extremes(
            np.asarray(rec[column_name("fei_amplitude", ch)], dtype=float), valid
        )
        d_lo, d_hi = _extremes(np.asarray(rec[column_name("fei_delay", ch)], dtype=float), valid)
        row["mwo_amplitude_min" + sfx], row["mwo_amplitude_max" + sfx] = a_lo, a_hi
        row["mwo_delay_min" + sfx], row["mwo_delay_max" + sfx] = d_lo, d_hi
        ok = n >= BENCHMARK_MIN_STEPS
        paper = criteria(target, measured, fs, reference) if ok else {}
        bench = benchmark_criteria(target, measured, fs, reference) if ok else {}
        for i in range(1, 10):
            row[f"J{i}{sfx}"] = float(paper.get(f"J{i}", nan))
        for i in range(1, 10):
            row[f"bench_J{i}{sfx}"] = float(bench.get(f"J{i}", nan))
        row["peak_target" + sfx] = float(np.max(np.abs(target))) if n else nan
        row["peak_reference" + sfx] = float(np.max(np.abs(reference))) if n else nan
        row["peak_force" + sfx] = float(np.max(np.abs(rec[column_name("force", ch)]))) if n else nan
    return row


def _invalid_row(spec: TrialSpec, reason: str) -> dict[str, Any]:
    row: dict[str, Any] = {"trial": spec.index, "alpha": float(spec.cfg["compensation"]["alpha"])}
    row.update({k: float(v) for k, v in spec.values.items()})
    row.update({c: math.nan for c in trial_columns(channel_suffixes(spec.cfg))})
    row.update(status="invalid", steps=0, trip_rule="", trip_reason=reason)
    if "trip_channel" in row:
        row["trip_channel"] = ""
    return row


#: Fewest recorded steps for which J1–J9 are computed (the benchmark's J1 needs 50 lags).
BENCHMARK_MIN_STEPS = 64


@dataclass
class RobustnessResult:
    """Outcome of :func:`robustness_study`.

    Attributes
    ----------
    rows : list of dict
        One per trial × α, ordered by α (as given) then trial.
    perturbations : list of Perturbation
    alphas : list of float
        The α of the runs (the configuration's when not varied).
    seed : int
    keys : list of str
        The varied keys (columns after ``alpha``).
    """

    rows: list[dict[str, Any]]
    perturbations: list[Perturbation]
    alphas: list[float]
    seed: int
    keys: list[str]
    suffixes: list[str] = field(default_factory=lambda: [""])

    @property
    def columns(self) -> list[str]:
        """CSV columns in order."""
        return ["trial", "alpha", *self.keys, *trial_columns(self.suffixes)]

    def by_alpha(self, alpha: float) -> list[dict[str, Any]]:
        """The rows run with ``alpha``."""
        return [r for r in self.rows if r["alpha"] == alpha]

    def summary(self) -> list[dict[str, Any]]:
        """Per α and metric: median, 5th and 95th percentiles over the trials with a value,
        their count, and per α the share of trials a safety rule stopped."""
        out = []
        for alpha in self.alphas:
            rows = self.by_alpha(alpha)
            tripped = sum(r["status"] == "trip" for r in rows)
            for m in (m + sfx for sfx in self.suffixes for m in SUMMARY_METRICS):
                out.append({"alpha": alpha, **metric_summary(rows, m, tripped)})
        return out


def metric_summary(rows: Sequence[dict], metric: str, tripped: int) -> dict:
    """Median, 5th and 95th percentiles of ``metric`` over the trials ``rows`` (finite values).

    Also the number of finite values ``n``, of ``trials`` and the share of tripped trials.
    """
    v = np.array([r.get(metric, math.nan) for r in rows], dtype=float)
    v = v[np.isfinite(v)]
    p5, p50, p95 = np.percentile(v, [5, 50, 95]) if v.size else (math.nan,) * 3
    return {
        "metric": metric,
        "median": float(p50),
        "p5": float(p5),
        "p95": float(p95),
        "n": int(v.size),
        "trials": len(rows),
        "share_tripped": tripped / len(rows) if rows else math.nan,
    }


#: Trial columns after the varied keys (see :func:`robustness_trial`).
TRIAL_COLUMNS: tuple[str, ...] = (
    "status",
    "steps",
    "trip_rule",
    "trip_time",
    "trip_reason",
    "fei_amplitude",
    "fei_delay",
    "fei_f_eq",
    "mwo_amplitude_min",
    "mwo_amplitude_max",
    "mwo_delay_min",
    "mwo_delay_max",
    *(f"J{i}" for i in range(1, 10)),
    *(f"bench_J{i}" for i in range(1, 10)),
    "peak_target",
    "peak_reference",
    "peak_force",
)
#: Per-channel trial columns (suffixed ``_<name>`` with several channels).
_CHANNEL_COLUMNS = TRIAL_COLUMNS[5:]


def trial_columns(suffixes: Sequence[str] = ("",)) -> list[str]:
    """Trial columns after the varied keys: :data:`TRIAL_COLUMNS` for one channel; with
    several, the run's columns, ``trip_channel``, then every per-channel column per channel."""
    if list(suffixes) == [""]:
        return list(TRIAL_COLUMNS)
    out = [*TRIAL_COLUMNS[:5], "trip_channel"]
    for sfx in suffixes:
        out += ["alpha" + sfx, *(c + sfx for c in _CHANNEL_COLUMNS)]
    return out


#: Metrics summarised per α (and per channel).
SUMMARY_METRICS: tuple[str, ...] = (
    "fei_amplitude",
    "fei_delay",
    "mwo_delay_min",
    "mwo_delay_max",
    "J1",
    "J2",
    "J3",
    "J4",
    "J7",
    "bench_J1",
    "bench_J2",
)


def plan_trials(
    cfg,
    perturbations: Sequence[Perturbation],
    trials: int,
    seed: int = 0,
    alphas: Sequence[float] | None = None,
    duration: float | None = None,
) -> list[TrialSpec]:
    """Draw the perturbed twins and build one :class:`TrialSpec` per trial × α.

    All draws are made here, from ``numpy.random.default_rng(seed)``, one column per
    perturbation in order: the same seed gives the same trials wherever they run. Every α
    runs the same drawn plants (common random numbers). A twin with sensor noise gets a noise
    seed per trial drawn from the same generator.
    """
    if int(trials) != trials or trials < 1:
        raise InputError(f"trials must be a positive integer, got {trials!r}")
    trials = int(trials)
    base = inline_twin(cfg)
    keys = [p.key for p in perturbations]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise InputError(f"--vary {dup[0]}: given more than once")
    alist = [float(base["compensation"]["alpha"])] if not alphas else [float(a) for a in alphas]
    for a in alist:
        if not (math.isfinite(a) and a >= 1):
            raise InputError(f"--alpha: α must be ≥ 1, got {a:g}")
    rng = np.random.default_rng(int(seed))
    draws = {p.key: p.draw(rng, trials) for p in perturbations}
    noise_seeds = rng.integers(0, 2**31 - 1, trials)
    base["loop"]["mode"] = "lockstep"
    base["loop"]["console"] = 0.0
    # the exact-FEI cross-check is only recorded (no safety rule reads it, the MWO extremes
    # come from the streaming FEI the FEI rule uses): off, it halves a trial's time
    base["fei"]["exact_hop"] = 0
    record = None
    spec_rec = base["ground_motion"]["record"]
    if spec_rec != "default":
        p = base.resolve_path(spec_rec)
        if p.is_file():
            record = (p.name, p.read_bytes())
    specs = []
    for a in alist:
        for i in range(trials):
            c = copy.deepcopy(base)
            values = {k: float(draws[k][i]) for k in keys}
            for k, v in values.items():
                _set_value(c, k, v)
            fs = c["loop"]["fs"]

            set_compensation(c["compensation"], "alpha", a, fs)
            if alphas:
                c["compensation"]["enabled"] = True
                c["compensation"]["method"] = "inverse"
                for entry in c.get("actuators") or []:  # --alpha: every channel's α
                    comp = entry.setdefault("compensation", {})
                    set_compensation(comp, "alpha", a, fs)
                    comp["enabled"] = True
                    comp["method"] = "inverse"
            if c["twin"]["sensor"]:
                c["twin"]["sensor"]["seed"] = int(noise_seeds[i])
            for j, entry in enumerate(c.get("actuators") or []):
                if entry["twin"]["sensor"]:  # each channel's sensor its own noise
                    entry["twin"]["sensor"]["seed"] = int(noise_seeds[i]) + 7919 * (j + 1)
            specs.append(TrialSpec(i, a, values, c, record, duration))
    return specs


def robustness_study(
    cfg,
    perturbations: Sequence[Perturbation] | None = None,
    trials: int = 200,
    *,
    seed: int = 0,
    alphas: Sequence[float] | None = None,
    duration: float | None = None,
    executor: Executor | None = None,
    progress: bool = True,
    on_row=None,
) -> RobustnessResult:
    """Perturbed-plant trials in lockstep through the full chain (docs/studies.md).

    Parameters
    ----------
    cfg : Config
        The test's configuration (``twin.enabled = true``).
    perturbations : sequence of Perturbation, optional
        Default: :func:`default_perturbations` (benchmark-style).
    trials : int
        Perturbed plants drawn.
    seed : int
        Seed of the draws.
    alphas : sequence of float, optional
        Run every plant with each α (default: the configuration's α).
    duration : float, optional
        Seconds of the record per trial (default: the configuration's).
    executor : concurrent.futures.Executor, optional
        Where the trials run (default: a process pool of 2; :func:`open_executor` gives a
        Dask one).
    progress : bool
        tqdm progress bar on stderr.
    on_row : callable, optional
        Called with each trial's row as it completes (e.g. to keep them on an interrupt).
    """
    base = inline_twin(cfg)
    perts = list(perturbations) if perturbations is not None else default_perturbations(base)
    specs = plan_trials(base, perts, trials, seed, alphas, duration)
    rows = run_cases(
        robustness_trial,
        [(s,) for s in specs],
        executor,
        progress,
        "trials",
        None if on_row is None else (lambda _i, row: on_row(row)),
    )
    alist = sorted({s.alpha for s in specs}, key=[s.alpha for s in specs].index)
    return RobustnessResult(
        rows, perts, alist, int(seed), [p.key for p in perts], channel_suffixes(base)
    )


def write_trials_csv(path: str | Path, result: RobustnessResult) -> None:
    """``trials.csv``: one line per trial × α, full-precision numbers (``repr``)."""

    cols = result.columns
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in result.rows:
            w.writerow([exact_text(r[c]) for c in cols])


def exact_text(v) -> str:
    """A CSV cell that reads back exactly (floats by ``repr``, NaN as ``nan``)."""
    if isinstance(v, float):
        return "nan" if math.isnan(v) else repr(v)
    return str(v)


def write_summary(path_csv: str | Path, result: RobustnessResult) -> None:
    """``summary.csv``: α, metric, median, p5, p95, n, trials, share_tripped."""

    rows = result.summary()
    cols = ["alpha", "metric", "median", "p5", "p95", "n", "trials", "share_tripped"]
    with Path(path_csv).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow([format_value(r[c]) if isinstance(r[c], float) else r[c] for c in cols])


def plot_robustness(out_dir: str | Path, result: RobustnessResult) -> list[Path]:
    """``robustness_hist.png`` (histograms of d and J2, one colour per α) and, with more than
    one α, ``robustness_alpha.png`` (median and 5–95 % band of d and J2, share tripped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    paths = []
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    series = [(a, sfx) for a in result.alphas for sfx in result.suffixes]
    for i, (a, sfx) in enumerate(series):
        rows = result.by_alpha(a)
        d = np.array([r["fei_delay" + sfx] for r in rows], dtype=float) * 1e3
        j2 = np.array([r["J2" + sfx] for r in rows], dtype=float)
        label = f"α = {a:g}" + (f", {sfx[1:]}" if sfx else "")
        kw = {"alpha": 0.55, "color": f"C{i}", "label": label, "bins": 20}
        ax1.hist(d[np.isfinite(d)], **kw)
        ax2.hist(j2[np.isfinite(j2)], **kw)
    ax1.set_xlabel("whole-record FEI delay d (ms)")
    ax2.set_xlabel("J2, normalised RMS tracking error (%)")
    for ax in (ax1, ax2):
        ax.set_ylabel("trials")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    n = len(result.rows) // max(1, len(result.alphas))
    fig.suptitle(f"{n} perturbed twins: " + ", ".join(p.key for p in result.perturbations))
    fig.tight_layout()
    paths.append(out / "robustness_hist.png")

    save_figure(fig, paths[-1], 120)
    plt.close(fig)
    if len(result.alphas) > 1:
        summ = result.summary()
        al = np.array(result.alphas)
        fig, axes = plt.subplots(1, 3, figsize=(13, 4))
        for ax, m, scale, label in (
            (axes[0], "fei_delay", 1e3, "FEI delay d (ms)"),
            (axes[1], "J2", 1.0, "J2 (%)"),
        ):
            for j, sfx in enumerate(result.suffixes):
                s = [
                    next(r for r in summ if r["alpha"] == a and r["metric"] == m + sfx) for a in al
                ]
                med = np.array([r["median"] for r in s]) * scale
                lo = np.array([r["p5"] for r in s]) * scale
                hi = np.array([r["p95"] for r in s]) * scale
                name = f" {sfx[1:]}" if sfx else ""
                ax.fill_between(al, lo, hi, alpha=0.3, color=f"C{j}", label=f"5–95 %{name}")
                ax.plot(al, med, "o-", color=f"C{j}", label=f"median{name}")
            ax.set_ylabel(label)
        axes[0].axhline(0.0, color="k", lw=0.6)
        share = [next(r for r in summ if r["alpha"] == a)["share_tripped"] * 100 for a in al]
        axes[2].bar(
            al, share, width=0.6 * float(np.min(np.diff(np.sort(al)))) if al.size > 1 else 1
        )
        axes[2].set_ylabel("trials stopped by a safety rule (%)")
        for ax in axes:
            ax.set_xlabel("inverse-compensation α")
            ax.grid(True, alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle("robustness against α over the same perturbed twins")
        fig.tight_layout()
        paths.append(out / "robustness_alpha.png")

        save_figure(fig, paths[-1], 120)
        plt.close(fig)
    return paths

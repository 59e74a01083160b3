"""Robustness study (``docs/studies.md``): perturbed twins in lockstep through the full chain.

:func:`robustness_study` draws perturbed twins (:mod:`rths_hil.studies.perturbations`:
:class:`Perturbation`, :func:`parse_vary`, benchmark-style :func:`default_perturbations`), runs
each in lockstep through
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
from typing import Any, ClassVar

import numpy as np

from rths_hil.sim_backends.specimen import SPECIMEN_DEFAULTS, KelvinVoigt

from ..config import Config, resolve_channel, set_compensation
from ..errors import InputError
from ..fei import fei
from ..hybrid import build_ground_motion, run
from ..metrics import benchmark_criteria, criteria
from ..plotting import save_figure
from ..records.columns import channel_suffix, column_name
from ..records.recorder import read_run
from ..structures.sdof import BoucWenParams, CRStepper
from .executors import run_cases
from .paper import format_value
from .perturbations import (
    Perturbation,
    _record_channels,
    _set_value,
    _twin_spec,
    channel_suffixes,
    default_perturbations,
    inline_twin,
)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# robustness study: perturbed twins in lockstep through the full chain


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
        chans = _record_channels(cfg)
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
    row = _trial_row(spec, cfg["compensation"]["alpha"], res)
    trip = res.trip
    if chans != [None]:
        row["trip_channel"] = trip.channel if trip is not None else ""
        for ch, entry in zip(chans, cfg["actuators"], strict=True):
            comp = resolve_channel(cfg, entry).config["compensation"]
            row[column_name("alpha", ch)] = float(comp["alpha"]) if comp["enabled"] else 1.0
    nan = math.nan
    for ch in chans:
        target = np.asarray(rec[column_name("target", ch)], dtype=float)
        measured = np.asarray(rec[column_name("measured", ch)], dtype=float)
        n = target.size
        reference = references[channel_suffix(ch)][:n]
        whole = fei(target, measured, fs) if n >= 8 else None
        row[column_name("fei_amplitude", ch)] = whole.amplitude if whole is not None else nan
        row[column_name("fei_delay", ch)] = whole.delay if whole is not None else nan
        row[column_name("fei_f_eq", ch)] = whole.f_eq if whole is not None else nan
        valid = np.asarray(rec[column_name("fei_valid", ch)], dtype=bool)
        a_lo, a_hi = _extremes(
            np.asarray(rec[column_name("fei_amplitude", ch)], dtype=float), valid
        )
        d_lo, d_hi = _extremes(np.asarray(rec[column_name("fei_delay", ch)], dtype=float), valid)
        row[column_name("mwo_amplitude_min", ch)] = a_lo
        row[column_name("mwo_amplitude_max", ch)] = a_hi
        row[column_name("mwo_delay_min", ch)] = d_lo
        row[column_name("mwo_delay_max", ch)] = d_hi
        ok = n >= BENCHMARK_MIN_STEPS
        paper = criteria(target, measured, fs, reference) if ok else {}
        bench = benchmark_criteria(target, measured, fs, reference) if ok else {}
        for i in range(1, 10):
            row[column_name(f"J{i}", ch)] = float(paper.get(f"J{i}", nan))
        for i in range(1, 10):
            row[column_name(f"bench_J{i}", ch)] = float(bench.get(f"J{i}", nan))
        force = rec[column_name("force", ch)]
        row[column_name("peak_target", ch)] = float(np.max(np.abs(target))) if n else nan
        row[column_name("peak_reference", ch)] = float(np.max(np.abs(reference))) if n else nan
        row[column_name("peak_force", ch)] = float(np.max(np.abs(force))) if n else nan
    return row


def _trial_row(spec: Any, alpha: float, res: Any) -> dict[str, Any]:
    """The head of a trial's row: its index, α, the drawn values and how its run ended."""
    row: dict[str, Any] = {"trial": spec.index, "alpha": float(alpha)}
    row.update({k: float(v) for k, v in spec.values.items()})
    trip = res.trip
    row.update(
        status=res.status,
        steps=int(res.steps),
        trip_rule=trip.rule if trip is not None else "",
        trip_time=float(trip.time) if trip is not None else math.nan,
        trip_reason=trip.reason if trip is not None else "",
    )
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


class TrialRows:
    """The rows of trials on perturbed twins, one per trial and group (an α, a method).

    Attributes
    ----------
    rows : list of dict
        One per group × trial, ordered by group (as given) then trial.
    keys : list of str
        The varied keys (columns after ``alpha``).
    suffixes : list of str
        Channel column suffixes (``[""]`` for one channel).
    seed : int
        Seed of the draws.
    """

    rows: list[dict[str, Any]]
    keys: list[str]
    suffixes: list[str]
    seed: int
    #: the row key naming a row's group, and the metrics :meth:`summary` summarises
    group_key: ClassVar[str]
    metrics: ClassVar[tuple[str, ...]]

    @property
    def groups(self) -> Sequence[Any]:
        """The groups, in order."""
        raise NotImplementedError

    @property
    def columns(self) -> list[str]:
        """``trials.csv`` columns in order."""
        raise NotImplementedError

    def summary(self) -> list[dict[str, Any]]:
        """Per group and metric (per channel): median, 5th and 95th percentiles over the trials
        with a value, their count, and per group the share of trials a safety rule stopped."""
        out = []
        for g in self.groups:
            rows = [r for r in self.rows if r[self.group_key] == g]
            tripped = sum(r["status"] == "trip" for r in rows)
            for m in (column_name(m, sfx[1:]) for sfx in self.suffixes for m in self.metrics):
                out.append({self.group_key: g, **metric_summary(rows, m, tripped)})
        return out


@dataclass
class RobustnessResult(TrialRows):
    """Outcome of :func:`robustness_study`: :class:`TrialRows` grouped by α.

    Attributes
    ----------
    perturbations : list of Perturbation
    alphas : list of float
        The α of the runs (the configuration's when not varied).
    """

    group_key = "alpha"
    metrics = SUMMARY_METRICS

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

    @property
    def groups(self) -> list[float]:
        """The α of the runs."""
        return self.alphas

    def by_alpha(self, alpha: float) -> list[dict[str, Any]]:
        """The rows run with ``alpha``."""
        return [r for r in self.rows if r["alpha"] == alpha]


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
    for ch in (sfx[1:] for sfx in suffixes):  # the channel of suffix ``_<ch>``
        out += [column_name(c, ch) for c in ("alpha", *_CHANNEL_COLUMNS)]
    return out


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


def write_trials_csv(path: str | Path, result: TrialRows) -> None:
    """``trials.csv``: one line per row (trial × α or method), full-precision numbers
    (``repr``; NaN where a row has no value)."""
    cols = result.columns
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in result.rows:
            w.writerow([exact_text(r.get(c, math.nan)) for c in cols])


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
    series = [(a, sfx[1:]) for a in result.alphas for sfx in result.suffixes]
    for i, (a, ch) in enumerate(series):
        rows = result.by_alpha(a)
        d = np.array([r[column_name("fei_delay", ch)] for r in rows], dtype=float) * 1e3
        j2 = np.array([r[column_name("J2", ch)] for r in rows], dtype=float)
        label = f"α = {a:g}" + (f", {ch}" if ch else "")
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
    if len(result.alphas) > 1:
        summ = result.summary()
        al = np.array(result.alphas)
        fig, axes = plt.subplots(1, 3, figsize=(13, 4))
        for ax, m, scale, label in (
            (axes[0], "fei_delay", 1e3, "FEI delay d (ms)"),
            (axes[1], "J2", 1.0, "J2 (%)"),
        ):
            for j, ch in enumerate(sfx[1:] for sfx in result.suffixes):
                col = column_name(m, ch)
                s = [next(r for r in summ if r["alpha"] == a and r["metric"] == col) for a in al]
                med = np.array([r["median"] for r in s]) * scale
                lo = np.array([r["p5"] for r in s]) * scale
                hi = np.array([r["p95"] for r in s]) * scale
                name = f" {ch}" if ch else ""
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
    return paths

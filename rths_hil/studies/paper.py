"""The FEI paper's computational study (Section 4) and robustness studies on perturbed twins.

Set-up (the FEI paper's Fig. 4.1): an SDOF structure (mass, 2 % damping, linear or Bouc-Wen per Eq.
4.1–4.2) is driven by a recorded ground motion sampled at 1024 Hz and integrated with the CR
algorithm; its displacement is the *target*. The actuator is a transport delay τ (fractional, not
rounded to samples) followed by a gain k_p: *measured* = k_p · target(t − τ). The moving-window FEI
(:func:`rths_hil.fei.moving_fei`) of the pair should return A = k_p and d = τ in every window.

Window-size study (the FEI paper's Fig. 4.2)
---------------------------------
For each record and natural frequency fn (period Tn), windows ``t_w = Tn·(1 + 0.1 j)``, j = 0, 1,
…, are tried in turn; the answer is the first one that satisfies the :class:`WindowCriterion`:

* **error** of a window: ``|d − τ| / τ`` (relative delay error);
* **windows that count**: every full window (the first ends at t = t_w; there are no partial
  windows) that the FEI marks valid *and* whose target level is at least ``min_level`` times the
  largest window level of the record (default 0.1: the strong-motion part; the quiet lead-in
  before the first arrivals, where a relative floor on a running peak lets noise-level windows
  through, and the decayed tail are left out). ``min_level = 0`` counts every valid window;
* **statistic** over the counted windows: ``"max"`` (every window within tolerance) or a
  percentile ``"pNN"`` (default ``"p95"``: 95 % of the windows within tolerance);
* the window passes when the statistic is ≤ ``tolerance`` (default 1 %, the FEI paper: 0.01 ms of
  1 ms).

If no window up to ``max_periods``·Tn (and half the record) passes, t_w is NaN.

Speed-ups that do not change the answer (checked against hop = 8 samples without decimation:
statistics within 0.1 percentage point): both signals are decimated to the largest power-of-two
factor (≤ 8) that keeps ``fs/decimate ≥ 64·fn``, and windows are evaluated every ``N/64`` samples
instead of every sample (the FEI of overlapping windows varies smoothly with the end time).

Accuracy study (the FEI paper's Table 4.1, Fig. 4.6)
-----------------------------------------
For each fn, linear and Bouc-Wen structures, gain 1.1 and delay 5 ms, window 3·Tn, hop 1 (the
the FEI paper's MWO, Eq. 7): the maximum over the counted windows (same selection as above) of the
amplitude error ``|A − k_p|/k_p`` and the delay error ``|d − τ|/τ``, in %.

Robustness study (``docs/studies.md``)
--------------------------------------
:func:`robustness_study` draws perturbed twins (:class:`Perturbation`, :func:`parse_vary`,
benchmark-style :func:`default_perturbations`), runs each in lockstep through
:func:`rths_hil.loop.run` (:func:`robustness_trial`) and evaluates it against the reference
structure (:func:`reference_response`) with J1–J9 as the RTHS benchmark's paper and evaluation
script define them (:mod:`rths_hil.metrics`), the whole-record FEI and the MWO extremes.

All studies run their cases through an executor (default
``concurrent.futures.ProcessPoolExecutor(max_workers=2)``); any
:class:`concurrent.futures.Executor` can be passed, e.g. a Dask one from :func:`open_executor`
(a ``LocalCluster`` on 127.0.0.1 or a lab's scheduler). Progress goes to stderr through tqdm.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
import re
import sys
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .fei import MovingFEIResult, moving_fei
from .groundmotion import GroundMotion
from .structure import BoucWenParams, simulate_sdof

log = logging.getLogger(__name__)

_STAT_RE = re.compile(r"^(max|p(\d+(?:\.\d+)?))$")


@dataclass(frozen=True)
class WindowCriterion:
    """Which windows count and how their delay errors are summarised (see module docstring).

    Attributes
    ----------
    tolerance : float
        Largest admissible statistic of the relative delay error (0.01 = 1 %).
    statistic : str
        ``"max"`` or ``"pNN"`` (NN-th percentile, e.g. ``"p95"``).
    min_level : float
        Count a valid window only if its target level is ≥ ``min_level`` × the record's largest
        window level (0 counts every valid window).
    """

    tolerance: float = 0.01
    statistic: str = "p95"
    min_level: float = 0.1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise InputError(f"criterion tolerance must be > 0, got {self.tolerance!r}")
        m = _STAT_RE.match(str(self.statistic))
        if not m or (m.group(2) is not None and not 0 < float(m.group(2)) <= 100):
            raise InputError(
                f"statistic must be 'max' or 'pNN' with 0 < NN ≤ 100, got {self.statistic!r}"
            )
        if not (0.0 <= self.min_level < 1.0):
            raise InputError(f"min_level must lie in [0, 1), got {self.min_level!r}")

    def counted(self, res: MovingFEIResult) -> np.ndarray:
        """Boolean mask of the windows that count."""
        if len(res) == 0 or not np.any(res.valid):
            return np.zeros(len(res), dtype=bool)
        peak = float(np.max(res.level))
        return res.valid & (res.level >= self.min_level * peak)

    def summarize(self, errors: np.ndarray) -> float:
        """The statistic of ``errors`` (NaN if empty)."""
        if errors.size == 0:
            return math.nan
        if self.statistic == "max":
            return float(np.max(errors))
        return float(np.percentile(errors, float(self.statistic[1:])))

    def delay_error(self, res: MovingFEIResult, delay: float) -> tuple[float, int]:
        """(statistic of |d − τ|/τ over the counted windows, number of counted windows)."""
        mask = self.counted(res)
        err = np.abs(res.delay[mask] - delay) / abs(delay)
        return self.summarize(err), int(mask.sum())


def auto_decimation(fs: float, fn: float, max_factor: int = 8) -> int:
    """Largest power of two ≤ ``max_factor`` with ``fs/q ≥ 64·fn`` (1 if none)."""
    q = 1
    while q * 2 <= max_factor and fs / (q * 2) >= 64.0 * fn:
        q *= 2
    return q


def _actuator(target: np.ndarray, fs: float, gain: float, delay: float) -> np.ndarray:
    from rths_hil.sim_backends.delay import DelayGain

    return DelayGain(delay=delay, gain=gain, dt=1.0 / fs).simulate(target)


def _check_common(fn: float, zeta: float, gain: float, delay: float) -> None:
    if not (math.isfinite(fn) and fn > 0):
        raise InputError(f"natural frequency must be > 0 Hz, got {fn!r}")
    if not (math.isfinite(zeta) and zeta >= 0):
        raise InputError(f"damping ratio must be ≥ 0, got {zeta!r}")
    if not (math.isfinite(gain) and gain > 0):
        raise InputError(f"actuator gain must be > 0, got {gain!r}")
    if not (math.isfinite(delay) and delay > 0):
        raise InputError(
            f"actuator delay must be > 0 s (the error is relative to it), got {delay!r}"
        )


# --------------------------------------------------------------------------------------------
# window-size study (Fig. 4.2)


@dataclass
class WindowSizeResult:
    """Outcome of the window search for one record and one natural frequency.

    Attributes
    ----------
    record : str
        Ground-motion name.
    fn_hz, tn_s : float
        Natural frequency and period.
    structure : str
        ``"linear"`` or ``"bouc-wen"``.
    window_s, window_periods : float
        Smallest passing window (s and multiples of Tn); NaN if none up to the cap.
    delay_error_pct : float
        The criterion's statistic (%) at the chosen window (at the largest tried if none passed).
    amplitude_error_pct : float
        Same statistic of ``|A − k_p|/k_p`` (%), for information.
    n_windows : int
        Windows counted at the chosen window.
    tried : int
        Number of window sizes evaluated.
    """

    record: str
    fn_hz: float
    tn_s: float
    structure: str
    window_s: float
    window_periods: float
    delay_error_pct: float
    amplitude_error_pct: float
    n_windows: int
    tried: int


def window_size_for(
    gm: GroundMotion,
    fn: float,
    *,
    zeta: float = 0.02,
    gain: float = 1.0,
    delay: float = 1e-3,
    criterion: WindowCriterion | None = None,
    bouc_wen: BoucWenParams | bool | None = None,
    start_periods: float = 1.0,
    step_periods: float = 0.1,
    max_periods: float = 10.0,
    decimate: int | None = None,
    hop: int | None = None,
) -> WindowSizeResult:
    """Smallest moving window meeting ``criterion`` for one record and fn (FEI paper, Fig. 4.2).

    Parameters
    ----------
    gm : GroundMotion
        Ground motion, already at the simulation rate (the FEI paper: 1024 Hz) and scale.
    fn : float
        Natural frequency (Hz).
    zeta, gain, delay : float
        Damping ratio, actuator gain k_p and delay τ (s) (the FEI paper: 0.02, 1, 1 ms).
    criterion : WindowCriterion, optional
        Default: 1 % on the 95th percentile of strong-motion windows.
    bouc_wen : BoucWenParams or bool, optional
        Bouc-Wen structure (``True``: the FEI paper's parameters) instead of linear.
    start_periods, step_periods, max_periods : float
        Window sizes tried: ``Tn·(start + j·step)`` up to ``max_periods·Tn`` (and at most half
        the record).
    decimate, hop : int, optional
        FEI decimation and hop; ``None`` chooses them as described in the module docstring.
    """
    _check_common(fn, zeta, gain, delay)
    crit = criterion or WindowCriterion()
    fs = gm.fs
    target = simulate_sdof(gm.accel, fs, fn, zeta, bouc_wen=bouc_wen)
    measured = _actuator(target, fs, gain, delay)
    q = auto_decimation(fs, fn) if decimate is None else int(decimate)
    tn = 1.0 / fn
    limit = min(max_periods * tn, 0.5 * gm.duration)
    structure = "bouc-wen" if bouc_wen else "linear"
    j, tried = 0, 0
    last = (math.nan, math.nan, 0)
    while True:
        periods = round(start_periods + j * step_periods, 10)
        tw = periods * tn
        if tw > limit + 1e-12:
            break
        n_dec = round(tw * fs / q)
        h = max(1, n_dec // 64) if hop is None else int(hop)
        res = moving_fei(target, measured, fs, tw, hop=h, decimate=q)
        tried += 1
        err, count = crit.delay_error(res, delay)
        mask = crit.counted(res)
        amp_err = crit.summarize(np.abs(res.amplitude[mask] - gain) / gain)
        last = (err, amp_err, count)
        if count > 0 and err <= crit.tolerance:
            return WindowSizeResult(
                gm.name, fn, tn, structure, tw, periods, 100 * err, 100 * amp_err, count, tried
            )
        j += 1
    return WindowSizeResult(
        gm.name, fn, tn, structure, math.nan, math.nan, 100 * last[0], 100 * last[1], last[2], tried
    )


class SerialExecutor(Executor):
    """Runs each task in the calling process at submit time (for tests and ``--workers 1``)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as exc:  # delivered through the future, like a pool
            fut.set_exception(exc)
        return fut


def make_executor(workers: int) -> Executor:
    """``SerialExecutor`` for 1 worker, else ``ProcessPoolExecutor(max_workers=workers)``."""
    if int(workers) != workers or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    return SerialExecutor() if workers == 1 else ProcessPoolExecutor(max_workers=int(workers))


def _default_executor() -> Executor:
    return ProcessPoolExecutor(max_workers=2)


def _run_cases(
    func,
    cases: Sequence[tuple],
    executor: Executor | None,
    progress: bool,
    desc: str,
    on_result=None,
):
    """Submit ``func(*case)`` for each case; return results in case order.

    ``on_result(index, result)`` is called as each case completes (in completion order).
    """
    from tqdm import tqdm

    own = executor is None
    ex = _default_executor() if own else executor
    results: list = [None] * len(cases)
    try:
        futures = {ex.submit(func, *case): i for i, case in enumerate(cases)}
        bar = tqdm(total=len(cases), desc=desc, file=sys.stderr, disable=not progress, unit="case")
        with bar:
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                if on_result is not None:
                    on_result(futures[fut], results[futures[fut]])
                bar.update(1)
    finally:
        if own:
            ex.shutdown(wait=True, cancel_futures=True)
    return results


def _ws_case(gm: GroundMotion, fn: float, kwargs: dict) -> WindowSizeResult:
    return window_size_for(gm, fn, **kwargs)


def window_size_study(
    records: Sequence[GroundMotion],
    fns: Sequence[float],
    *,
    executor: Executor | None = None,
    progress: bool = True,
    **kwargs,
) -> list[WindowSizeResult]:
    """Run :func:`window_size_for` for every record × fn (the FEI paper's Fig. 4.2), in parallel.

    Parameters
    ----------
    records : sequence of GroundMotion
        At the simulation rate and scale.
    fns : sequence of float
        Natural frequencies (Hz) (the FEI paper: 0.2 … 5.1 Hz by 0.1).
    executor : concurrent.futures.Executor, optional
        Default: a ``ProcessPoolExecutor(max_workers=2)`` created and shut down here.
    progress : bool
        Show a tqdm progress bar on stderr.
    **kwargs
        Passed to :func:`window_size_for`.

    Returns
    -------
    list of WindowSizeResult
        Record-major order.
    """
    if not records:
        raise InputError("window-size study: give at least one ground motion")
    for fn in fns:
        _check_common(
            fn, kwargs.get("zeta", 0.02), kwargs.get("gain", 1.0), kwargs.get("delay", 1e-3)
        )
        for gm in records:
            if fn >= gm.fs / 2:
                raise InputError(f"natural frequency {fn:g} Hz is above the Nyquist frequency")
    cases = [(gm, float(fn), kwargs) for gm in records for fn in fns]
    return _run_cases(_ws_case, cases, executor, progress, "window-size")


# --------------------------------------------------------------------------------------------
# accuracy study (Table 4.1, Fig. 4.6)


@dataclass
class AccuracyResult:
    """One row of the FEI paper's Table 4.1 plus the time histories for Fig. 4.6.

    Attributes
    ----------
    fn_hz : float
    structure : str
        ``"linear"`` or ``"bouc-wen"``.
    window_s : float
    max_err_amplitude_pct, max_err_delay_pct : float
        Maximum over the counted windows of ``|A − k_p|/k_p`` and ``|d − τ|/τ`` (%).
    peak_displacement_m : float
        Peak |target| (m), to show whether the structure yielded.
    t_end, amplitude, delay : ndarray
        Moving-FEI histories (NaN where a window is invalid).
    counted : ndarray of bool
        Windows included in the maxima.
    """

    fn_hz: float
    structure: str
    window_s: float
    max_err_amplitude_pct: float
    max_err_delay_pct: float
    peak_displacement_m: float
    t_end: np.ndarray = field(repr=False)
    amplitude: np.ndarray = field(repr=False)
    delay: np.ndarray = field(repr=False)
    counted: np.ndarray = field(repr=False)

    def row(self) -> dict[str, float | str]:
        """The CSV row (columns of :data:`ACCURACY_COLUMNS`)."""
        d = asdict(self)
        return {k: d[k] for k in ACCURACY_COLUMNS}


ACCURACY_COLUMNS = (
    "fn_hz",
    "structure",
    "window_s",
    "max_err_amplitude_pct",
    "max_err_delay_pct",
    "peak_displacement_m",
)


def accuracy_case(
    gm: GroundMotion,
    fn: float,
    *,
    bouc_wen: BoucWenParams | bool | None = None,
    zeta: float = 0.02,
    gain: float = 1.1,
    delay: float = 5e-3,
    window_s: float | None = None,
    hop: int = 1,
    min_level: float = 0.1,
) -> AccuracyResult:
    """Maximum FEI errors for one structure (FEI paper, Table 4.1); ``window_s``: default 3·Tn."""
    _check_common(fn, zeta, gain, delay)
    tw = 3.0 / fn if window_s is None else float(window_s)
    if not (math.isfinite(tw) and tw > 0):
        raise InputError(f"window must be > 0 s, got {window_s!r}")
    if tw > gm.duration:
        raise InputError(
            f"window of {tw:g} s is longer than the record {gm.name!r} ({gm.duration:g} s)"
        )
    fs = gm.fs
    target = simulate_sdof(gm.accel, fs, fn, zeta, bouc_wen=bouc_wen)
    measured = _actuator(target, fs, gain, delay)
    res = moving_fei(target, measured, fs, tw, hop=hop)
    mask = WindowCriterion(statistic="max", min_level=min_level).counted(res)
    a_err = np.abs(res.amplitude[mask] - gain) / gain
    d_err = np.abs(res.delay[mask] - delay) / delay
    return AccuracyResult(
        fn,
        "bouc-wen" if bouc_wen else "linear",
        tw,
        100 * float(np.max(a_err)) if a_err.size else math.nan,
        100 * float(np.max(d_err)) if d_err.size else math.nan,
        float(np.max(np.abs(target))),
        res.t_end,
        res.amplitude,
        res.delay,
        mask,
    )


def _acc_case(gm: GroundMotion, fn: float, bw: bool, kwargs: dict) -> AccuracyResult:
    return accuracy_case(gm, fn, bouc_wen=bw or None, **kwargs)


def accuracy_study(
    gm: GroundMotion,
    fns: Sequence[float] = (0.5, 0.7, 1.0),
    *,
    window_periods: float | None = 3.0,
    window_s: float | None = None,
    executor: Executor | None = None,
    progress: bool = True,
    **kwargs,
) -> list[AccuracyResult]:
    """The FEI paper's Table 4.1: linear and Bouc-Wen SDOF for each fn, rows ordered by fn then
    structure.

    The window is ``window_periods``·Tn unless ``window_s`` (s, same for every fn) is given.
    Other keyword arguments go to :func:`accuracy_case` (gain, delay, zeta, hop, min_level).
    """
    cases = []
    for fn in fns:
        if not (math.isfinite(fn) and fn > 0):
            raise InputError(f"natural frequency must be > 0 Hz, got {fn!r}")
        tw = window_s if window_s is not None else window_periods / fn
        if tw > gm.duration:
            raise InputError(
                f"window of {tw:g} s (fn = {fn:g} Hz) is longer than the record ({gm.duration:g} s)"
            )
        for bw in (False, True):
            cases.append((gm, float(fn), bw, {**kwargs, "window_s": tw}))
    return _run_cases(_acc_case, cases, executor, progress, "accuracy")


# --------------------------------------------------------------------------------------------
# output


def write_window_size_csv(path: str | Path, rows: Sequence[WindowSizeResult]) -> None:
    """CSV with one line per record × fn (columns = :class:`WindowSizeResult` fields)."""
    import csv

    names = list(WindowSizeResult.__dataclass_fields__)
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for r in rows:
            w.writerow([_fmt(getattr(r, n)) for n in names])


def write_accuracy_csv(path: str | Path, rows: Sequence[AccuracyResult]) -> None:
    """CSV with the columns of :data:`ACCURACY_COLUMNS` (the FEI paper's Table 4.1)."""
    import csv

    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(ACCURACY_COLUMNS)
        for r in rows:
            w.writerow([_fmt(v) for v in r.row().values()])


def _fmt(v) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.6g}"
    return str(v)


def plot_window_size(path: str | Path, rows: Sequence[WindowSizeResult]) -> None:
    """Fig. 4.2-style PNG: t_w against fn (a) and against Tn (b), one line per record."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    keys = sorted({(r.record, r.structure) for r in rows})
    for rec, st in keys:
        sel = sorted(
            (r for r in rows if r.record == rec and r.structure == st), key=lambda r: r.fn_hz
        )
        fn = np.array([r.fn_hz for r in sel])
        tw = np.array([r.window_s for r in sel])
        label = rec if len({k[1] for k in keys}) == 1 else f"{rec} ({st})"
        ax1.plot(fn, tw, marker="o", ms=3, label=label)
        ax2.plot(1 / fn, tw, marker="o", ms=3, label=label)
    tn = np.linspace(0.19, 5.1, 50)
    for c, ls in ((2, ":"), (3, "--")):
        ax2.plot(tn, c * tn, "k", ls=ls, lw=0.8, label=f"{c}·Tn")
    ax1.set_xlabel("natural frequency fn (Hz)")
    ax1.set_ylabel("window size t_w (s)")
    ax1.set_title("(a) t_w against fn")
    ax2.set_xlabel("natural period Tn (s)")
    ax2.set_ylabel("window size t_w (s)")
    ax2.set_title("(b) t_w against Tn")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    from .plotting import save_figure

    save_figure(fig, path, 120)
    plt.close(fig)


def plot_accuracy(
    path: str | Path, rows: Sequence[AccuracyResult], gain: float, delay: float
) -> None:
    """Fig. 4.6-style PNG: A(t) and d(t) for the linear (a, b) and Bouc-Wen (c, d) structures."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex=True)
    for col, st in enumerate(("linear", "bouc-wen")):
        for r in (r for r in rows if r.structure == st):
            axes[0, col].plot(r.t_end, r.amplitude, lw=0.8, label=f"{r.fn_hz:g} Hz")
            axes[1, col].plot(r.t_end, 1e3 * r.delay, lw=0.8, label=f"{r.fn_hz:g} Hz")
        axes[0, col].axhline(gain, color="k", lw=0.6, ls="--")
        axes[1, col].axhline(1e3 * delay, color="k", lw=0.6, ls="--")
        axes[0, col].set_ylabel("A")
        axes[1, col].set_ylabel("d (ms)")
        axes[1, col].set_xlabel("window end time (s)")
        axes[0, col].set_ylim(gain * 0.97, gain * 1.03)
        axes[1, col].set_ylim(0.7e3 * delay, 1.3e3 * delay)
    titles = ("(a) A, linear", "(c) A, Bouc-Wen", "(b) d, linear", "(d) d, Bouc-Wen")
    for ax, title in zip(axes.flat, (titles[0], titles[1], titles[2], titles[3]), strict=True):
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    from .plotting import save_figure

    save_figure(fig, path, 120)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# executors: local processes, a local Dask cluster or a lab's Dask scheduler


@contextlib.contextmanager
def open_executor(scheduler: str | None = None, workers: int = 2) -> Iterator[Executor]:
    """An executor for the studies, closed (with its cluster) on exit.

    Parameters
    ----------
    scheduler : str, optional
        ``None``: :func:`make_executor` (in-process for 1 worker, else a process pool).
        ``"local"``: a ``dask.distributed.LocalCluster`` of ``workers`` single-threaded worker
        processes, scheduler and workers bound to 127.0.0.1 over TCP. Anything else is the
        address of a running Dask scheduler (``tcp://host:8786``; ``host:8786`` means TCP),
        e.g. a lab's cluster started with ``dask scheduler`` and ``dask worker --nthreads 1``.
    workers : int
        Worker processes of a local pool or cluster (ignored with an address).

    Yields
    ------
    concurrent.futures.Executor
        For Dask, ``Client.get_executor(pure=False)``: every submitted task runs, and a task
        whose worker dies is rerun on another one (the scheduler's ``allowed-failures``).
    """
    if scheduler is None:
        ex = make_executor(workers)
        try:
            yield ex
        finally:
            ex.shutdown(wait=True, cancel_futures=True)
        return
    if int(workers) != workers or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    from .errors import require

    require("studies", "a Dask scheduler (--scheduler, study robustness)")
    from distributed import Client, LocalCluster

    if logging.getLogger().getEffectiveLevel() > logging.INFO:
        logging.getLogger("distributed").setLevel(logging.WARNING)  # no start/stop chatter
    cluster = None
    if scheduler == "local":
        cluster = LocalCluster(
            n_workers=int(workers),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            protocol="tcp",
            dashboard_address=None,
        )
        client = Client(cluster)
        client.wait_for_workers(int(workers))
    else:
        address = scheduler if "://" in scheduler else f"tcp://{scheduler}"
        if not _ADDRESS_RE.match(address):
            raise InputError(
                f"--scheduler {scheduler!r}: expected 'local' or a scheduler address "
                "such as tcp://host:8786"
            )
        try:
            client = Client(address, timeout=10)
        except (OSError, TimeoutError) as exc:
            raise InputError(
                f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})"
            ) from None
        n = len(client.scheduler_info().get("workers", {}))
        log.info("Dask scheduler %s with %d worker(s)", address, n)
        if n == 0:
            log.warning("the Dask scheduler at %s has no workers yet; tasks will wait", address)
    try:
        yield client.get_executor(pure=False)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


_ADDRESS_RE = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://[^\s/:]+(:\d+)?/?$")


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


def channel_suffixes(cfg) -> list[str]:
    """Record-column suffixes of the channels: ``[""]`` for one channel, else ``_<name>``
    (as the loop names them, docs/channels.md)."""
    names = _channel_names(cfg)
    return [f"_{n}" for n in names] if len(names) > 1 else [""]


def _set_value(cfg, key: str, value: float) -> None:
    """Set ``key`` (a checked path) to ``value`` in a Config, in place.

    ``twin.*`` sets the top-level twin and, in a configuration with ``[[actuators]]`` (whose
    twins :func:`_inline_twin` made explicit), every channel's twin;
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
        from .config import set_compensation

        set_compensation(cfg["compensation"], parts[1], value, cfg["loop"]["fs"])
    else:
        cfg[parts[0]][parts[1]] = float(value)


def _inline_twin(cfg):
    """A copy of ``cfg`` whose twin is given by inline tables (a ``twin.model`` file is read)."""
    from rths_hil.sim_backends.modelfile import load_model

    from .config import Config, resolve_channel

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
    from rths_hil.sim_backends.modelfile import load_model

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
    from rths_hil.sim_backends.registry import MODEL_ALIASES, MODELS

    model = tw["actuator"].get("model", "delay_gain")
    model = MODEL_ALIASES.get(model, model)
    params = MODELS[model].params if model in MODELS else {}
    keys = [f"{prefix}twin.actuator.{k}" for k in ("delay", "gain", *params)]
    keys += [f"{prefix}twin.specimen.{k}" for k in ("stiffness", "damping", "mass")]
    keys += [f"{prefix}twin.{k}" for k in _TWIN_DOMAIN if k.startswith("sensor.")]
    return keys


def _varyable_keys(cfg) -> list[str]:
    from .config import SCHEMA

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
    from .config import SCHEMA
    from .units import parse_time

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
    values = []
    for p in parts:
        try:
            if unit == "s":
                v = parse_time(p, key)
            elif unit == "m":
                from .units import parse_length

                v = parse_length(p, key)
            elif unit == "m/s²":
                from .units import parse_accel

                v = parse_accel(p, key)
            elif unit in ("N", "m/s"):
                from .units import parse_force, parse_velocity

                v = (parse_force if unit == "N" else parse_velocity)(p, key)
            else:
                v = float(p)
        except (InputError, ValueError):
            what = f"a number in {unit}" if unit else "a number"
            raise InputError(f"{where}: {p!r} is not {what}") from None
        if not math.isfinite(v):
            raise InputError(f"{where}: {p!r} is not finite")
        values.append(float(v))
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
    from .config import SCHEMA, _coerce, _cross_check

    trial = copy.deepcopy(cfg)
    for key, v in values.items():
        parts = key.split(".")
        if _twin_key(key) is None:
            try:
                _coerce(SCHEMA[parts[0]][parts[1]], v, key)
            except InputError as exc:
                raise InputError(f"{where}: {exc}") from None
        _set_value(trial, key, v)
    try:
        _cross_check(trial)
        for name in _channel_names(trial) or [None]:
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
        from rths_hil.sim_backends.models import BENCHMARK_NOMINAL

        p = {**BENCHMARK_NOMINAL, **spec.actuator.params}
        for name, sigma in (("a3", 1.3), ("beta1", 3.3), ("beta2", 3.3e3)):
            normal(f"twin.actuator.{name}", p[name], sigma)
        if "specimen_stiffness" in spec.actuator.params or k is None:
            normal("twin.actuator.specimen_stiffness", p["specimen_stiffness"], 50e3)
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
    import os
    import shutil
    import tempfile

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
    run of :func:`rths_hil.loop.run` with such a plant (``tests/test_robustness.py``).

    Parameters
    ----------
    cfg : Config
        Resolved configuration with an inline twin (see :func:`parse_vary`).
    n : int, optional
        Steps (default: as the loop, from ``loop.duration`` or the record).
    """
    from rths_hil.sim_backends.specimen import SPECIMEN_DEFAULTS, KelvinVoigt

    from .loop import build_ground_motion
    from .structure import CRStepper

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

    For any structure and any number of channels: a lockstep run of :func:`rths_hil.loop.run`
    in which every channel's twin keeps its specimen but achieves each command exactly
    (``delay_gain`` with zero delay and unit gain, no effects, no sensor noise) and
    compensation is off, so that the target each channel is given is x_r = T·u of the
    numerical substructure coupled to ideal actuators and the specimens (Silva et al. 2020,
    Eqs. 15 and 18). Returns ``{suffix: target}`` for the suffixes of
    :func:`channel_suffixes`.
    """
    from .loop import run
    from .recorder import read_run

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
    return {sfx: np.asarray(rec["target" + sfx], dtype=float) for sfx in channel_suffixes(cfg)}


def _extremes(values: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    v = values[valid & np.isfinite(values)]
    return (float(v.min()), float(v.max())) if v.size else (math.nan, math.nan)


def robustness_trial(spec: TrialSpec) -> dict[str, Any]:
    """Run one perturbed trial in lockstep through :func:`rths_hil.loop.run`; return its row.

    The run's record goes to a scratch directory that is removed afterwards. The row has the
    trial's parameters, how it ended (``status``, the tripped rule, its time and reason), the
    whole-record FEI (the FEI paper's Eq. 2.1–2.5: A, d, f_eq), the extremes of the online
    moving-window FEI (MWO) over its valid windows, J1–J9 with the paper's numbering
    (:func:`rths_hil.metrics.criteria`, J1 in s) and as the benchmark's script computes them
    (:func:`rths_hil.metrics.benchmark_criteria`, ``bench_J1`` in ms), and the peaks.
    """
    import os
    import tempfile

    from .fei import fei
    from .loop import run
    from .metrics import benchmark_criteria, criteria
    from .recorder import read_run

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
        from .config import resolve_channel

        row["trip_channel"] = trip.channel if trip is not None else ""
        for sfx, entry in zip(sfx_all, cfg["actuators"], strict=True):
            comp = resolve_channel(cfg, entry).config["compensation"]
            row["alpha" + sfx] = float(comp["alpha"]) if comp["enabled"] else 1.0
    nan = math.nan
    for sfx in sfx_all:
        target = np.asarray(rec["target" + sfx], dtype=float)
        measured = np.asarray(rec["measured" + sfx], dtype=float)
        n = target.size
        reference = references[sfx][:n]
        whole = fei(target, measured, fs) if n >= 8 else None
        row["fei_amplitude" + sfx] = whole.amplitude if whole is not None else nan
        row["fei_delay" + sfx] = whole.delay if whole is not None else nan
        row["fei_f_eq" + sfx] = whole.f_eq if whole is not None else nan
        valid = np.asarray(rec["fei_valid" + sfx], dtype=bool)
        a_lo, a_hi = _extremes(np.asarray(rec["fei_amplitude" + sfx], dtype=float), valid)
        d_lo, d_hi = _extremes(np.asarray(rec["fei_delay" + sfx], dtype=float), valid)
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
        row["peak_force" + sfx] = float(np.max(np.abs(rec["force" + sfx]))) if n else nan
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
                v = np.array([r[m] for r in rows], dtype=float)
                v = v[np.isfinite(v)]
                p5, p50, p95 = np.percentile(v, [5, 50, 95]) if v.size else (math.nan,) * 3
                out.append(
                    {
                        "alpha": alpha,
                        "metric": m,
                        "median": float(p50),
                        "p5": float(p5),
                        "p95": float(p95),
                        "n": int(v.size),
                        "trials": len(rows),
                        "share_tripped": tripped / len(rows) if rows else math.nan,
                    }
                )
        return out


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
    base = _inline_twin(cfg)
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
            from .config import set_compensation

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
    base = _inline_twin(cfg)
    perts = list(perturbations) if perturbations is not None else default_perturbations(base)
    specs = plan_trials(base, perts, trials, seed, alphas, duration)
    rows = _run_cases(
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
    import csv

    cols = result.columns
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in result.rows:
            w.writerow([_exact(r[c]) for c in cols])


def _exact(v) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else repr(v)
    return str(v)


def write_summary(path_csv: str | Path, result: RobustnessResult) -> None:
    """``summary.csv``: α, metric, median, p5, p95, n, trials, share_tripped."""
    import csv

    rows = result.summary()
    cols = ["alpha", "metric", "median", "p5", "p95", "n", "trials", "share_tripped"]
    with Path(path_csv).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow([_fmt(r[c]) if isinstance(r[c], float) else r[c] for c in cols])


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
    from .plotting import save_figure

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
        from .plotting import save_figure

        save_figure(fig, paths[-1], 120)
        plt.close(fig)
    return paths

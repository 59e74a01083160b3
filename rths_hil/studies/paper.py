"""The FEI paper's computational study (Section 4): window size and accuracy of the FEI.

Set-up (the FEI paper's Fig. 4.1): an SDOF structure (mass, 2 % damping, linear or Bouc-Wen per Eq.
4.1–4.2) is driven by a recorded ground motion sampled at 1024 Hz and integrated with the CR
algorithm; its displacement is the *target*. The actuator is a transport delay τ (fractional, not
rounded to samples) followed by a gain k_p: *measured* = k_p · target(t − τ). The moving-window FEI
(:func:`rths_hil.fei.moving_fei`) of the pair should return A = k_p and d = τ in every window.

Window-size study (the FEI paper's Fig. 4.2)
--------------------------------------------
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
----------------------------------------------------
For each fn, linear and Bouc-Wen structures, gain 1.1 and delay 5 ms, window 3·Tn, hop 1 (the
FEI paper's MWO, Eq. 7): the maximum over the counted windows (same selection as above) of the
amplitude error ``|A − k_p|/k_p`` and the delay error ``|d − τ|/τ``, in %.

Both studies run their cases through an executor (:mod:`rths_hil.studies.executors`).
"""

from __future__ import annotations

import csv
import logging
import math
import re
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rths_hil.sim_backends.delay import DelayGain

from ..errors import InputError
from ..fei import MovingFEIResult, moving_fei
from ..groundmotion import GroundMotion
from ..plotting import save_figure
from ..structures.sdof import BoucWenParams, simulate_sdof
from .executors import run_cases

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
    return run_cases(_ws_case, cases, executor, progress, "window-size")


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
        if window_s is not None:
            tw = window_s
        elif window_periods is not None:
            tw = window_periods / fn
        else:
            raise InputError("give the window: window_periods or window_s")
        if tw > gm.duration:
            raise InputError(
                f"window of {tw:g} s (fn = {fn:g} Hz) is longer than the record ({gm.duration:g} s)"
            )
        for bw in (False, True):
            cases.append((gm, float(fn), bw, {**kwargs, "window_s": tw}))
    return run_cases(_acc_case, cases, executor, progress, "accuracy")


# --------------------------------------------------------------------------------------------
# output


def write_window_size_csv(path: str | Path, rows: Sequence[WindowSizeResult]) -> None:
    """CSV with one line per record × fn (columns = :class:`WindowSizeResult` fields)."""

    names = list(WindowSizeResult.__dataclass_fields__)
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for r in rows:
            w.writerow([format_value(getattr(r, n)) for n in names])


def write_accuracy_csv(path: str | Path, rows: Sequence[AccuracyResult]) -> None:
    """CSV with the columns of :data:`ACCURACY_COLUMNS` (the FEI paper's Table 4.1)."""

    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(ACCURACY_COLUMNS)
        for r in rows:
            w.writerow([format_value(v) for v in r.row().values()])


def format_value(v) -> str:
    """A CSV cell: floats with 6 significant digits, NaN as ``nan``."""
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

    save_figure(fig, path, 120)


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

    save_figure(fig, path, 120)

"""The end-of-run summary: :func:`summarize` reads a run directory back and computes the
whole-record FEI (the FEI paper's Eq. 2.1–2.5) of measured vs target and measured vs command, the
tracking metrics J1–J3 and TI (:mod:`rths_hil.metrics`), statistics of the online (MWO)
estimates, lateness and the e-stop outcome; it writes ``summary.json``. :func:`format_summary`
renders it for the console."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..formats import json_text
from ..metrics import overlap_peak_lag
from ..records.columns import column_name
from ..records.recorder import RECORD_FILE, RunData, read_npy_header, read_run
from .live import _fmt, _number

__all__ = ["exact_fei_points", "format_summary", "summarize"]


def record_channels(run: RunData) -> list[tuple[str, str]]:
    """(name, record channel) of each channel of a run (one unnamed channel for older runs).

    The record channel names the channel's columns (:func:`column_name`): the channel's name in
    a record of several channels, ``""`` in a record of one.
    """
    chans = run.meta.get("channels") or []
    multi = len(chans) > 1
    out = [(c.get("name", ""), c.get("name", "") if multi else "") for c in chans]
    return out or [("", "")]


def channel_controls(run: RunData) -> dict[str, str]:
    """Record channel → ``control.mode`` of each channel (``displacement`` for older runs)."""
    chans = run.meta.get("channels") or []
    return {
        ch: (c.get("control") or "displacement")
        for (_, ch), c in zip(record_channels(run), chans, strict=False)
    }


def tracked_column(control: str) -> str:
    """The record column a channel tracks: ``measured`` (displacement, m) or ``force`` (N)."""
    return "measured" if control == "displacement" else "force"


def exact_fei_points(
    rec: np.ndarray, channel: str = ""
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact-FEI cross-check as points: (window-end step, A, d), one per new valid window.

    Each exact value is placed at the step its window ended (``fei_exact_step``), not at the
    step its result came back from the worker process (paced runs), so the points sit on the
    streaming curve. Records without ``fei_exact_step`` use the step the value appeared.
    ``channel`` is the record channel (``""`` for a record of one channel).
    """
    amp = rec[column_name("fei_exact_amplitude", channel)].astype(float)
    dly = rec[column_name("fei_exact_delay", channel)].astype(float)
    ok = rec[column_name("fei_exact_valid", channel)].astype(bool)
    name = column_name("fei_exact_step", channel)
    if name in (rec.dtype.names or ()):
        end = rec[name].astype(np.int64)
        change = np.flatnonzero(np.diff(end, prepend=-1) != 0)
        change = change[(end[change] >= 0) & ok[change] & np.isfinite(amp[change])]
        return end[change], amp[change], dly[change]
    change = np.flatnonzero(np.diff(amp, prepend=np.nan) != 0)
    change = change[ok[change] & np.isfinite(amp[change])]
    return change, amp[change], dly[change]


def _events(run: RunData, kind: str) -> list[dict]:
    return [e for e in run.events if e.get("kind") == kind]


def _num(v) -> float:
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return math.nan
    return math.nan if v is None else float(v)


def summarize(run_dir: str | Path, write: bool = True, lean_rows: int = 1 << 21) -> dict[str, Any]:
    """Summary of a run directory (also of a crashed or tripped run); writes ``summary.json``.

    Returns
    -------
    dict
        ``status``, ``steps``, ``duration``, ``trip`` (rule, reason, time, step or None),
        ``fei_target`` / ``fei_command`` (whole-record A, d, f_eq of measured vs target/command),
        ``metrics`` (J1 in s, J2 and J3 in %, TI), ``online`` (mean, min, max of the valid
        streaming A and d), ``lateness`` (p50, p99, p99.9, max in s; overruns), ``estop``,
        and from the ``end`` event when it has them ``overrun_causes`` (paced overruns by
        cause: ``machine``, ``machine_backlog``, ``machine_in_work``, ``work``,
        ``work_backlog``), ``wall_time``,
        ``steps_per_second`` (``None`` without a loop step), ``missed_replies``,
        ``reply_gaps`` (``count``, ``missed``, ``longest`` s, ``longest_steps``; per channel
        under ``channels``), ``driver_stats``, ``twin_stats``, ``final_alpha``. With several
        channels the per-record figures (FEI, metrics, online, peak) are under ``channels`` →
        channel name, and ``trip`` names its ``channel``.

    Notes
    -----
    The record is read memory-mapped and column by column. Records longer than ``lean_rows``
    rows (≈ 8.5 min at 4096 Hz) are evaluated in chunks with the same equations
    (:func:`_fei_lean`, :func:`_metrics_lean`): a one-hour record at 4096 Hz is 2.3 GB on
    disk, and the whole-record FEI then needs two one-sided spectra and one padded column in
    memory (≈ 0.4 GB; measured peak of the summary 0.77 GB) instead of ≈ 4.7 GB. (One complex
    FFT of ``x + i·y`` would need fewer arrays on paper but measured 0.92 GB: the complex
    transform is not done in place.)
    """
    run = read_run(run_dir, mmap=True)
    rec = run.record
    fs = run.fs
    n = len(rec)
    end = (_events(run, "end") or [{}])[-1]
    trips = _events(run, "trip")
    stops = _events(run, "operator_stop")
    estops = _events(run, "estop")
    status = end.get("status") or ("crashed" if n else "empty")
    out: dict[str, Any] = {
        "run_dir": str(run.path),
        "status": status,
        "mode": run.meta.get("mode"),
        "driver": run.meta.get("driver"),
        "fs": fs,
        "steps": n,
        "planned_steps": run.meta.get("planned_steps"),
        "duration": n / fs if fs else 0.0,
        "trip": None,
        "estop": bool(estops),
        "estop_confirmed": estops[-1].get("confirmed") if estops else None,
    }
    if trips:
        t = trips[-1]
        out["trip"] = {k: t.get(k) for k in ("rule", "reason", "time", "step", "values", "channel")}
    elif stops:
        s = stops[-1]
        out["trip"] = {
            "rule": "operator",
            "reason": f"operator stop ({s.get('signal')})",
            "time": s.get("time"),
            "step": s.get("step"),
            "values": {},
        }
    short = _too_short(n, fs, run.meta.get("window_s"))
    if short:
        out["too_short"] = short
    if n >= 16:
        chans = record_channels(run)
        warnings = _events(run, "stability")
        energy = end.get("stability") or {}
        controls = channel_controls(run)
        with _Rows(run.path / RECORD_FILE) as src:
            if len(chans) == 1:
                ctl = controls.get(chans[0][1], "displacement")
                out.update(_record_figures(src, fs, lean_rows, chans[0][1], ctl))
                stab = _stability_figures(src, chans[0][1], chans[0][0], energy, warnings)
                if stab:
                    out["stability"] = stab
            else:  # several channels: the same figures per channel
                out["channels"] = {
                    name: _record_figures(src, fs, lean_rows, ch, controls.get(ch, "displacement"))
                    for name, ch in chans
                }
                for name, ch in chans:
                    stab = _stability_figures(
                        src, ch, name, energy, warnings, controls.get(ch, "displacement")
                    )
                    if stab:
                        out["channels"][name]["stability"] = stab
    if out["mode"] == "paced" and n:
        lat = np.array(rec["lateness"], dtype=float)
        p50, p99, p999 = np.percentile(lat, [50, 99, 99.9])
        out["lateness"] = {
            "p50": float(p50),
            "p99": float(p99),
            "p99.9": float(p999),
            "max": float(lat.max()),
            "overruns": (end.get("lateness") or {}).get("overruns"),
        }
        del lat
    # the run's wall-clock duration (s); the event's wall_time is its ISO 8601 stamp
    wall = end.get("wall_duration", end.get("wall_time"))
    if isinstance(wall, int | float):
        out["wall_time"] = wall
    for key in (
        "missed_replies",
        "reply_gaps",
        "overrun_causes",
        "stalls",
        "driver_stats",
        "twin_stats",
        "final_alpha",
    ):
        if key in end:
            out[key] = end[key]
    if "steps_per_second" in end:  # NaN (no loop step: a trip in the start ramp) -> null
        out["steps_per_second"] = _number(end["steps_per_second"])
    if write:
        p = Path(run_dir) / "summary.json"
        p.write_text(json_text(out))
    return out


MIN_EVAL_DURATION = 1.0
"""Shortest record (s) whose whole-record FEI and J1–J3 the summary reports (see
:func:`_too_short`)."""


def _too_short(n: int, fs: float, window_s: float | None) -> str | None:
    """Why a record of ``n`` rows is too short for the whole-record FEI and J1–J3, or None.

    The rule: a record shorter than 1 s (:data:`MIN_EVAL_DURATION`) or than one FEI window
    (``window_s``, the run's ``fei.window``; about three natural periods) is too short. The FEI
    paper's moving-window index is not defined before one window has filled, and the metrics
    J1–J3 of a fraction of a cycle are dominated by the start-up transient (a 38-step OpenSees
    run gave J2 = 1067 %). The values are still computed and kept in ``summary.json``; the
    console says the run is too short instead of printing them.
    """
    dur = n / fs if fs else 0.0
    need = MIN_EVAL_DURATION
    what = "1 s"
    if window_s and window_s > need:
        need, what = float(window_s), f"one FEI window, {float(window_s):.2f} s"
    if dur < need:
        return f"run too short for the whole-record FEI and J1–J3 ({dur:.2f} s < {what})"
    return None


class _Rows:
    """Rows of ``record.npy`` read in chunks with plain file reads.

    Not memory-mapped on purpose: pages of a mapped file that have been read count in the
    process's resident set (a one-hour record at 4096 Hz is 2.3 GB); data read with ``read``
    stays in the OS page cache, outside it.
    """

    def __init__(self, path: Path) -> None:
        h = read_npy_header(path)  # checked: any header length, rows within the file
        self._f = open(path, "rb")
        self.dtype, self.offset, self.n = h.dtype, h.offset, h.rows

    def __len__(self) -> int:
        return self.n

    def __enter__(self) -> _Rows:
        return self

    def __exit__(self, *exc) -> None:
        self._f.close()

    def read(self, i: int, j: int) -> np.ndarray:
        """Rows ``i … j−1`` (structured array)."""
        j = min(j, self.n)
        self._f.seek(self.offset + i * self.dtype.itemsize)
        return np.fromfile(self._f, dtype=self.dtype, count=max(j - i, 0))

    def column(self, name: str, i: int = 0, j: int | None = None) -> np.ndarray:
        """Rows ``i … j−1`` of one column as float64 (the whole column by default)."""
        j = self.n if j is None else min(j, self.n)
        out = np.empty(max(j - i, 0))
        for a in range(i, j, _CHUNK):
            b = min(a + _CHUNK, j)
            out[a - i : b - i] = self.read(a, b)[name]
        return out


def _record_figures(
    rec: _Rows, fs: float, lean_rows: int, channel: str = "", control: str = "displacement"
) -> dict[str, Any]:
    """Whole-record FEI, metrics, online-estimate statistics and peaks of a record (≥ 16 rows).

    ``channel`` selects a channel's columns (``"left"``: ``target_left`` …; ``""``: one channel).
    ``control`` is the channel's ``control.mode``: the FEI and J1–J3 are of its tracked
    quantity, the measured displacement (m) or, on a force or load channel, the measured force
    against the target force (N); ``control``, ``tracked`` and ``unit`` say which.
    """
    from ..fei import fei

    out: dict[str, Any] = {}
    n = len(rec)
    tracked = tracked_column(control)
    out["control"] = control
    out["tracked"] = tracked
    out["unit"] = "m" if tracked == "measured" else "N"
    meas = column_name(tracked, channel)
    target_col, command_col = column_name("target", channel), column_name("command", channel)
    finite = _all_finite(rec, (target_col, command_col, meas))
    lean = n > lean_rows and finite
    for key, col in (("fei_target", target_col), ("fei_command", command_col)):
        try:
            if lean:
                r = _fei_lean(rec, col, fs, meas)
            else:
                ref = rec.column(col)
                measured = rec.column(meas)
                sel = np.isfinite(measured) & np.isfinite(ref)
                r = fei(ref[sel], measured[sel], fs)
                del ref, measured, sel
            out[key] = {
                "amplitude": float(r.amplitude),
                "delay": float(r.delay),
                "f_eq": float(r.f_eq),
                "valid": bool(r.valid),
            }
        except Exception as exc:  # a record too short or degenerate: say so, don't fail
            out[key] = {"error": str(exc)}
    if lean:
        out["metrics"] = _metrics_lean(rec, fs, target_col, meas)
    else:
        target = rec.column(target_col)
        measured = rec.column(meas)
        ok = np.isfinite(measured)
        out["metrics"] = _metrics(target[ok], measured[ok], fs)
        if not ok.any() or np.ptp(target[ok]) == 0.0:
            # a constant target (a held load): no lag or phase to measure
            out["metrics"]["j1_delay"] = out["metrics"]["tracking_indicator"] = None
        del target, measured, ok
    # online estimates and peaks, chunk by chunk
    cnt = 0
    a_sum = d_sum = 0.0
    a_min = d_min = math.inf
    a_max = d_max = -math.inf
    pk = {"target": 0.0, "measured": 0.0, "force": 0.0}
    online = tuple(column_name(b, channel) for b in ("fei_amplitude", "fei_delay", "fei_valid"))
    for c in _chunks(rec, (*online, *(column_name(name, channel) for name in pk))):
        fa, fd = c[online[0]], c[online[1]]
        v = c[online[2]].astype(bool) & np.isfinite(fa) & np.isfinite(fd)
        if v.any():
            cnt += int(v.sum())
            a_sum += float(fa[v].sum())
            d_sum += float(fd[v].sum())
            a_min, a_max = min(a_min, float(fa[v].min())), max(a_max, float(fa[v].max()))
            d_min, d_max = min(d_min, float(fd[v].min())), max(d_max, float(fd[v].max()))
        for name in pk:
            x = np.abs(c[column_name(name, channel)])
            if np.isfinite(x).any():
                pk[name] = max(pk[name], float(np.nanmax(x)))
    if cnt:
        out["online"] = {
            "windows": cnt,
            "amplitude": {"mean": a_sum / cnt, "min": a_min, "max": a_max},
            "delay": {"mean": d_sum / cnt, "min": d_min, "max": d_max},
        }
    out["peak"] = pk
    return out


def _stability_figures(
    rec: _Rows,
    channel: str,
    name: str,
    energy: dict,
    warnings: list[dict],
    control: str = "displacement",
) -> dict[str, Any] | None:
    """The stability indicator of a channel over the run, or None (no ``stability`` column, or
    a load channel: its force is not from the structure, it has no indicator).

    ``peak`` and ``mean`` of the valid windowed S, ``valid`` (their share of the rows),
    ``whole_run`` (all the injected over all the dissipated energy, from the ``end`` event),
    ``injected`` and ``dissipated`` (J), ``warn`` and ``limit`` (the levels), ``warnings``
    (``stability`` events) and ``first_warning`` (its time, s).
    """
    col = column_name("stability", channel)
    if col not in (rec.dtype.names or ()) or control == "load":
        return None
    cnt = 0
    total = 0.0
    peak = -math.inf
    for c in _chunks(rec, (col,)):
        s = c[col]
        ok = np.isfinite(s)
        if ok.any():
            cnt += int(ok.sum())
            total += float(s[ok].sum())
            peak = max(peak, float(s[ok].max()))
    mine = [e for e in warnings if (e.get("channel") or "") == (name or "")]
    e = energy.get(name or "") or {}
    return {
        "peak": peak if cnt else None,
        "mean": total / cnt if cnt else None,
        "valid": cnt / len(rec) if len(rec) else 0.0,
        "whole_run": _number(e.get("ratio")),
        "injected": _number(e.get("injected")),
        "dissipated": _number(e.get("dissipated")),
        "warn": _number(e.get("warn")),
        "limit": _number(e.get("limit")),
        "warnings": len(mine),
        "first_warning": _number(mine[0].get("time")) if mine else None,
    }


_CHUNK = 1 << 18  # rows per chunk of a chunked pass (≈ 2 MB per float column)


def _chunks(rec: _Rows, names, chunk: int | None = None):
    """Yield ``{name: float or bool array}`` for consecutive row chunks of a record."""
    chunk = chunk or _CHUNK
    for i in range(0, len(rec), chunk):
        part = rec.read(i, i + chunk)
        yield {
            name: np.array(part[name], dtype=bool if part.dtype[name].kind == "b" else float)
            for name in names
        }


def _all_finite(rec: _Rows, names) -> bool:
    return all(bool(np.isfinite(c[name]).all()) for c in _chunks(rec, names) for name in names)


def _windowed(rec: _Rows, name: str, M: int, dtype=np.float64) -> tuple[np.ndarray, float]:
    """Column ``name`` mean-free times the Hann window, zero-padded to ``M``; and max |x|.

    ``np.hanning(n)[i] = 0.5 − 0.5·cos(2πi/(n−1))``, built chunk by chunk; the mean is
    accumulated in float64 whatever ``dtype`` the column is stored in.
    """
    n = len(rec)
    x = np.zeros(M, dtype=dtype)
    peak = 0.0
    for i in range(0, n, _CHUNK):
        j = min(i + _CHUNK, n)
        x[i:j] = rec.read(i, j)[name]
    mean = float(x[:n].mean(dtype=np.float64))
    for i in range(0, n, _CHUNK):
        seg = x[i : min(i + _CHUNK, n)]
        peak = max(peak, float(np.abs(seg).max()))
        k = np.arange(i, i + seg.size, dtype=float)
        seg -= mean
        seg *= 0.5 - 0.5 * np.cos(2.0 * math.pi * k / (n - 1))
    return x, peak


def _fei_lean(rec: _Rows, ref: str, fs: float, meas: str = "measured"):
    """Whole-record FEI of column ``meas`` vs column ``ref`` in bounded memory (the FEI paper,
    Eq. 2.1–2.5).

    The same sums as :func:`rths_hil.fei.fei` (Hann window, mean removal, zero-padding to
    ``M = 2p``, spectral sums E, F, S over bins 1 … p−1, then the same closing equations),
    but the time series are built column by column and each spectrum is summed in chunks:
    the peak memory is two one-sided spectra and one padded column. The transforms are done
    in single precision (the sums in double): a one-hour record at 4096 Hz then peaks at
    ≈ 0.44 GB instead of ≈ 0.74 GB, and E and S differ from the double-precision sums by
    ≈ 5e-8 relative (measured on such a record), far below what A and d are reported to.
    """
    import scipy.fft as sfft

    from ..fei.batch import ABS_FLOOR, ZERO_VARIANCE_RTOL, FEIResult, _finish, fft_length

    n = len(rec)
    M = fft_length(n)
    p = M // 2
    x, peak = _windowed(rec, ref, M, np.float32)
    X = sfft.rfft(x, overwrite_x=True)  # complex64
    del x
    E = F = 0.0
    for b in range(1, p, _CHUNK):
        Xb = X[b : min(b + _CHUNK, p)].astype(np.complex128)
        P = Xb.real * Xb.real + Xb.imag * Xb.imag
        E += float(P.sum())
        F += float(P @ np.arange(b, b + Xb.size, dtype=float))
    y, _ = _windowed(rec, meas, M, np.float32)
    Y = sfft.rfft(y, overwrite_x=True)
    del y
    S = 0j
    for b in range(1, p, _CHUNK):
        e = min(b + _CHUNK, p)
        S += complex(np.vdot(X[b:e].astype(np.complex128), Y[b:e]))  # Σ Y·conj(X)
    del X, Y
    ww = 0.0
    for i in range(0, n, _CHUNK):
        k = np.arange(i, min(i + _CHUNK, n), dtype=float)
        w = 0.5 - 0.5 * np.cos(2.0 * math.pi * k / (n - 1))
        ww += float(w @ w)
    floor = max(ABS_FLOOR, ZERO_VARIANCE_RTOL * peak)
    amp, phase, f_eq, delay, valid, level, _ = _finish(
        np.atleast_1d(E), np.atleast_1d(F), np.atleast_1d(S), fs, M, ww, floor, 0.0
    )
    return FEIResult(
        float(amp[0]), float(phase[0]), float(f_eq[0]), float(delay[0]), bool(valid[0]),
        float(level[0]),
    )  # fmt: skip


def _metrics_lean(
    rec: _Rows, fs: float, tcol: str = "target", mcol: str = "measured", max_lag_s: float = 0.1
) -> dict[str, float]:
    """J1–J3 and TI of column ``mcol`` vs ``tcol`` in chunks (same equations as
    :mod:`rths_hil.metrics`; all rows finite)."""
    from scipy.signal import correlate

    n = len(rec)
    sx = sy = 0.0
    for c in _chunks(rec, (tcol, mcol)):
        sx += float(c[tcol].sum())
        sy += float(c[mcol].sum())
    mx, my = sx / n, sy / n
    L = min(int(np.floor(max_lag_s * fs + 1e-9)), n - 1)
    R = np.zeros(2 * L + 1)
    xx = ee = 0.0
    xpk = epk = 0.0
    ti = 0.0
    prev = None  # last (x, y) of the previous chunk, raw
    for i in range(0, n, _CHUNK):
        j = min(i + _CHUNK, n)
        x = rec.column(tcol, i, j)
        y = rec.column(mcol, i, j)
        # J2, J3 (raw values), TI (trapezoids, joined across chunks)
        d = y - x
        ee += float(d @ d)
        xx += float(x @ x)
        epk = max(epk, float(np.abs(d).max()))
        xpk = max(xpk, float(np.abs(x).max()))
        xs = x if prev is None else np.r_[prev[0], x]
        ys = y if prev is None else np.r_[prev[1], y]
        ti += float((0.5 * (xs[1:] + xs[:-1]) * np.diff(ys)).sum())
        ti -= float((0.5 * (ys[1:] + ys[:-1]) * np.diff(xs)).sum())
        prev = (x[-1], y[-1])
        # J1: R(τ) = Σ_t x(t)·y(t+τ), mean-free, |τ| ≤ L; y zero outside the record
        a, b = max(i - L, 0), min(j + L, n)
        yseg = np.zeros(j - i + 2 * L)
        yseg[a - (i - L) : b - (i - L)] = rec.column(mcol, a, b) - my
        R += correlate(yseg, x - mx, mode="valid", method="fft")
    out: dict[str, float] = {}
    out["j2_nrms"] = 100.0 * math.sqrt(ee / n) / math.sqrt(xx / n) if xx > 0 else math.nan
    out["j3_peak"] = 100.0 * epk / xpk if xpk > 0 else math.nan
    out["tracking_indicator"] = 0.5 * ti
    # overlap energies of each lag (as metrics.j1_delay), from the record's head and tail
    head_x = rec.column(tcol, 0, L + 1) - mx
    tail_x = rec.column(tcol, n - L - 1, n) - mx
    head_y = rec.column(mcol, 0, L + 1) - my
    tail_y = rec.column(mcol, n - L - 1, n) - my
    tx = ty = 0.0
    for c in _chunks(rec, (tcol, mcol)):
        tx += float(((c[tcol] - mx) ** 2).sum())
        ty += float(((c[mcol] - my) ** 2).sum())
    lags = np.arange(-L, L + 1)
    hx = np.r_[0.0, np.cumsum(head_x * head_x)]  # Σ of the first m samples' squares
    hy = np.r_[0.0, np.cumsum(head_y * head_y)]
    tlx = np.r_[0.0, np.cumsum((tail_x * tail_x)[::-1])]  # Σ of the last m samples' squares
    tly = np.r_[0.0, np.cumsum((tail_y * tail_y)[::-1])]
    pos = np.maximum(lags, 0)
    neg = np.maximum(-lags, 0)
    ex = np.where(lags >= 0, tx - tlx[pos], tx - hx[neg])
    ey = np.where(lags >= 0, ty - hy[pos], ty - tly[neg])
    out["j1_delay"] = overlap_peak_lag(R, lags, ex, ey, fs)
    return {k2: out[k2] for k2 in ("j1_delay", "j2_nrms", "j3_peak", "tracking_indicator")}


def _metrics(target: np.ndarray, measured: np.ndarray, fs: float) -> dict[str, float]:
    try:
        from .. import metrics
    except ImportError:  # pragma: no cover - the metrics module ships with the package
        return {}
    out: dict[str, float] = {}
    for name, fn in (
        ("j1_delay", lambda: metrics.j1_delay(target, measured, fs, 0.1)),
        ("j2_nrms", lambda: metrics.j2_nrms(target, measured)),
        ("j3_peak", lambda: metrics.j3_peak(target, measured)),
        ("tracking_indicator", lambda: metrics.tracking_indicator(target, measured)),
    ):
        try:
            out[name] = float(fn())
        except Exception:
            out[name] = math.nan
    return out


def format_summary(s: dict[str, Any]) -> str:
    """The end-of-run summary as console text."""
    lines = [
        f"run {s['run_dir']}: {s['status']} after {s['steps']} steps "
        f"({s['duration']:.2f} s at {s['fs']:g} Hz, {s.get('mode')}, driver {s.get('driver')})"
    ]
    trip = s.get("trip")
    if trip:
        lines.append(
            f"  e-stop: {trip['rule']}"
            + (f" on channel {trip['channel']}" if trip.get("channel") else "")
            + f" at t = {_num(trip['time']):.4f} s "
            f"(step {trip['step']}): {trip['reason']}"
            + (
                ""
                if s.get("estop_confirmed") in (None, True)
                else "  [controller did not confirm the latch]"
            )
        )
    else:
        lines.append("  e-stop: none")
    chans = s.get("channels")
    short = s.get("too_short")
    if short:
        lines.append(f"  {short}")
    if chans:
        for name, block in chans.items():
            lines.append(f"  channel {name}:")
            lines += ["  " + line for line in _format_channel(block, bool(short))]
    else:
        lines += _format_channel(s, bool(short))
    if not short and any(
        "amplitude" in (b.get("fei_target") or {}) for b in (chans or {"": s}).values()
    ):
        lines.append(
            "  (FEI measured vs target: the tracking quality, what the structure received; "
            "measured vs command: the actuator's raw lag and gain, before compensation)"
        )
    lat = s.get("lateness")
    if lat:
        lines.append(
            f"  lateness p50 {lat['p50'] * 1e6:.0f} µs, p99 {lat['p99'] * 1e6:.0f} µs, "
            f"p99.9 {lat['p99.9'] * 1e6:.0f} µs, max {lat['max'] * 1e6:.0f} µs, "
            f"overruns {lat.get('overruns')}"
        )
        c = s.get("overrun_causes")
        if c:
            lines.append(
                f"  overruns by cause: machine {c.get('machine')} "
                f"(+{c.get('machine_backlog')} catch-up), machine inside the work "
                f"{c.get('machine_in_work', 0)}, work {c.get('work')} "
                f"(+{c.get('work_backlog')} catch-up)"
            )
        st = s.get("stalls")
        if st and st.get("count"):
            lines.append(
                f"  stalls of the bridge itself (not the controller): {st['count']}, longest "
                f"{st['longest'] * 1e3:.1f} ms, total {st['total'] * 1e3:.1f} ms"
            )
    sps = _number(s.get("steps_per_second"))
    if sps is not None or "missed_replies" in s:
        # no loop step taken (a trip in the start ramp): no rate, only the missed replies
        rate = f"{sps:.0f} steps/s" if sps is not None else "no loop steps"
        line = f"  {rate}, missed replies {s.get('missed_replies', 0)}"
        gaps = s.get("reply_gaps") or {}
        if gaps.get("count"):  # held measurements, not a fault (docs/loop.md)
            line += (
                f" in {gaps['count']} gap{'s' if gaps['count'] != 1 else ''} (longest "
                f"{_fmt(_number(gaps.get('longest')), 1e3, '.1f')} ms, "
                f"{gaps.get('longest_steps')} steps; measurement held)"
            )
        lines.append(line)
    return "\n".join(lines)


def _format_channel(s: dict[str, Any], short: bool = False) -> list[str]:
    """Summary lines of one channel (FEI, metrics, online FEI, peaks); ``short``: the run is
    too short for the whole-record FEI and J1–J3 (:func:`_too_short`), they are left out."""
    lines: list[str] = []
    forced = s.get("control", "displacement") != "displacement"
    if forced:  # the mode and the tracked quantity in its unit
        lines.append(
            f"  control: {s['control']}; tracked: the measured force (N) against the target force"
        )
    for key, label in (
        ()
        if short
        else (
            ("fei_target", "measured vs target "),
            ("fei_command", "measured vs command"),
        )
    ):
        f = s.get(key)
        if f and "amplitude" in f:
            lines.append(
                f"  FEI {label}: A = {_fmt(f['amplitude'], spec='.4f')}, "
                f"d = {_fmt(f['delay'], 1e3, '.2f', True)} ms, "
                f"f_eq = {_fmt(f['f_eq'], spec='.3f')} Hz"
            )
    m = {} if short else (s.get("metrics") or {})
    if m:
        lines.append(
            f"  J1 = {_fmt(m.get('j1_delay'), 1e3, '.2f', True)} ms, "
            f"J2 = {_fmt(m.get('j2_nrms'), spec='.2f')} %, "
            f"J3 = {_fmt(m.get('j3_peak'), spec='.2f')} %, "
            f"TI = {_fmt(m.get('tracking_indicator'), spec='.3g')}"
        )
    o = s.get("online")
    if o:
        lines.append(
            f"  online MWO ({o['windows']} valid windows): A {o['amplitude']['mean']:.4f} "
            f"[{o['amplitude']['min']:.4f}, {o['amplitude']['max']:.4f}], d "
            f"{o['delay']['mean'] * 1e3:+.2f} ms [{o['delay']['min'] * 1e3:+.2f}, "
            f"{o['delay']['max'] * 1e3:+.2f}]"
        )
    st = s.get("stability")
    if st:
        if st.get("peak") is None:
            text = "no valid window (the structure hardly moved)"
        else:
            text = (
                f"peak {st['peak']:.3g}, mean {_fmt(st.get('mean'), spec='.3g')}, "
                f"whole run {_fmt(st.get('whole_run'), spec='.3g')}"
            )
        levels = (
            f" (warn {st['warn']:g}, limit {st['limit']:g})"
            if st.get("warn") is not None and st.get("limit") is not None
            else ""
        )
        first = st.get("first_warning")
        warned = (
            f"; {st['warnings']} warning{'s' if st['warnings'] != 1 else ''}, the first at "
            f"t = {first:.2f} s"
            if st.get("warnings") and first is not None
            else ""
        )
        lines.append(f"  stability S: {text}{levels}{warned}")
    if s.get("peak"):
        p = s["peak"]
        if forced:
            lines.append(
                f"  peak target {p['target'] / 1e3:.2f} kN, force {p['force'] / 1e3:.2f} kN, "
                f"measured {p['measured'] * 1e3:.2f} mm"
            )
        else:
            lines.append(
                f"  peak target {p['target'] * 1e3:.2f} mm, measured "
                f"{p['measured'] * 1e3:.2f} mm, force {p['force'] / 1e3:.2f} kN"
            )
    return lines

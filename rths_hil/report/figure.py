"""The PNG report: :func:`plot_report` draws ``report.png`` like the FEI paper's Fig. 5.1
(calculated, command and measured displacements) and Fig. 5.2 (online A and d), plus lateness or
the Kalman estimates."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..records.columns import column_name
from ..records.recorder import RECORD_FILE, RunData, read_run
from .summary import (
    _CHUNK,
    _events,
    _num,
    _Rows,
    channel_controls,
    format_summary,
    record_channels,
    summarize,
    tracked_column,
)

__all__ = ["plot_report"]


def plot_report(
    run_dir: str | Path,
    path: str | Path | None = None,
    max_points: int = 20_000,
    summary: dict[str, Any] | None = None,
    keep_figure: bool = False,
) -> Path | Any:
    """Draw ``report.png`` (the FEI paper's Fig. 5.1 and 5.2 style) for a run directory.

    One channel, top to bottom: the ground motion; displacements (calculated, command,
    measured); a zoom around the peak; the tracking error (measured − target); online FEI A
    and d (streaming curve, exact cross-check dots at their windows' ends); lateness (paced)
    or the Kalman estimates (lockstep); then the force–displacement loop beside the summary
    text (:func:`format_summary`). Several channels: the ground motion, then per channel the
    displacements, the tracking error, A and d; the lateness or Kalman panel of the first
    channel; every channel's force–displacement loop beside the summary. Displacements are
    drawn in mm, forces in kN (the files stay SI); a force or load channel (``control.mode``)
    has its target, command and measured force (kN) in the displacements' panel and its force
    tracking error. A trip or an operator stop is a red line on
    every time panel, labelled with the rule and the time on the top one.

    ``summary`` is the run's :func:`summarize` dict (read from ``summary.json``, or computed,
    when not given). Returns the path of the PNG (``keep_figure``: the matplotlib figure,
    not saved, for a notebook or a test). The record is read in chunks; a record
    longer than ``max_points`` rows is drawn as its min/max envelope over ``max_points / 2``
    buckets (every peak stays visible) and its force–displacement loop from every q-th row,
    so a one-hour record costs a few MB of memory, not gigabytes.
    """
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = read_run(run_dir, mmap=True)
    out = Path(path) if path is not None else run.path / "report.png"
    if summary is None:
        sj = run.path / "summary.json"
        try:
            summary = json.loads(sj.read_text())
        except (OSError, ValueError, RecursionError):
            summary = summarize(run.path, write=False)
    chans = record_channels(run)
    multi = len(chans) > 1
    controls = channel_controls(run)
    # each channel's tracked column: the measured displacement, or a force channel's force
    tracked = {ch: tracked_column(controls.get(ch, "displacement")) for _, ch in chans}
    per_channel = (
        "target", "command", "measured", "force", "fei_amplitude", "fei_delay", "fei_valid",
        "kf_delay", "kf_gain",
    )  # fmt: skip
    derived = {
        column_name("error", ch): (
            lambda p, ch=ch, m=tracked[ch]: p[column_name(m, ch)] - p[column_name("target", ch)]
        )
        for _, ch in chans
    }
    with _Rows(run.path / RECORD_FILE) as src:
        has_stab = {  # a load channel has no indicator (its force is not the structure's)
            ch: column_name("stability", ch) in (src.dtype.names or ())
            and controls.get(ch) != "load"
            for _, ch in chans
        }
        cols = (
            "lateness",
            "ground_accel",
            *(column_name(c, ch) for _, ch in chans for c in per_channel),
            *(column_name("stability", ch) for _, ch in chans if has_stab[ch]),
            *derived,
        )
        env = _envelopes(src, cols, max_points, derived)
        n = len(src)
        zoom = _peak_zoom(src, n, run.fs) if not multi and n else None
        exact = {ch: _exact_points(src, run.fs, ch) for _, ch in chans}
        loops = {
            ch: _strided(src, (column_name("measured", ch), column_name("force", ch)), max_points)
            for _, ch in chans
        }
    t = env["time"]
    mm = 1e3
    paced = run.meta.get("mode") == "paced"
    per = 5 if not multi else 4
    n_time = 1 + per * len(chans) + 1  # ground motion, channels, lateness/Kalman
    heights = [1.0] * n_time + [2.2]
    fig = plt.figure(figsize=(11, 2.4 * n_time + 4.6), constrained_layout=True)
    gs = fig.add_gridspec(n_time + 1, 5, height_ratios=heights)
    axes = [fig.add_subplot(gs[0, :])]
    for i in range(1, n_time):  # one time axis; the zoom around the peak (row 2) has its own
        axes.append(fig.add_subplot(gs[i, :], sharex=None if i == 2 and not multi else axes[0]))
    ax = axes[0]
    gm = run.meta.get("ground_motion") or {}
    ax.plot(t, env["ground_accel"], lw=0.7, color="0.3")
    ax.set_ylabel("ground accel. (m/s²)")
    ax.set_title(
        f"{run.path.name}: ground motion"
        + (f" ({gm['name']}, PGA {gm['pga']:.3g} m/s²)" if gm.get("name") and gm.get("pga") else "")
        + (
            " (applied by OpenSees: not in the record)"
            if not np.nanmax(np.abs(env["ground_accel"]), initial=0)
            else ""
        )
    )
    pair = run.meta.get("fei_pair", "target")
    for c, (name, ch) in enumerate(chans):
        head = f"channel {name}: " if multi else ""
        k = 1 + per * c
        meas = tracked[ch]
        # a force or load channel tracks its force: drawn in kN, its mode in the titles
        if meas == "force":
            sc, unit, what = 1e-3, "kN", "force"
            head += f"{controls.get(ch)}-controlled, "
        else:
            sc, unit, what = mm, "mm", "displacement"
        ax = axes[k]
        ax.plot(t, env[column_name("target", ch)] * sc, lw=1.0, label="calculated (target)")
        ax.plot(t, env[column_name("command", ch)] * sc, lw=0.8, label="command")
        ax.plot(t, env[column_name(meas, ch)] * sc, lw=0.8, ls="--", label="measured")
        ax.set_ylabel(f"{what} ({unit})")
        ax.set_title(f"{head}{what}s (cf. the FEI paper's Fig. 5.1)")
        ax.legend(loc="upper right", fontsize=8)
        k += 1
        if not multi:
            ax = axes[k]
            if zoom is not None and len(zoom):
                tz = zoom["time"]
                ax.plot(tz, zoom["target"] * sc, lw=1.2, label="calculated (target)")
                ax.plot(tz, zoom["command"] * sc, lw=1.0, label="command")
                ax.plot(tz, zoom[meas] * sc, lw=1.0, ls="--", label="measured")
                ax.legend(loc="upper right", fontsize=8)
            ax.set_ylabel(f"{what} ({unit})")
            ax.set_title("around the peak")
            k += 1
        ax = axes[k]
        ax.plot(t, env[column_name("error", ch)] * sc, lw=0.7, color="C3")
        ax.axhline(0.0, color="0.5", lw=0.5)
        ax.set_ylabel(f"error ({unit})")
        ax.set_title(f"{head}tracking error, measured − target {what}")
        k += 1
        valid = env[column_name("fei_valid", ch)] > 0.5
        ex = exact[ch]
        for ax, col, exv, scale, label in (
            (axes[k], "fei_amplitude", ex["amplitude"], 1.0, "A"),
            (axes[k + 1], "fei_delay", ex["delay"], 1e3, "d (ms)"),
        ):
            ax.plot(t, env[column_name(col, ch)] * scale, lw=1.0, label="online, streaming")
            ax.plot(ex["time"], exv * scale, "o", ms=3, label="exact (cross-check)")
            _shade_invalid(ax, t, valid)
            ax.set_ylabel(label)
            ax.legend(loc="upper right", fontsize=8)
        axes[k].set_title(
            f"{head}online FEI, measured {what} vs {pair} (cf. the FEI paper's Fig. 5.2); "
            "grey: invalid windows" + ("; green: stability indicator S" if has_stab[ch] else "")
        )
        if has_stab[ch]:  # beside the FEI: S on the right axis of the A panel
            ax2 = axes[k].twinx()
            ys = env[column_name("stability", ch)]
            few = int(np.isfinite(ys).sum()) < 50  # a trip soon after the first valid window
            ax2.plot(t, ys, lw=0.9, color="C2", marker="o" if few else None, ms=3)
            stb = (summary.get("channels", {}).get(name) if multi else summary) or {}
            lev = (stb.get("stability") or {}).get("warn")
            if lev is not None:
                ax2.axhline(lev, color="C2", lw=0.6, ls=":")
            ax2.set_ylabel("S", color="C2")
    _timing_panel(axes[n_time - 1], t, env, paced, chans[0], multi)
    _mark_stops(run, axes)
    # force–displacement loop(s) and the summary text
    ax = fig.add_subplot(gs[n_time, :2])
    for name, ch in chans:
        x, f = loops[ch]
        ax.plot(x * mm, f / 1e3, lw=0.6, label=name if multi else None)
    ax.set_xlabel("measured displacement (mm)")
    ax.set_ylabel("measured force (kN)")
    ax.set_title("force–displacement")
    if multi:
        ax.legend(fontsize=8)
    ax = fig.add_subplot(gs[n_time, 2:])
    ax.axis("off")
    text = "\n".join(
        "\n".join(textwrap.wrap(line, 84, subsequent_indent="      ") or [""])
        for line in format_summary(summary).splitlines()
    )
    ax.text(0.0, 1.0, text, va="top", ha="left", family="monospace", fontsize=7)
    ax.set_title("summary", loc="left")
    if keep_figure:
        return fig
    from ..plotting import save_figure

    return save_figure(fig, out, 90)


def _peak_zoom(src: _Rows, n: int, fs: float) -> np.ndarray:
    """The rows ±1 s (full rate) around the peak target displacement."""
    ipk, best = 0, -1.0
    for i in range(0, n, _CHUNK):
        x = np.abs(src.column("target", i, i + _CHUNK))
        if x.size and np.isfinite(x).any():
            j = int(np.nanargmax(x))
            if x[j] > best:
                ipk, best = i + j, float(x[j])
    return src.read(max(ipk - int(fs), 0), ipk + int(fs) + 1)


def _timing_panel(
    ax: Any, t: np.ndarray, env: dict[str, Any], paced: bool, chan: tuple[str, str], multi: bool
) -> None:
    """The last time panel: lateness (paced) or the Kalman estimates of channel ``chan``."""
    name, ch = chan
    if paced:
        ax.plot(t, env["lateness"] * 1e6, lw=0.6)
        ax.set_ylabel("lateness (µs)")
        ax.set_title("send time minus deadline")
    else:
        ax.plot(t, env[column_name("kf_delay", ch)] * 1e3, lw=1.0, label="Kalman delay (ms)")
        ax2 = ax.twinx()
        ax2.plot(t, env[column_name("kf_gain", ch)], lw=1.0, color="C1", label="Kalman gain")
        ax.set_ylabel("delay (ms)")
        ax2.set_ylabel("gain")
        ax.set_title(
            "Kalman estimates of the actuator, measured vs command"
            + (f" (channel {name})" if multi else "")
        )
    ax.set_xlabel("time (s)")


def _mark_stops(run: RunData, axes: list[Any]) -> None:
    """A red line on every time panel at each trip or operator stop, labelled on the top one."""
    stops = _events(run, "trip") + _events(run, "operator_stop")
    for tr in stops:
        tt = _num(tr.get("time"))
        label = tr.get("rule") or "operator stop"
        if tr.get("channel"):
            label += f" on {tr['channel']}"
        for a in axes:
            a.axvline(tt, color="r", lw=1.0)
        axes[0].annotate(
            f"e-stop: {label} at {tt:.3f} s",
            xy=(tt, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(-4, -4),
            textcoords="offset points",
            ha="right",
            va="top",
            color="r",
            fontsize=8,
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "r", "lw": 0.6},
        )


def _strided(src: _Rows, names, max_points: int) -> tuple[np.ndarray, ...]:
    """Columns ``names`` at every q-th row, ``q = ceil(n / max_points)`` (pairs stay paired:
    a force–displacement loop cannot be drawn from two separate envelopes)."""
    n = len(src)
    q = max(1, -(-n // max_points))
    parts: dict[str, list] = {k: [] for k in names}
    chunk = max(q, (_CHUNK // q) * q)
    for i in range(0, n, chunk):
        part = src.read(i, i + chunk)[::q]
        for k in names:
            parts[k].append(np.asarray(part[k], dtype=float))
    return tuple(np.concatenate(v) if v else np.zeros(0) for v in parts.values())


def _envelopes(
    src: _Rows, names, max_points: int, derived: dict[str, Any] | None = None
) -> dict[str, np.ndarray]:
    """Columns (and ``time``) at full rate, or as a min/max envelope when the record is long.

    With ``q = ceil(2n / max_points)`` rows per bucket each bucket contributes its minimum and
    its maximum, in time order (``fei_valid``: its minimum twice, so a bucket with an invalid
    window is shaded). NaNs are ignored within a bucket. ``derived`` maps a name that is not
    a column to a function of a chunk of rows (e.g. the tracking error).
    """
    derived = derived or {}

    def col(part, k):
        return derived[k](part) if k in derived else part[k]

    n = len(src)
    names = ("time", *names)
    if n <= max_points:
        part = src.read(0, n)
        return {k: np.asarray(col(part, k), dtype=float) for k in names}
    q = -(-2 * n // max_points)
    chunk = max(q, (_CHUNK // q) * q)
    out: dict[str, list] = {k: [] for k in names}
    for i in range(0, n, chunk):
        part = src.read(i, i + chunk)
        m = len(part) // q * q
        if m == 0:
            continue
        for k in names:
            v = np.asarray(col(part, k)[:m], dtype=float).reshape(-1, q)
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN buckets stay NaN
                lo, hi = np.nanmin(v, axis=1), np.nanmax(v, axis=1)
            if k == "time":
                lo, hi = v[:, 0], v[:, -1]
            elif k.startswith("fei_valid"):
                hi = lo
            out[k].append(np.column_stack([lo, hi]).ravel())
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


def _exact_points(src: _Rows, fs: float, channel: str = "") -> dict[str, np.ndarray]:
    """The exact-FEI cross-check of a channel, chunk by chunk: ``time`` (s), ``amplitude``,
    ``delay``, one point per new valid window, at the step its window ended
    (``fei_exact_step``; see :func:`exact_fei_points`)."""
    keep: dict[str, list] = {"time": [], "amplitude": [], "delay": []}
    step_col = column_name("fei_exact_step", channel)
    has_step = step_col in (src.dtype.names or ())
    prev = -1 if has_step else np.nan
    for i in range(0, len(src), _CHUNK):
        part = src.read(i, i + _CHUNK)
        amp = np.asarray(part[column_name("fei_exact_amplitude", channel)], dtype=float)
        ok = part[column_name("fei_exact_valid", channel)].astype(bool) & np.isfinite(amp)
        if has_step:
            end = np.asarray(part[step_col], dtype=np.int64)
            sel = (np.diff(end, prepend=prev) != 0) & (end >= 0) & ok
            prev = end[-1] if end.size else prev
            t_end = end[sel] / fs
        else:  # records before fei_exact_step: where the value appeared
            sel = (np.diff(amp, prepend=prev) != 0) & ok
            prev = amp[-1] if amp.size else prev
            t_end = np.asarray(part["time"][sel], dtype=float)
        keep["time"].append(t_end)
        keep["amplitude"].append(amp[sel])
        delay = part[column_name("fei_exact_delay", channel)][sel]
        keep["delay"].append(np.asarray(delay, dtype=float))
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in keep.items()}


def _shade_invalid(ax, t: np.ndarray, valid: np.ndarray) -> None:
    if not len(t):
        return
    inv = ~valid
    edges = np.flatnonzero(np.diff(inv.astype(np.int8), prepend=0, append=0))
    for a, b in zip(edges[::2], edges[1::2], strict=False):
        ax.axvspan(t[a], t[min(b, len(t) - 1)], color="0.9", lw=0)

"""Operator output of a run: the live console line, the end-of-run summary, the PNG report.

* :class:`LiveLine` formats the status the loop hands over every ``loop.console`` seconds
  (step rate, p99 lateness, online A and d, peak displacement, margin to the nearest limit).
  The loop computes the numbers off the step path (every 0.5 s by default); formatting and
  printing happen here.
* :func:`summarize` reads a run directory back and computes the whole-record FEI (seed
  Eq. 2.1–2.5) of measured vs target and measured vs command, the tracking metrics J1–J3 and TI
  (:mod:`rths_hil.metrics`), statistics of the online (MWO) estimates, lateness and the e-stop
  outcome; it writes ``summary.json``. :func:`format_summary` renders it for the console.
* :func:`plot_report` draws ``report.png`` like the seed's Fig. 5.1 (calculated, command and
  measured displacements) and Fig. 5.2 (online A and d), plus lateness or the Kalman estimates.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import IO, Any

import numpy as np

from .recorder import RunData, read_run

__all__ = ["LiveLine", "format_live", "format_summary", "plot_report", "summarize"]


def _fmt(v: float, scale: float = 1.0, spec: str = ".3f", signed: bool = False) -> str:
    if v is None or not math.isfinite(v):
        return "—"
    return format(v * scale, ("+" if signed else "") + spec)


def format_live(s: dict[str, Any]) -> str:
    """One console line from the loop's status dict."""
    name, frac = s.get("margin", ("none", math.inf))
    if s.get("channel"):  # several channels: the one nearest a limit
        name = f"{s['channel']} {name}"
    margin = "no limits" if not math.isfinite(frac) else f"{name} {frac * 100:.0f} %"
    lat = f"p99 late {s['p99_lateness'] * 1e3:.3f} ms" if s.get("mode") == "paced" else "lockstep"
    return (
        f"t {s['t']:7.2f} s ({100.0 * s['k'] / s['n']:3.0f} %) | {s['rate']:7.0f} steps/s | {lat}"
        f" | overruns {s['overruns']} | {('[' + s['channel'] + '] ') if s.get('channel') else ''}"
        f"A {_fmt(s['amplitude'], spec='.4f')}"
        f" d {_fmt(s['delay'], 1e3, '.2f', True)} ms | peak {s['peak_displacement'] * 1e3:.2f} mm"
        f" | margin {margin} | α {s['alpha']:.2f}"
    )


class LiveLine:
    """A callable for :class:`rths_hil.loop.RTHSLoop` ``live=``: prints the status line.

    On a terminal the line is rewritten in place (carriage return); otherwise (logs, CI) every
    ``every``-th status is printed on its own line.
    """

    def __init__(self, stream: IO[str] | None = None, every: int = 10) -> None:
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every = max(1, int(every))
        self._n = 0
        self._width = 0

    def __call__(self, status: dict[str, Any]) -> None:
        line = format_live(status)
        if self.tty:
            pad = max(0, self._width - len(line))
            self.stream.write("\r" + line + " " * pad)
            self._width = len(line)
        elif self._n % self.every == 0:
            self.stream.write(line + "\n")
        self._n += 1
        self.stream.flush()

    def finish(self) -> None:
        """End the in-place line."""
        if self.tty and self._width:
            self.stream.write("\n")
            self.stream.flush()
            self._width = 0


def channel_suffixes(run: RunData) -> list[tuple[str, str]]:
    """(name, column suffix) of each channel of a run (one unnamed channel for older runs)."""
    chans = run.meta.get("channels") or []
    out = [(c.get("name", ""), c.get("suffix", "")) for c in chans]
    return out or [("", "")]


def exact_fei_points(rec: np.ndarray, sfx: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact-FEI cross-check as points: (window-end step, A, d), one per new valid window.

    Each exact value is placed at the step its window ended (``fei_exact_step``), not at the
    step its result came back from the worker process (paced runs), so the points sit on the
    streaming curve. Records without ``fei_exact_step`` use the step the value appeared.
    """
    amp = rec["fei_exact_amplitude" + sfx].astype(float)
    dly = rec["fei_exact_delay" + sfx].astype(float)
    ok = rec["fei_exact_valid" + sfx].astype(bool)
    name = "fei_exact_step" + sfx
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


def summarize(run_dir: str | Path, write: bool = True) -> dict[str, Any]:
    """Summary of a run directory (also of a crashed or tripped run); writes ``summary.json``.

    Returns
    -------
    dict
        ``status``, ``steps``, ``duration``, ``trip`` (rule, reason, time, step or None),
        ``fei_target`` / ``fei_command`` (whole-record A, d, f_eq of measured vs target/command),
        ``metrics`` (J1 in s, J2 and J3 in %, TI), ``online`` (mean, min, max of the valid
        streaming A and d), ``lateness`` (p50, p99, p99.9, max in s; overruns), ``estop``,
        and from the ``end`` event when it has them ``overrun_causes`` (paced overruns by
        cause: ``machine``, ``machine_backlog``, ``work``, ``work_backlog``), ``wall_time``,
        ``steps_per_second``, ``missed_replies``, ``driver_stats``, ``twin_stats``,
        ``final_alpha``.
    """
    run = read_run(run_dir)
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
    chans = channel_suffixes(run)
    if len(chans) == 1:
        out.update(_channel_summary(rec, chans[0][1], fs))
    else:
        out["channels"] = {name: _channel_summary(rec, sfx, fs) for name, sfx in chans}
    lat = rec["lateness"].astype(float) if n else np.zeros(0)
    if out["mode"] == "paced" and n:
        p50, p99, p999 = np.percentile(lat, [50, 99, 99.9])
        out["lateness"] = {
            "p50": float(p50),
            "p99": float(p99),
            "p99.9": float(p999),
            "max": float(lat.max()),
            "overruns": (end.get("lateness") or {}).get("overruns"),
        }
    for key in (
        "wall_time",
        "steps_per_second",
        "missed_replies",
        "overrun_causes",
        "driver_stats",
        "twin_stats",
        "final_alpha",
    ):
        if key in end:
            out[key] = end[key]
    if write:
        p = Path(run_dir) / "summary.json"
        p.write_text(json.dumps(_clean(out), indent=2, allow_nan=False) + "\n")
    return out


def _channel_summary(rec: np.ndarray, sfx: str, fs: float) -> dict[str, Any]:
    """FEI, metrics, online FEI and peaks of one channel (columns with suffix ``sfx``)."""
    from .fei import fei

    out: dict[str, Any] = {}
    n = len(rec)
    if n >= 16:
        target = rec["target" + sfx].astype(float)
        command = rec["command" + sfx].astype(float)
        measured = rec["measured" + sfx].astype(float)
        ok = np.isfinite(measured)
        for key, ref in (("fei_target", target), ("fei_command", command)):
            sel = ok & np.isfinite(ref)
            try:
                r = fei(ref[sel], measured[sel], fs)
                out[key] = {
                    "amplitude": float(r.amplitude),
                    "delay": float(r.delay),
                    "f_eq": float(r.f_eq),
                    "valid": bool(r.valid),
                }
            except Exception as exc:  # a record too short or degenerate: say so, don't fail
                out[key] = {"error": str(exc)}
        out["metrics"] = _metrics(target[ok], measured[ok], fs)
        fa = rec["fei_amplitude" + sfx].astype(float)
        fd = rec["fei_delay" + sfx].astype(float)
        v = rec["fei_valid" + sfx].astype(bool) & np.isfinite(fa) & np.isfinite(fd)
        if v.any():
            out["online"] = {
                "windows": int(v.sum()),
                "amplitude": {
                    "mean": float(fa[v].mean()),
                    "min": float(fa[v].min()),
                    "max": float(fa[v].max()),
                },
                "delay": {
                    "mean": float(fd[v].mean()),
                    "min": float(fd[v].min()),
                    "max": float(fd[v].max()),
                },
            }
        out["peak"] = {
            "target": float(np.nanmax(np.abs(target))),
            "measured": float(np.nanmax(np.abs(measured))),
            "force": float(np.nanmax(np.abs(rec["force" + sfx].astype(float)))),
        }
    return out


def _clean(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    return obj


def _metrics(target: np.ndarray, measured: np.ndarray, fs: float) -> dict[str, float]:
    try:
        from . import metrics
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
    if chans:
        for name, block in chans.items():
            lines.append(f"  channel {name}:")
            lines += ["  " + line for line in _format_channel(block)]
    else:
        lines += _format_channel(s)
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
                f"(+{c.get('machine_backlog')} catch-up), work {c.get('work')} "
                f"(+{c.get('work_backlog')} catch-up)"
            )
    if s.get("steps_per_second"):
        lines.append(
            f"  {s['steps_per_second']:.0f} steps/s, missed replies {s.get('missed_replies', 0)}"
        )
    return "\n".join(lines)


def _format_channel(s: dict[str, Any]) -> list[str]:
    """Summary lines of one channel (FEI, metrics, online FEI, peaks)."""
    lines: list[str] = []
    for key, label in (
        ("fei_target", "measured vs target "),
        ("fei_command", "measured vs command"),
    ):
        f = s.get(key)
        if f and "amplitude" in f:
            lines.append(
                f"  FEI {label}: A = {_fmt(f['amplitude'], spec='.4f')}, "
                f"d = {_fmt(f['delay'], 1e3, '.2f', True)} ms, "
                f"f_eq = {_fmt(f['f_eq'], spec='.3f')} Hz"
            )
    m = s.get("metrics") or {}
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
    if s.get("peak"):
        p = s["peak"]
        lines.append(
            f"  peak target {p['target'] * 1e3:.2f} mm, measured "
            f"{p['measured'] * 1e3:.2f} mm, force {p['force'] / 1e3:.2f} kN"
        )
    return lines


def plot_report(run_dir: str | Path, path: str | Path | None = None) -> Path:
    """Draw ``report.png`` (the FEI paper's Fig. 5.1 and 5.2 style); return its path.

    One channel: displacements, a zoom around the peak, online FEI A and d (streaming curve,
    exact cross-check dots at their windows' ends), lateness or Kalman. Several channels: a
    displacement panel and the FEI A and d panels per channel, then the lateness or Kalman
    panel of the first channel.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = read_run(run_dir)
    rec = run.record
    out = Path(path) if path is not None else run.path / "report.png"
    t = rec["time"].astype(float)
    mm = 1e3
    paced = run.meta.get("mode") == "paced"
    chans = channel_suffixes(run)
    multi = len(chans) > 1
    per = 3 if multi else 4
    rows = per * len(chans) + 1
    fig, axes = plt.subplots(
        rows, 1, figsize=(11, 2.6 * rows), constrained_layout=True, squeeze=False
    )
    axes = axes[:, 0]
    pair = run.meta.get("fei_pair", "target")
    for c, (name, sfx) in enumerate(chans):
        head = f"channel {name}: " if multi else ""
        ax = axes[per * c]
        ax.plot(t, rec["target" + sfx] * mm, lw=1.0, label="calculated (target)")
        ax.plot(t, rec["command" + sfx] * mm, lw=0.8, label="command")
        ax.plot(t, rec["measured" + sfx] * mm, lw=0.8, ls="--", label="measured")
        ax.set_ylabel("displacement (mm)")
        ax.set_title(f"{run.path.name}: {head}displacements (cf. the FEI paper's Fig. 5.1)")
        ax.legend(loc="upper right", fontsize=8)
        k = per * c + 1
        if not multi:  # zoom around the peak target displacement
            ax = axes[k]
            if len(t):
                i = int(np.nanargmax(np.abs(rec["target"])))
                sel = (t >= t[i] - 1.0) & (t <= t[i] + 1.0)
                ax.plot(t[sel], rec["target"][sel] * mm, lw=1.2, label="calculated (target)")
                ax.plot(t[sel], rec["command"][sel] * mm, lw=1.0, label="command")
                ax.plot(t[sel], rec["measured"][sel] * mm, lw=1.0, ls="--", label="measured")
                ax.legend(loc="upper right", fontsize=8)
            ax.set_ylabel("displacement (mm)")
            ax.set_title("around the peak")
            k += 1
        valid = rec["fei_valid" + sfx].astype(bool)
        ex_k, ex_a, ex_d = exact_fei_points(rec, sfx)
        ex_t = ex_k / run.fs
        for ax, col, exv, scale, label in (
            (axes[k], "fei_amplitude", ex_a, 1.0, "A"),
            (axes[k + 1], "fei_delay", ex_d, 1e3, "d (ms)"),
        ):
            ax.plot(t, rec[col + sfx] * scale, lw=1.0, label="online, streaming")
            ax.plot(ex_t, exv * scale, "o", ms=3, label="exact (cross-check)")
            _shade_invalid(ax, t, valid)
            ax.set_ylabel(label)
            ax.legend(loc="upper right", fontsize=8)
        axes[k].set_title(
            f"{head}online FEI, measured vs {pair} (cf. the FEI paper's Fig. 5.2); "
            "grey: invalid windows"
        )
    ax = axes[-1]
    sfx = chans[0][1]
    if paced:
        ax.plot(t, rec["lateness"] * 1e6, lw=0.6)
        ax.set_ylabel("lateness (µs)")
        ax.set_title("send time minus deadline")
    else:
        ax.plot(t, rec["kf_delay" + sfx] * 1e3, lw=1.0, label="Kalman delay (ms)")
        ax2 = ax.twinx()
        ax2.plot(t, rec["kf_gain" + sfx], lw=1.0, color="C1", label="Kalman gain")
        ax.set_ylabel("delay (ms)")
        ax2.set_ylabel("gain")
        ax.set_title(
            "Kalman estimates of the actuator" + (f" (channel {chans[0][0]})" if multi else "")
        )
    ax.set_xlabel("time (s)")
    for tr in _events(run, "trip") + _events(run, "operator_stop"):
        for a in axes:
            a.axvline(_num(tr.get("time")), color="r", lw=1.0)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def _shade_invalid(ax, t: np.ndarray, valid: np.ndarray) -> None:
    if not len(t):
        return
    inv = ~valid
    edges = np.flatnonzero(np.diff(inv.astype(np.int8), prepend=0, append=0))
    for a, b in zip(edges[::2], edges[1::2], strict=False):
        ax.axvspan(t[a], t[min(b, len(t) - 1)], color="0.9", lw=0)

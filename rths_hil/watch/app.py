"""The live page: a Bokeh document per browser session, fed from a :class:`RunFollower`.

Each session refreshes every :data:`REFRESH_S` (5.5 Hz): the shared follower reads what is new on
disk (at most once per refresh period whatever the number of sessions), and the session sends
the browser only what changed. The cost of a refresh in the browser is mostly the repaint of
each plot whose data or range changed (every renderer of such a plot is painted again), so:

* the 10 s plots get the new rows only (:meth:`ColumnDataSource.stream` with a rollover of
  10 s), decimated by a stride aligned to the step index, so a point never moves: the
  displacement at every refresh, the FEI A and d (estimates over a window of seconds) every
  :data:`FEI_S`, on a time axis of their own; the time axes are set, and the value axes move
  only when the data leaves them or uses less than a third of them;
* the whole-test plot (the minimum and maximum of each bucket of about one pixel, only for
  completed buckets), the force–displacement loop, the lateness plot (on its own time axis),
  the limit bars and the counts are refreshed once per :data:`SLOW_S`;
* text boxes change only when their text does (a text box re-lays out the page);
* a session that looks back (replay slider) gets the window it asks for, whole.

Per channel: target / command / measured over the window and the whole test (overview); the
online FEI amplitude A(t) and delay d(t) (the FEI paper, Eq. 2.2 and 2.5; streaming and exact)
with the safety rule's tolerance bands and the windows where the FEI is invalid greyed; the
Kalman gain and delay on the same axes; the force–displacement loop; the share of every safety
limit in use as bars. For the run: its state (running, completed, e-stop with rule, channel and
time, operator stop, killed), the loop's lateness and overruns, the event list, a time slider to
replay a finished run, and the operator-stop button.

Nothing on the page can start or change motion: the only action is the operator stop, which
sends the run's process SIGINT (what Ctrl-C sends), after a confirmation.
"""

from __future__ import annotations

import html
import logging
import math
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from bokeh.document import Document
from bokeh.layouts import column, row
from bokeh.models import (
    BoxAnnotation,
    Button,
    ColumnDataSource,
    CustomJS,
    Div,
    FactorRange,
    Legend,
    Range1d,
    Slider,
    Span,
    Toggle,
)
from bokeh.plotting import figure

from .source import RunFollower, RunState, channel_column

__all__ = [
    "FEI_S",
    "REFRESH_S",
    "SLOW_S",
    "WINDOW_POINTS",
    "WINDOW_S",
    "WatchContext",
    "build_document",
]

log = logging.getLogger(__name__)

REFRESH_S = 0.18  # s between two refreshes of a page (5.5 Hz: ≥ 5 Hz with the timer's jitter)
SLOW_S = 1.0  # s between two refreshes of the slow panels (overview, loop, lateness, bars)
FEI_S = 2 * REFRESH_S  # s between two refreshes of the FEI plots (window estimates)
TICK_S = 0.03  # s between two checks whether a refresh is due
IN_FLIGHT = 2  # refreshes sent and not yet applied by the browser, at most
WINDOW_S = 10.0  # s of record in the detailed plots
WINDOW_POINTS = 600  # at most this many points per line in the detailed plots
OVERVIEW_BUCKETS = 500  # buckets (about one pixel each) of the whole-test plot
CONFIRM_S = 10.0  # s the stop confirmation stays open

#: Columns of the 10 s displacement plot's source, and of the FEI plots' source (delays in ms).
WINDOW_COLUMNS = ("t", "target", "command", "measured")
FEI_COLUMNS = ("t", "a", "d", "a_ex", "d_ex", "kf_g", "kf_d")

COLORS = {
    "target": "#1f77b4",
    "command": "#2ca02c",
    "measured": "#d62728",
    "exact": "#9467bd",
    "kalman": "#ff7f0e",
}
_BANNER = {
    "missing": ("#6b7280", "WAITING"),
    "empty": ("#6b7280", "WAITING"),
    "unreadable": ("#b45309", "UNREADABLE"),
    "starting": ("#2563eb", "STARTING"),
    "running": ("#15803d", "RUNNING"),
    "completed": ("#1d4ed8", "COMPLETED"),
    "trip": ("#b91c1c", "E-STOP"),
    "operator_stop": ("#c2410c", "OPERATOR STOP"),
    "error": ("#b91c1c", "ERROR"),
    "killed": ("#7f1d1d", "KILLED"),
}


@dataclass
class WatchContext:
    """What every session of one ``rths-hil watch`` server shares.

    Attributes
    ----------
    follower : RunFollower
        The run being followed.
    token : str or None
        When set, a session must carry ``?token=<token>`` in its URL.
    allow_stop : bool
        Show the operator-stop button (when the writing process is known).
    notify : callable, optional
        Called with one line for the terminal (state changes, stop sent).
    """

    follower: RunFollower
    token: str | None = None
    allow_stop: bool = True
    notify: Callable[[str], None] | None = None
    _polled_at: float = -1e9
    _state: RunState | None = None
    _last_phase: str | None = None

    def state(self) -> RunState:
        """Poll the follower at most once per refresh period (shared by all sessions)."""
        now = time.monotonic()
        if self._state is None or now - self._polled_at >= 0.5 * REFRESH_S:
            self._state = self.follower.poll(now)
            self._polled_at = now
            if self._state.phase != self._last_phase:
                self._last_phase = self._state.phase
                self.say(f"{self._state.phase}: {self._state.message}")
        return self._state

    def say(self, line: str) -> None:
        """One line for the terminal."""
        if self.notify is not None:
            self.notify(line)


# ----------------------------------------------------------------------------------------------
# data helpers


def _stride(n_rows: int, points: int) -> int:
    return max(1, math.ceil(n_rows / points))


def _col(rec: np.ndarray, names, base: str, ch: str, idx) -> np.ndarray:
    name = channel_column(names, base, ch)
    if name is None:
        return np.full(len(idx) if not isinstance(idx, slice) else 0, np.nan)
    return np.asarray(rec[name][idx], dtype=float)


def _block_max(x: np.ndarray, m: int) -> np.ndarray:
    """Max of each block of ``m`` samples (the last block may be short)."""
    if m == 1 or x.size == 0:
        return x
    n = x.size // m * m
    out = x[:n].reshape(-1, m).max(axis=1)
    if n < x.size:
        out = np.append(out, x[n:].max())
    return out


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end indices (end exclusive) of the runs of True in ``mask``."""
    if mask.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _tail_run(mask: np.ndarray) -> int:
    """Length of the run of True at the end of ``mask``."""
    if mask.size == 0 or not mask[-1]:
        return 0
    false = np.flatnonzero(~mask)
    return int(mask.size - (false[-1] + 1 if false.size else 0))


def _num(x, default: float = 0.0) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


def _envelope(x: np.ndarray, m: int) -> np.ndarray:
    """Minimum and maximum of each block of ``m`` samples, in the order they occur.

    Returns ``2 · (x.size // m)`` values: per block, its extreme that comes first, then the
    other. Drawn as a line through two points per block of about one pixel, this is the
    signal's envelope at that resolution: no peak is lost to decimation (unlike a stride).
    NaN samples are ignored; a block of NaN gives NaN.
    """
    nb = x.size // m
    b = x[: nb * m].reshape(nb, m)
    nan = np.isnan(b)
    lo = np.where(nan, np.inf, b)
    hi = np.where(nan, -np.inf, b)
    i_lo, i_hi = lo.argmin(axis=1), hi.argmax(axis=1)
    r = np.arange(nb)
    v_lo, v_hi = lo[r, i_lo], hi[r, i_hi]
    empty = nan.all(axis=1)
    v_lo[empty] = np.nan
    v_hi[empty] = np.nan
    lo_first = i_lo <= i_hi
    out = np.empty((nb, 2))
    out[:, 0] = np.where(lo_first, v_lo, v_hi)
    out[:, 1] = np.where(lo_first, v_hi, v_lo)
    return out.ravel()


def _fit(rng: Range1d, lo: float, hi: float, min_span: float) -> None:
    """Move a value axis only when the data leaves it or uses less than a third of it.

    A value axis that follows the data at every refresh moves its ticks and labels at every
    refresh; this one changes a few times in a test, and then with 15 % of room on each side.
    """
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return
    span = max(hi - lo, min_span)
    start, end = rng.start, rng.end
    if lo >= start and hi <= end and span >= (end - start) / 3:
        return
    mid = 0.5 * (lo + hi)
    rng.start = min(lo, mid - 0.5 * span) - 0.15 * span
    rng.end = max(hi, mid + 0.5 * span) + 0.15 * span


class _Invalid:
    """The spans of loop time where a channel's FEI is invalid, found incrementally.

    Spans closer than ``gap`` samples are one span (the plot cannot show the gap); a span still
    open at the newest row reaches far to the right (``r = +1e6 s``), so that the greyed area
    follows the data without a change of the source at every refresh.
    """

    OPEN = 1e6  # s added to the start of a span still open

    def __init__(self, gap: int) -> None:
        self.gap = max(1, gap)
        self.upto = 0  # rows read
        self.spans: list[list[int]] = []  # [first row, end row (exclusive) or -1 while open]

    def update(self, valid: np.ndarray, a: int) -> None:
        """Read the validity of rows ``a, a + 1, …`` (``a`` = :attr:`upto`)."""
        inv = ~np.asarray(valid, dtype=bool)
        end = a + inv.size
        if self.spans and self.spans[-1][1] == -1 and inv.size and not inv[0]:
            self.spans[-1][1] = a  # the span open at the last read ended there
        s, e = _runs(inv)
        for s_i, e_i in zip((s + a).tolist(), (e + a).tolist(), strict=True):
            last = self.spans[-1] if self.spans else None
            if last is not None and (last[1] == -1 or s_i - last[1] < self.gap):
                last[1] = e_i  # continues the open span, or joins one that ended a moment ago
            else:
                self.spans.append([s_i, e_i])
        if self.spans and self.spans[-1][1] == end:
            self.spans[-1][1] = -1  # still invalid at the newest row
        self.upto = end

    def columns(self, t0: float, fs: float, t_from: float) -> dict:
        """The spans ending after loop time ``t_from`` as the strip source's columns."""
        half = 0.5 / fs
        left, right = [], []
        for s, e in self.spans:
            r = t0 + (e - 1) / fs + half if e != -1 else t0 + s / fs + self.OPEN
            if r >= t_from:
                left.append(t0 + s / fs - half)
                right.append(r)
        return {"l": left, "r": right}


# ----------------------------------------------------------------------------------------------
# the document


def channel_config(cfg: dict, ch: str) -> dict:
    """The configuration one channel ran with: its ``[[actuators]]`` entry over the top level."""
    out = dict(cfg)
    for entry in cfg.get("actuators") or []:
        if isinstance(entry, dict) and entry.get("name") == ch and ch:
            for section, table in entry.items():
                if isinstance(table, dict):
                    out[section] = {**(cfg.get(section) or {}), **table}
    return out


def _consecutive(flag: np.ndarray, carry: int) -> np.ndarray:
    """Length of the run of True ending at each sample (``carry``: the run before the first)."""
    n = flag.size
    pos = np.arange(1, n + 1)
    last_false = np.maximum.accumulate(np.where(flag, 0, pos))
    count = pos - last_false
    return np.where(last_false == 0, count + carry, count)


class _Limits:
    """Share of each safety limit in use for one channel, updated incrementally.

    For each limit of ``[safety]`` (the loop's rules, :mod:`rths_hil.safety`): ``now`` is the
    share over the latest refresh period (the latest value for the FEI and Kalman estimates,
    the current run for consecutive counts), ``peak`` the largest share so far. 1 = the limit.
    """

    def __init__(self, ch: str, safety: dict, cfg: dict, paced: bool) -> None:
        self.ch = ch
        self.safety = safety
        self.cfg = cfg
        self.paced = paced
        fs = _num(cfg.get("loop", {}).get("fs"), 1.0) if cfg else 1.0
        self.thr = _num((cfg.get("loop", {}) or {}).get("overrun_threshold"), 0.5) / fs
        self.reset()

    def reset(self) -> None:
        self.upto = 0
        self.peak: dict[str, float] = {}
        self.last: dict[str, float] = {}
        self.carry: dict[str, int] = {}

    def _shares(self, rec, names, a: int, b: int) -> dict[str, np.ndarray]:
        """Share of each limit at each row of ``[a, b)``."""
        sf, ch = self.safety, self.ch
        out: dict[str, np.ndarray] = {}

        def col(base: str) -> np.ndarray | None:
            name = channel_column(names, base, ch)
            return None if name is None else np.asarray(rec[name][a:b], dtype=float)

        for label, bases, key in (
            ("displacement", ("target", "command", "measured"), "displacement_limit"),
            ("velocity", ("velocity",), "velocity_limit"),
            ("force", ("force",), "force_limit"),
        ):
            lim = _num(sf.get(key))
            cols = [c for c in (col(x) for x in bases) if c is not None]
            if lim > 0 and cols:
                out[label] = np.max(np.abs(np.vstack(cols)), axis=0) / lim
        for label, base, key, ref in (
            ("FEI |A−1|", "fei_amplitude", "fei_amplitude_tol", 1.0),
            ("FEI |d|", "fei_delay", "fei_delay_tol", 0.0),
        ):
            tol, x = _num(sf.get(key)), col(base)
            if tol > 0 and x is not None:
                out[label] = np.abs(x - ref) / tol
        g = col("kf_gain")
        if (self.cfg.get("kalman", {}) or {}).get("enabled", True) and g is not None:
            gmin, gmax = _num(sf.get("kf_gain_min"), 0.5), _num(sf.get("kf_gain_max"), 1.5)
            ref = 1.0 if gmin < 1.0 < gmax else 0.5 * (gmin + gmax)
            up, down = max(gmax - ref, 1e-12), max(ref - gmin, 1e-12)
            out["Kalman gain"] = np.where(g >= ref, (g - ref) / up, (ref - g) / down)
            dmax, d = _num(sf.get("kf_delay_max")), col("kf_delay")
            if dmax > 0 and d is not None:
                out["Kalman delay"] = np.abs(d) / dmax
        ok = channel_column(names, "feedback_ok", ch)
        wd = _num(sf.get("watchdog_missed"))
        if ok is not None and wd > 0:
            miss = ~np.asarray(rec[ok][a:b], dtype=bool)
            run = _consecutive(miss, self.carry.get("missed replies", 0))
            out["missed replies"] = run / wd
        mo = _num(sf.get("max_overruns"))
        if self.paced and mo > 0 and "lateness" in names:
            over = np.asarray(rec["lateness"][a:b], dtype=float) > self.thr
            run = _consecutive(over, self.carry.get("overruns", 0))
            out["overruns"] = run / mo
        return out

    def update(self, rec, names, k_end: int, now_rows: int) -> dict:
        """Shares up to row ``k_end`` as the bar chart's columns."""
        if k_end < self.upto:
            self.reset()
        a = self.upto
        if k_end > a:
            for label, x in self._shares(rec, names, a, k_end).items():
                fin = x[np.isfinite(x)]
                if fin.size:
                    self.peak[label] = max(self.peak.get(label, 0.0), float(fin.max()))
                    self.last[label] = float(fin[-1])
                if label in ("missed replies", "overruns"):
                    scale = _num(
                        self.safety.get("watchdog_missed" if label[0] == "m" else "max_overruns"), 1
                    )
                    self.carry[label] = round(float(x[-1]) * scale)
            self.upto = k_end
        recent = self._shares(rec, names, max(0, k_end - now_rows), k_end)
        labels, now_v, peak_v = [], [], []
        for label in self.peak:
            x = recent.get(label, np.zeros(0))
            x = x[np.isfinite(x)]
            if label in ("displacement", "velocity", "force"):
                now = float(x.max()) if x.size else 0.0
            else:
                now = self.last.get(label, 0.0)
            labels.append(label)
            now_v.append(min(now, 1.1))
            peak_v.append(min(self.peak[label], 1.1))
        colors = ["#16a34a" if u < 0.7 else "#f59e0b" if u < 0.9 else "#dc2626" for u in now_v]
        return {"limit": labels, "used": now_v, "peak": peak_v, "color": colors}


class _ChannelView:
    """The plots of one actuator channel and what the browser already holds of them."""

    def __init__(
        self,
        ch: str,
        label: str,
        safety: dict,
        cfg: dict,
        paced: bool,
        x_range: Range1d,
        fei_range: Range1d,
        overview_range: Range1d,
        fs: float,
        gap: int,
    ) -> None:
        self.ch = ch
        self.fs = fs
        sfx = "_" + ch if ch else ""
        w = 560
        tools = "pan,wheel_zoom,box_zoom,reset,save"
        # the 10 s window (streamed), the force–displacement loop and the whole test (slow)
        self.win = ColumnDataSource(data={k: [] for k in WINDOW_COLUMNS}, name=f"window{sfx}")
        self.fei = ColumnDataSource(data={k: [] for k in FEI_COLUMNS}, name=f"fei{sfx}")
        self.fd = ColumnDataSource(data={"measured": [], "force": []}, name=f"loop{sfx}")
        self.ovw = ColumnDataSource(
            data={"t": [], "target": [], "measured": []}, name=f"overview{sfx}"
        )
        self.invalid = ColumnDataSource(data={"l": [], "r": []}, name=f"invalid{sfx}")
        self.bars = ColumnDataSource(data={"limit": [], "used": [], "peak": [], "color": []})
        self.title = Div(
            text=f"<h2 style='margin:8px 0 0 0'>Channel {html.escape(label)}</h2>",
            name=f"title{sfx}",
        )
        self.invalid_tracker = _Invalid(gap)
        self.ovw_bucket = 0  # rows per bucket of the whole-test plot (0: not started)
        self.ovw_upto = 0  # rows of the record already in it
        self.ovw_whole = -1  # rows of the ended run when it was drawn whole

        # value axes set by the refresh (see _fit): an automatic range moves at every refresh
        self.y_disp = Range1d(-1e-3, 1e-3)
        p = figure(
            title="displacement: last 10 s",
            height=260,
            width=w,
            x_range=x_range,
            y_range=self.y_disp,
            tools=tools,
            x_axis_label="time (s)",
            y_axis_label="m",
        )
        for key in ("target", "command", "measured"):
            p.line("t", key, source=self.win, color=COLORS[key], legend_label=key, line_width=1.6)
        p.legend.location = "top_left"
        p.legend.click_policy = "hide"
        self.disp = p

        q = figure(
            title="displacement: whole test (min/max per pixel)",
            height=260,
            width=w,
            x_range=overview_range,
            tools=tools,
            x_axis_label="time (s)",
            y_axis_label="m",
        )
        q.line("t", "target", source=self.ovw, color=COLORS["target"], legend_label="target")
        q.line("t", "measured", source=self.ovw, color=COLORS["measured"], legend_label="measured")
        q.legend.location = "top_left"
        self.window_box = BoxAnnotation(left=0, right=0, fill_color="#fbbf24", fill_alpha=0.25)
        q.add_layout(self.window_box)
        self.overview = q

        a_tol = _num(safety.get("fei_amplitude_tol"))
        d_tol = _num(safety.get("fei_delay_tol"))
        self.y_a = Range1d(0.9, 1.1)
        self.y_d = Range1d(-5.0, 5.0)
        pa = figure(
            title="FEI amplitude A (1 = perfect); Kalman gain",
            height=220,
            width=w,
            x_range=fei_range,
            y_range=self.y_a,
            tools=tools,
            x_axis_label="time (s)",
        )
        pd = figure(
            title="FEI delay d (ms, > 0: measured lags); Kalman delay",
            height=220,
            width=w,
            x_range=fei_range,
            y_range=self.y_d,
            tools=tools,
            x_axis_label="time (s)",
        )
        for fig, key, ex, kf, tol, label in (
            (pa, "a", "a_ex", "kf_g", a_tol, "A"),
            (pd, "d", "d_ex", "kf_d", d_tol * 1e3, "d"),
        ):
            fig.vstrip(x0="l", x1="r", source=self.invalid, fill_color="#9ca3af", fill_alpha=0.35)
            lines = [
                fig.line("t", key, source=self.fei, color=COLORS["measured"], line_width=1.6),
                fig.line("t", ex, source=self.fei, color=COLORS["exact"], line_dash="dashed"),
                fig.line("t", kf, source=self.fei, color=COLORS["kalman"]),
            ]
            fig.add_layout(
                Legend(
                    items=[
                        (f"{label} streaming", [lines[0]]),
                        (f"{label} exact", [lines[1]]),
                        ("Kalman", [lines[2]]),
                    ],
                    location="top_left",
                    orientation="horizontal",
                    background_fill_alpha=0.6,
                )
            )
            if tol > 0:  # the band, its edges dotted (one renderer: each costs a repaint)
                ref = 1.0 if key == "a" else 0.0
                fig.add_layout(
                    BoxAnnotation(
                        bottom=ref - tol,
                        top=ref + tol,
                        fill_color="#22c55e",
                        fill_alpha=0.12,
                        line_color="#16a34a",
                        line_dash="dotted",
                        line_alpha=1.0,
                    )
                )
        self.fei_a, self.fei_d = pa, pd

        pf = figure(
            title="force–displacement (last 10 s)",
            height=260,
            width=w,
            tools=tools,
            x_axis_label="measured displacement (m)",
            y_axis_label="force (N)",
        )
        pf.line("measured", "force", source=self.fd, color="#374151")
        self.loop = pf

        factors = [
            "displacement",
            "velocity",
            "force",
            "FEI |A−1|",
            "FEI |d|",
            "Kalman gain",
            "Kalman delay",
            "missed replies",
            "overruns",
        ]
        pb = figure(
            title="share of each safety limit in use (bar: now, ◆: peak)",
            height=260,
            width=w,
            y_range=FactorRange(factors=factors[::-1]),
            x_range=(0, 1.1),
            tools="",
            toolbar_location=None,
        )
        pb.hbar(y="limit", right="used", height=0.6, color="color", source=self.bars)
        pb.scatter("peak", "limit", marker="diamond", size=10, color="#111827", source=self.bars)
        pb.add_layout(Span(location=1.0, dimension="height", line_color="#b91c1c", line_width=2))
        self.margin = pb
        self.limits = _Limits(ch, safety, cfg, paced)
        self.layout = column(self.title, row(p, q), row(pa, pd), row(pf, pb))

    # -- data ----------------------------------------------------------------------------------
    def window_data(self, rec: np.ndarray, names, idx: slice, group: str = "win") -> dict:
        """The columns of the 10 s plots' source ``group`` (``win``, ``fei``) at rows ``idx``."""
        ch = self.ch
        t = np.asarray(rec["time"][idx], dtype=float)
        if group == "win":
            return {
                "t": t,
                "target": _col(rec, names, "target", ch, idx),
                "command": _col(rec, names, "command", ch, idx),
                "measured": _col(rec, names, "measured", ch, idx),
            }
        return {
            "t": t,
            "a": _col(rec, names, "fei_amplitude", ch, idx),
            "d": _col(rec, names, "fei_delay", ch, idx) * 1e3,
            "a_ex": _col(rec, names, "fei_exact_amplitude", ch, idx),
            "d_ex": _col(rec, names, "fei_exact_delay", ch, idx) * 1e3,
            "kf_g": _col(rec, names, "kf_gain", ch, idx),
            "kf_d": _col(rec, names, "kf_delay", ch, idx) * 1e3,
        }

    def fit_axes(self, group: str) -> None:
        """Value axes of the 10 s plots of ``group`` around the data they hold."""

        def span(data, *keys: str) -> tuple[float, float]:
            x = np.concatenate([np.asarray(data[k], dtype=float) for k in keys])
            x = x[np.isfinite(x)]
            return (float(x.min()), float(x.max())) if x.size else (math.nan, math.nan)

        if group == "win":
            _fit(self.y_disp, *span(self.win.data, "target", "command", "measured"), 1e-4)
        else:
            _fit(self.y_a, *span(self.fei.data, "a", "a_ex", "kf_g"), 0.02)
            _fit(self.y_d, *span(self.fei.data, "d", "d_ex", "kf_d"), 1.0)

    def overview_update(self, rec: np.ndarray, names, rows: int, planned: int, final: bool):
        """Extend the whole-test plot with the buckets completed since the last call.

        Buckets of ``(planned or rows) / OVERVIEW_BUCKETS`` rows (about one pixel), each drawn
        as its minimum and maximum (:func:`_envelope`); when the run outgrows the planned
        length the buckets double and the plot is rebuilt. ``final``: the run has ended, the
        last, incomplete bucket is drawn too (replacing the source).
        """
        if final and rows == self.ovw_whole:
            return
        want = max(1, math.ceil(max(rows, planned) / OVERVIEW_BUCKETS))
        rebuild = final or self.ovw_bucket == 0 or want > 2 * self.ovw_bucket
        if self.ovw_bucket == 0 or want > 2 * self.ovw_bucket:
            self.ovw_bucket = want
        if rebuild:
            self.ovw_upto = 0
        if final:
            self.ovw_whole = rows
        m = self.ovw_bucket
        a = self.ovw_upto
        b = rows if final else a + (rows - a) // m * m
        if b <= a and not rebuild:
            return
        t = np.asarray(rec["time"][a:b:m], dtype=float)
        ends = np.minimum(np.arange(a, b, m) + m, b)
        half = 0.5 * (ends - np.arange(a, b, m)) / self.fs
        data = {"t": np.column_stack([t, t + half]).ravel()}
        for key in ("target", "measured"):
            x = _col(rec, names, key, self.ch, slice(a, b))
            pad = (-x.size) % m  # the last, incomplete bucket (final only): NaN-padded
            data[key] = _envelope(np.append(x, np.full(pad, np.nan)), m)
        self.ovw_upto = b
        if rebuild:
            self.ovw.data = data
        else:
            self.ovw.stream(data)


class _Page:
    """One session's document and its refresh."""

    def __init__(self, doc: Document, ctx: WatchContext) -> None:
        self.doc = doc
        self.ctx = ctx
        self.follow = True
        self.channels: list[str] | None = None
        self.views: list[_ChannelView] = []
        self.n_events = -1
        self.stop_sent = False
        self.confirm_until = 0.0
        self.replay_playing = False

        # fixed sizes: a text change then needs no new page layout in the browser
        self.state_div = Div(text="", name="state", width=1140, height=70)
        self.info_div = Div(text="", name="info", width=1140, height=40)
        self._slider_at = 0.0
        self._slow_at = 0.0
        self._last_key = None
        self._n_ovr = 0
        # what the browser holds of each 10 s source group (``win``, ``fei``): every m-th row
        # up to the row in ``_next`` (exclusive) while following the live end; absent: nothing
        # to stream onto (replace it)
        self._next: dict[str, int] = {}
        self._fei_at = 0.0
        self.stop_btn = Button(
            label="Operator stop…", button_type="danger", name="stop", visible=False, width=160
        )
        self.confirm_div = Div(
            text="<b>Stop the run now?</b> The loop sends the e-stop to every actuator and "
            "flushes the record (the same as Ctrl-C in the run's terminal).",
            visible=False,
            width=520,
        )
        self.confirm_btn = Button(
            label="Yes, stop the run", button_type="danger", name="confirm", visible=False
        )
        self.cancel_btn = Button(label="Cancel", name="cancel", visible=False)
        self.stop_btn.on_click(self._ask)
        self.confirm_btn.on_click(self._stop)
        self.cancel_btn.on_click(self._cancel)

        self.slider = Slider(
            start=0.0,
            end=1.0,
            value=1.0,
            step=0.01,
            title="window ends at (s)",
            width=700,
            name="slider",
            disabled=True,
        )
        self._setting = False  # True while the page itself moves the slider
        self.slider.on_change("value", self._slid)
        self.play = Toggle(label="▶ replay", name="play", width=100, disabled=True)
        self.play.on_change("active", self._play)
        self.live_btn = Button(label="follow the end", name="follow", width=120)
        self.live_btn.on_click(self._follow)

        # set by each refresh (an automatic range, recomputed from every plot sharing it at each
        # data change, cost the browser far more than the plots themselves); the lateness plot
        # has its own, set once per SLOW_S: a plot whose range moves is painted again
        self.x_range = Range1d(0.0, WINDOW_S)
        self.fei_range = Range1d(0.0, WINDOW_S)
        self.lat_range = Range1d(0.0, WINDOW_S)
        self.overview_range = Range1d(0.0, 1.0)

        self.lat_src = ColumnDataSource(data={"t": [], "lat": []}, name="lateness")
        lp = figure(
            title="lateness of the send (ms; paced; 0 in lockstep)",
            height=200,
            width=560,
            x_range=self.lat_range,
            tools="pan,wheel_zoom,box_zoom,reset,save",
            x_axis_label="time (s)",
        )
        lp.line("t", "lat", source=self.lat_src, color="#374151")
        self.thr_span = Span(
            location=0, dimension="width", line_color="#b91c1c", line_dash="dashed"
        )
        lp.add_layout(self.thr_span)
        self.lat_plot = lp
        self.ev_src = ColumnDataSource(data={"time": [], "kind": [], "detail": []}, name="events")
        # the event list as an HTML table in a text box: a DataTable (SlickGrid) re-measured
        # itself at every redraw of the page and cost the browser more than all the plots
        self.ev_table = Div(text="", width=560, height=200, styles={"overflow-y": "auto"})
        self.channel_box = column(Div(text=""))
        # flow control: each refresh ends with a new ``tick``; the browser echoes it into
        # ``ack`` once it has applied that refresh. At most IN_FLIGHT refreshes are sent and not
        # yet applied, so a slow browser gets fewer refreshes instead of a growing backlog.
        self.seq = 0
        self.acked = 0
        self.sent_at = 0.0
        # (plain models, not widgets: changing them costs the browser no new page layout)
        self.tick = Range1d(0, 1, name="tick")
        self.ack = Range1d(0, 1, name="ack")
        self.tick.js_on_change(
            "start", CustomJS(args={"ack": self.ack}, code="ack.start = cb_obj.start")
        )
        self.ack.on_change("start", self._acked)
        controls = row(
            self.stop_btn, self.confirm_div, self.confirm_btn, self.cancel_btn, name="controls"
        )
        replay = row(self.slider, self.play, self.live_btn)
        self.root = column(
            self.state_div,
            self.info_div,
            controls,
            replay,
            self.channel_box,
            Div(text="<h2 style='margin:8px 0 0 0'>Run</h2>"),
            row(self.lat_plot, self.ev_table),
        )
        doc.add_root(self.root)
        doc.add_root(self.ev_src)  # the events as data (for tools reading the page)
        doc.add_root(self.tick)
        doc.add_root(self.ack)
        doc.title = "rths-hil watch"
        self.refresh()
        doc.add_periodic_callback(self.refresh, int(TICK_S * 1000))

    # -- controls ------------------------------------------------------------------------------
    def _ask(self) -> None:
        self.confirm_until = time.monotonic() + CONFIRM_S
        self._show_confirm(True)

    def _cancel(self) -> None:
        self.confirm_until = 0.0
        self._show_confirm(False)

    def _show_confirm(self, on: bool) -> None:
        self.confirm_div.visible = on
        self.confirm_btn.visible = on
        self.cancel_btn.visible = on

    def _stop(self) -> None:
        self._show_confirm(False)
        if time.monotonic() > self.confirm_until:
            return
        self.confirm_until = 0.0
        try:
            pid = self.ctx.follower.signal_writer(signal.SIGINT)
        except OSError as exc:
            self.ctx.say(f"operator stop: cannot signal the run's process: {exc.strerror}")
            return
        if pid is None:
            self.ctx.say("operator stop: no process is writing the record; nothing sent")
            return
        self.stop_sent = True
        self.stop_btn.disabled = True
        self.stop_btn.label = "stop sent"
        self.ctx.say(f"operator stop: SIGINT sent to the run (process {pid})")

    def _slid(self, attr, old, new) -> None:
        if self._setting:
            return
        self.follow = False
        self.replay_playing = self.replay_playing and self.play.active
        self.refresh()

    def _set_slider(self, value: float) -> None:
        self._setting = True
        try:
            self.slider.value = value
        finally:
            self._setting = False

    def _play(self, attr, old, new) -> None:
        self.replay_playing = bool(new)
        self.follow = False
        if new and self.slider.value >= self.slider.end - 1e-9:
            self._set_slider(min(self.slider.start + WINDOW_S, self.slider.end))

    def _follow(self) -> None:
        self.follow = True
        self.play.active = False
        self.refresh()

    def _acked(self, attr, old, new) -> None:
        try:
            self.acked = int(new)
        except (TypeError, ValueError):
            pass

    # -- refresh -------------------------------------------------------------------------------
    def _build_channels(self, chans: list[str], safety: dict) -> None:
        self.channels = chans
        f = self.ctx.follower
        meta, fs = f.meta, f.fs()
        gap = _stride(round(WINDOW_S * fs), WINDOW_POINTS)
        self.views = []
        for ch in chans:
            cfg = channel_config(meta.get("config", {}) or {}, ch)
            self.views.append(
                _ChannelView(
                    ch,
                    ch or str(meta.get("driver", "actuator")),
                    cfg.get("safety", {}) or {},
                    cfg,
                    meta.get("mode") == "paced",
                    self.x_range,
                    self.fei_range,
                    self.overview_range,
                    fs,
                    gap,
                )
            )
        self._next = {}
        self.channel_box.children = [v.layout for v in self.views]

    def refresh(self) -> None:
        """Read the follower's latest state and redraw (called every :data:`REFRESH_S`)."""
        now = time.monotonic()
        if now - self.sent_at < REFRESH_S - 0.5 * TICK_S:
            return
        if self.seq - self.acked > IN_FLIGHT - 1 and now - self.sent_at < 2.0:
            return  # the browser has not applied the refreshes already sent
        try:
            self._refresh()
        finally:
            # last: the browser applies the changes in order, so the tick comes after the data
            self.seq += 1
            self.sent_at = now
            self.tick.start = self.seq

    def _refresh(self) -> None:
        st = self.ctx.state()
        f = self.ctx.follower
        self._banner(st)
        if time.monotonic() > self.confirm_until and self.confirm_btn.visible:
            self._show_confirm(False)
        self.stop_btn.visible = (
            self.ctx.allow_stop and st.live and st.writer is not None
        ) or self.stop_sent
        if f.record is None or f.rows == 0:
            return
        cfg = f.meta.get("config", {}) or {}
        safety = cfg.get("safety", {}) or {}
        chans = f.channels
        if chans != self.channels:
            self._build_channels(chans, safety)
        rec, names, fs = f.record, f.names, f.fs()
        t_last = float(rec["time"][-1])
        t_first = float(rec["time"][0])
        # replay slider
        # the slider follows a live run every 5 s (a change of a widget re-lays out the page)
        now = time.monotonic()
        if not st.live or now - self._slider_at >= 5.0:
            self._slider_at = now
            self._setting = True
            try:
                self.slider.start = t_first
                self.slider.end = max(t_last, t_first + 1.0 / fs)
                self.slider.step = max(1.0 / fs, 0.01)
                self.slider.disabled = False
            finally:
                self._setting = False
        self.play.disabled = not st.finished
        if self.replay_playing:
            v = self.slider.value + REFRESH_S
            if v >= t_last:
                v = t_last
                self.play.active = False
            self._set_slider(v)
        if self.follow and self._slider_at == now:
            self._set_slider(t_last)
        t_end = t_last if self.follow else min(self.slider.value, t_last)
        k_end = min(f.rows, round((t_end - t_first) * fs) + 1)
        key = (k_end, f.rows, st.phase, len(f.events), self.follow)
        if key == self._last_key:
            return  # nothing new: the browser redraws nothing
        self._last_key = key
        # the slow panels: once per SLOW_S while live, at each change otherwise
        slow = not st.live or now - self._slow_at >= SLOW_S
        if slow:
            self._slow_at = now
        n_win = round(WINDOW_S * fs)
        m = _stride(n_win, WINDOW_POINTS)  # the window's stride: fixed for the run
        k0 = max(0, k_end - n_win)
        first = k0 + (-k0) % m  # stride aligned to the step index: a point never moves
        t_from = max(t_end - WINDOW_S, t_first)
        self.x_range.start = t_from
        self.x_range.end = t_from + WINDOW_S
        rollover = math.ceil(n_win / m) + 1
        self._window("win", rec, names, first, k_end, m, rollover)
        # the FEI plots: every FEI_S while following a live run (the FEI and Kalman estimates
        # are over a window of seconds); at each change otherwise
        if not (st.live and self.follow) or now - self._fei_at >= FEI_S - 0.5 * TICK_S:
            self._fei_at = now
            self.fei_range.start = t_from
            self.fei_range.end = t_from + WINDOW_S
            self._window("fei", rec, names, first, k_end, m, rollover)
            for v in self.views:
                valid_name = channel_column(names, "fei_valid", v.ch)
                if valid_name is None:
                    continue
                tr = v.invalid_tracker
                if f.rows > tr.upto:
                    tr.update(rec[valid_name][tr.upto : f.rows], tr.upto)
                spans = tr.columns(t_first, fs, t_from)
                if spans != v.invalid.data:
                    v.invalid.data = spans
        self.overview_range.start = t_first
        self.overview_range.end = max(t_first + f.planned_duration(), t_last)
        thr = _num((cfg.get("loop", {}) or {}).get("overrun_threshold"), 0.5) / fs
        self.thr_span.location = thr * 1e3
        if slow:
            self._slow(st, f, rec, names, fs, (first, k_end, m), t_from, t_end, thr)
        self._events(f.events)
        self.info_div.text = self._info(st, t_end)  # sent only when it changed

    def _window(self, group: str, rec, names, first: int, k_end: int, m: int, roll: int) -> None:
        """Send the 10 s source ``group`` of every channel: rows ``first:k_end:m``.

        While following the live end, only the rows new since the last time (streamed with a
        rollover of ``roll`` points: the browser drops those older than the window); else the
        whole window.
        """
        nxt = self._next.get(group)
        stream = self.follow and nxt is not None and first <= nxt <= k_end
        a = nxt if stream else first
        if self.follow:
            self._next[group] = a + m * max(0, math.ceil((k_end - a) / m))
        else:
            self._next.pop(group, None)
        for v in self.views:
            src = v.win if group == "win" else v.fei
            if not stream:
                src.data = v.window_data(rec, names, slice(first, k_end, m), group)
            elif a < k_end:
                src.stream(v.window_data(rec, names, slice(a, k_end, m), group), roll)
            v.fit_axes(group)

    def _slow(self, st, f, rec, names, fs, rows, t_from, t_end, thr) -> None:
        """The panels refreshed once per SLOW_S: lateness, counts, overview, loop, bars."""
        first, k_end, m = rows
        # lateness: the maximum over each stride block, so that no overrun is hidden
        lat = _block_max(np.asarray(rec["lateness"][first:k_end], dtype=float), m) * 1e3
        t = np.asarray(rec["time"][first:k_end:m], dtype=float)
        self.lat_src.data = {"t": t, "lat": lat[: t.size]}
        self.lat_range.start = t_from
        self.lat_range.end = t_from + WINDOW_S
        if f.meta.get("mode") == "paced":
            self._n_ovr = int((np.asarray(rec["lateness"][:k_end], dtype=float) > thr).sum())
        planned = int(f.meta.get("planned_steps") or 0)
        idx = slice(first, k_end, m)
        for v in self.views:
            v.fd.data = {
                "measured": _col(rec, names, "measured", v.ch, idx),
                "force": _col(rec, names, "force", v.ch, idx),
            }
            v.overview_update(rec, names, f.rows, planned, final=st.finished)
            v.window_box.left = t_end - WINDOW_S
            v.window_box.right = t_end
            v.bars.data = v.limits.update(rec, names, k_end, max(1, round(REFRESH_S * fs)))
        self.lat_plot.title.text = self._progress(st, float(rec["time"][-1]), self._n_ovr)

    def _events(self, events: list[dict]) -> None:
        if len(events) == self.n_events:
            return
        self.n_events = len(events)
        times, kinds, details = [], [], []
        for e in events:
            times.append(f"{_num(e.get('time'), math.nan):.3f}")
            kinds.append(str(e.get("kind", "?")))
            skip = {"kind", "time", "step", "wall_time"}
            if e.get("kind") == "end":
                keys = ["status", "steps_per_second", "estop_confirmed", "handback"]
                keys.append("missed_replies")
            elif e.get("kind") == "start":
                keys = ["mode", "fs", "steps"]
            else:
                keys = [k for k in e if k not in skip and k != "values"]
            details.append("; ".join(f"{k}={e[k]}" for k in keys if k in e and k not in skip)[:300])
        self.ev_src.data = {"time": times, "kind": kinds, "detail": details}
        rows = "".join(
            f"<tr><td style='text-align:right;padding:1px 10px 1px 0'>{t}</td>"
            f"<td style='padding-right:10px'>{html.escape(k)}</td>"
            f"<td style='color:#4b5563'>{html.escape(d)}</td></tr>"
            for t, k, d in zip(times, kinds, details, strict=True)
        )
        self.ev_table.text = (
            "<table style='font:13px sans-serif;border-collapse:collapse;width:100%'>"
            "<tr style='text-align:left'><th>t (s)</th><th>event</th><th>detail</th></tr>"
            + rows
            + "</table>"
        )

    def _banner(self, st: RunState) -> None:
        color, word = _BANNER.get(st.phase, ("#6b7280", st.phase.upper()))
        msg = html.escape(st.message)
        self.state_div.text = (
            f"<div style='background:{color};color:white;padding:8px 14px;border-radius:6px;"
            f"font:600 17px sans-serif;max-height:46px;overflow:hidden'>{word} — {msg}</div>"
        )

    def _info(self, st: RunState, t_end: float) -> str:
        """The line under the banner: what changes rarely (a text box re-lays out the page)."""
        f = self.ctx.follower
        meta = f.meta
        dur = f.planned_duration()
        parts = [
            html.escape(str(f.run_dir)),
            f"{meta.get('mode', '?')} at {_num(meta.get('fs')):g} Hz",
            f"driver {html.escape(str(meta.get('driver', '?')))}",
        ]
        if dur:
            parts.append(f"planned {dur:.1f} s")
        if st.writer is not None:
            parts.append(f"process {st.writer}")
        if not self.follow:
            parts.append(f"<b>replay: window ends at {t_end:.2f} s</b>")
        return "<div style='font:14px sans-serif;color:#374151'>" + " · ".join(parts) + "</div>"

    def _progress(self, st: RunState, t_last: float, n_ovr: int) -> str:
        """Loop time, steps, overruns and lag: the title of the lateness plot (once a second)."""
        f = self.ctx.follower
        parts = [f"t = {t_last:.2f} s", f"{f.rows} steps"]
        if f.meta.get("mode") == "paced":
            parts.append(f"{n_ovr} overruns")
        w0 = f.wall_t0()
        if st.live and w0 is not None:
            lag = time.time() - (w0 + t_last + _num(f.record["lateness"][-1]))
            parts.append(f"{lag:.2f} s behind")
        return "lateness, ms · " + " · ".join(parts)


def _forbidden(doc: Document) -> None:
    doc.add_root(
        Div(
            text="<h2>rths-hil watch: this page needs the token printed when the watcher "
            "started (…/?token=…)</h2>",
            name="forbidden",
        )
    )


def build_document(ctx: WatchContext) -> Callable[[Document], None]:
    """The Bokeh application function: one :class:`_Page` per session (token checked)."""
    import hmac

    def make(doc: Document) -> None:
        if ctx.token is not None:
            req = doc.session_context.request if doc.session_context else None
            args = req.arguments if req is not None else {}
            given = args.get("token", [b""])[0]
            if isinstance(given, bytes):
                given = given.decode("utf-8", "replace")
            if not hmac.compare_digest(given, ctx.token):
                _forbidden(doc)
                return
        _Page(doc, ctx)

    return make

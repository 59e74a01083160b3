"""The live page: a Bokeh document per browser session, fed from a :class:`RunFollower`.

Each session refreshes every :data:`REFRESH_S` (5.5 Hz): the shared follower reads what is new on
disk (at most once per refresh period whatever the number of sessions), and the session sends
the browser only what changed. The cost of a refresh in the browser is mostly the repaint of
each plot whose data or range changed (every renderer of such a plot is painted again), so:

* the 10 s plots get the new rows only (:meth:`ColumnDataSource.stream` with a rollover of
  10 s), decimated by a stride aligned to the step index, so a point never moves: the
  displacement at every refresh, the FEI A and d, the Kalman estimates and S (estimates over a
  window of seconds) every :data:`FEI_S`, on a time axis of their own; the time axes are set,
  and the value axes move only when the data leaves them or uses less than a third of them;
* the whole-test plot (the minimum and maximum of each bucket of about one pixel, only for
  completed buckets), the force–displacement loop, the lateness plot (on its own time axis),
  the limit bars and the counts are refreshed once per :data:`SLOW_S`;
* text boxes change only when their text does (a text box re-lays out the page);
* a session that looks back (replay slider) gets the window it asks for, whole.

Per channel: target / command / measured over the window and the whole test (overview); the
online FEI amplitude A(t) and delay d(t) (the FEI paper, Eq. 2.2 and 2.5; streaming and exact)
with the safety rule's tolerance bands and the windows where the FEI is invalid greyed; the
Kalman delay and gain (measured vs command: the actuator's own lag) on a plot of their own,
the delay against its own band (``safety.kf_delay_max``); the energy stability indicator S
(:mod:`rths_hil.stability`) with the rule's warning and limit as lines; the force–displacement
loop; the share of every safety limit in use as bars, the wall-clock feedback watchdog of a
paced run and S among them. Displacements are shown in mm and forces in kN (the record stays
SI). For the run: its state (running, completed, e-stop with rule, channel and time, operator stop,
killed), the loop's lateness and overruns, the event list, a time slider to replay a finished
run, and the operator-stop button.

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
from typing import Any

import numpy as np
from bokeh.document import Document
from bokeh.layouts import column, row
from bokeh.models import (
    Button,
    ColumnDataSource,
    CustomJS,
    Div,
    Range1d,
    Slider,
    Span,
    Toggle,
)
from bokeh.plotting import figure

from .figures import ChannelView
from .shaping import (
    actuator_label,
    block_max,
    channel_config,
    channel_control,
    channel_values,
    finite_or,
    stride,
)
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
CONFIRM_S = 10.0  # s the stop confirmation stays open

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


class _Page:
    """One session's document and its refresh."""

    def __init__(self, doc: Document, ctx: WatchContext) -> None:
        self.doc = doc
        self.ctx = ctx
        self.follow = True
        self.channels: list[str] | None = None
        self.views: list[ChannelView] = []
        self.n_events = -1
        self.stop_sent = False
        self.confirm_until = 0.0
        self.replay_playing = False

        # fixed sizes: a text change then needs no new page layout in the browser
        self.state_div = Div(text="", name="state", width=1140, height=70)
        self.info_div = Div(text="", name="info", width=1140, height=40)
        self._slider_at = 0.0
        self._slow_at = 0.0
        self._last_key: tuple[Any, ...] | None = None
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
        gap = stride(round(WINDOW_S * fs), WINDOW_POINTS)
        self.views = []
        for ch in chans:
            cfg = channel_config(meta.get("config", {}) or {}, ch)
            self.views.append(
                ChannelView(
                    ch,
                    actuator_label(ch, meta),
                    cfg.get("safety", {}) or {},
                    cfg,
                    meta.get("mode") == "paced",
                    self.x_range,
                    self.fei_range,
                    self.overview_range,
                    fs,
                    gap,
                    channel_control(meta, ch),
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

    def _update_slider(
        self, live: bool, now: float, t_first: float, t_last: float, fs: float
    ) -> None:
        """The replay slider's range: it follows a live run every 5 s (a change of a widget
        re-lays out the page)."""
        if live and now - self._slider_at < 5.0:
            return
        self._slider_at = now
        self._setting = True
        try:
            self.slider.start = t_first
            self.slider.end = max(t_last, t_first + 1.0 / fs)
            self.slider.step = max(1.0 / fs, 0.01)
            self.slider.disabled = False
        finally:
            self._setting = False

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
        now = time.monotonic()
        self._update_slider(st.live, now, t_first, t_last, fs)
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
        m = stride(n_win, WINDOW_POINTS)  # the window's stride: fixed for the run
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
        thr = finite_or((cfg.get("loop", {}) or {}).get("overrun_threshold"), 0.5) / fs
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
        if self.follow and nxt is not None and first <= nxt <= k_end:
            stream, a = True, nxt
        else:
            stream, a = False, first
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
        lat = block_max(np.asarray(rec["lateness"][first:k_end], dtype=float), m) * 1e3
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
                "measured": channel_values(rec, names, "measured", v.ch, idx) * 1e3,  # mm
                "force": channel_values(rec, names, "force", v.ch, idx) * 1e-3,  # kN
            }
            v.overview_update(rec, names, f.rows, planned, final=st.finished)
            v.window_box.left = t_end - WINDOW_S
            v.window_box.right = t_end
            v.limits.note_stalls(f.events)
            v.bars.data = v.limits.update(rec, names, k_end, max(1, round(REFRESH_S * fs)))
        self.lat_plot.title.text = self._progress(st, float(rec["time"][-1]), self._n_ovr)

    def _events(self, events: list[dict]) -> None:
        if len(events) == self.n_events:
            return
        self.n_events = len(events)
        times, kinds, details = [], [], []
        for e in events:
            times.append(f"{finite_or(e.get('time'), math.nan):.3f}")
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
        text = st.message
        if text.lower().startswith(word.lower()):  # "E-STOP — e-stop: nan …": say it once
            text = text[len(word) :].lstrip(": ")
        msg = html.escape(text)
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
            f"{meta.get('mode', '?')} at {finite_or(meta.get('fs')):g} Hz",
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
        rec = f.record
        if st.live and w0 is not None and rec is not None:
            lag = time.time() - (w0 + t_last + finite_or(rec["lateness"][-1]))
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

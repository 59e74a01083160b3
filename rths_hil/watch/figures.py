"""The plots of one actuator channel (Bokeh) and what the browser already holds of them.

The numbers come from :mod:`rths_hil.watch.shaping`; the page (:mod:`rths_hil.watch.app`)
lays the channels out and refreshes them.
"""

from __future__ import annotations

import html
import math

import numpy as np
from bokeh.layouts import column, row
from bokeh.models import (
    BoxAnnotation,
    ColumnDataSource,
    Div,
    FactorRange,
    Legend,
    LinearAxis,
    Range1d,
    Span,
)
from bokeh.plotting import figure

from ..records.columns import channel_suffix
from .shaping import (
    InvalidSpans,
    LimitShares,
    channel_values,
    envelope,
    finite_or,
    fit_range,
    stability_levels,
)

OVERVIEW_BUCKETS = 500  # buckets (about one pixel each) of the whole-test plot

#: Columns of the 10 s displacement plot's source, and of the source of the FEI, Kalman and
#: stability plots (delays in ms; ``s``: the energy stability indicator S).
WINDOW_COLUMNS = ("t", "target", "command", "measured")
FEI_COLUMNS = ("t", "a", "d", "a_ex", "d_ex", "kf_g", "kf_d", "s")

#: Colours of the stability indicator's warning and limit levels.
S_LEVEL_COLORS = {"warn": "#d97706", "limit": "#b91c1c"}

COLORS = {
    "target": "#1f77b4",
    "command": "#2ca02c",
    "measured": "#d62728",
    "exact": "#9467bd",
    "kalman": "#ff7f0e",
}


class ChannelView:
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
        control: str = "displacement",
    ) -> None:
        self.ch = ch
        self.fs = fs
        # the tracked quantity: the displacement (shown in mm), or the force of a force- or
        # load-controlled channel (its target and command are forces; shown in kN)
        self.control = control
        self.force_mode = control != "displacement"
        self.tracked = "force" if self.force_mode else "measured"
        self.scale, self.unit = (1e-3, "kN") if self.force_mode else (1e3, "mm")
        quantity = "force" if self.force_mode else "displacement"
        sfx = channel_suffix(ch)
        w = 560
        tools = "pan,wheel_zoom,box_zoom,reset,save"

        def timeline(title: str, height: int, x_range: Range1d, **kw) -> figure:
            """A plot over time (s) of the page's width and tools."""
            return figure(
                title=title,
                height=height,
                width=w,
                x_range=x_range,
                tools=tools,
                x_axis_label="time (s)",
                **kw,
            )

        # the 10 s window (streamed), the force–displacement loop and the whole test (slow)
        self.win = ColumnDataSource(data={k: [] for k in WINDOW_COLUMNS}, name=f"window{sfx}")
        self.fei = ColumnDataSource(data={k: [] for k in FEI_COLUMNS}, name=f"fei{sfx}")
        self.fd = ColumnDataSource(data={"measured": [], "force": []}, name=f"loop{sfx}")
        self.ovw = ColumnDataSource(
            data={"t": [], "target": [], "measured": []}, name=f"overview{sfx}"
        )
        self.invalid = ColumnDataSource(data={"l": [], "r": []}, name=f"invalid{sfx}")
        self.bars = ColumnDataSource(
            data={"limit": [], "used": [], "peak": [], "color": []}, name=f"bars{sfx}"
        )
        self.title = Div(
            text=f"<h2 style='margin:8px 0 0 0'>{html.escape(label)}"
            f"<span style='font-weight:400;font-size:16px;color:#4b5563'> · "
            f"{html.escape(control)} control · tracked: {quantity} ({self.unit})</span></h2>",
            name=f"title{sfx}",
        )
        self.invalid_tracker = InvalidSpans(gap)
        self.ovw_bucket = 0  # rows per bucket of the whole-test plot (0: not started)
        self.ovw_upto = 0  # rows of the record already in it
        self.ovw_whole = -1  # rows of the ended run when it was drawn whole

        # value axes set by the refresh (see fit_range): an automatic range moves at every refresh
        self.y_disp = Range1d(-1.0, 1.0)  # mm (kN)
        p = timeline(
            f"{quantity}: last 10 s", 260, x_range, y_range=self.y_disp, y_axis_label=self.unit
        )
        for key in ("target", "command", "measured"):
            p.line("t", key, source=self.win, color=COLORS[key], legend_label=key, line_width=1.6)
        p.legend.location = "top_left"
        p.legend.click_policy = "hide"
        self.disp = p

        q = timeline(
            f"{quantity}: whole test (min/max per pixel)",
            260,
            overview_range,
            y_axis_label=self.unit,
        )
        q.line("t", "target", source=self.ovw, color=COLORS["target"], legend_label="target")
        q.line("t", "measured", source=self.ovw, color=COLORS["measured"], legend_label="measured")
        q.legend.location = "top_left"
        self.window_box = BoxAnnotation(left=0, right=0, fill_color="#fbbf24", fill_alpha=0.25)
        q.add_layout(self.window_box)
        self.overview = q

        a_tol = finite_or(safety.get("fei_amplitude_tol"))
        d_tol = finite_or(safety.get("fei_delay_tol"))
        self.y_a = Range1d(0.9, 1.1)
        self.y_d = Range1d(-5.0, 5.0)
        pa = timeline(
            "FEI amplitude A, measured vs target (1 = perfect)",
            220,
            fei_range,
            name=f"fei_a{sfx}",
            y_range=self.y_a,
        )
        pd = timeline(
            "FEI delay d, measured vs target (ms, > 0: measured lags)",
            220,
            fei_range,
            name=f"fei_d{sfx}",
            y_range=self.y_d,
        )
        for fig, key, ex, tol, label in (
            (pa, "a", "a_ex", a_tol, "A"),
            (pd, "d", "d_ex", d_tol * 1e3, "d"),
        ):
            fig.vstrip(x0="l", x1="r", source=self.invalid, fill_color="#9ca3af", fill_alpha=0.35)
            lines = [
                fig.line("t", key, source=self.fei, color=COLORS["measured"], line_width=1.6),
                fig.line("t", ex, source=self.fei, color=COLORS["exact"], line_dash="dashed"),
            ]
            fig.add_layout(
                Legend(
                    items=[
                        (f"{label} streaming", [lines[0]]),
                        (f"{label} exact", [lines[1]]),
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

        # the Kalman estimates compare measured with *command* (the actuator's own lag, about
        # the servo lag plus the transport delay): their own plot, delay on the left axis with
        # its own band (|delay| ≤ safety.kf_delay_max), gain on the right axis
        kd_max = finite_or(safety.get("kf_delay_max")) * 1e3
        self.y_kd = Range1d(0.0, 30.0)
        self.y_kg = Range1d(0.9, 1.1)
        pk = timeline(
            "Kalman estimates of the actuator, measured vs command: delay (ms), gain",
            220,
            fei_range,
            y_range=self.y_kd,
            y_axis_label="delay (ms)",
            name=f"kalman{sfx}",
        )
        pk.extra_y_ranges = {"gain": self.y_kg}
        pk.add_layout(LinearAxis(y_range_name="gain", axis_label="gain"), "right")
        kl = [
            pk.line("t", "kf_d", source=self.fei, color=COLORS["kalman"], line_width=1.6),
            pk.line("t", "kf_g", source=self.fei, color="#0891b2", y_range_name="gain"),
        ]
        pk.add_layout(
            Legend(
                items=[("delay", [kl[0]]), ("gain", [kl[1]])],
                location="top_left",
                orientation="horizontal",
                background_fill_alpha=0.6,
            )
        )
        if kd_max > 0:
            pk.add_layout(
                BoxAnnotation(
                    bottom=-kd_max,
                    top=kd_max,
                    fill_color="#f97316",
                    fill_alpha=0.08,
                    line_color="#ea580c",
                    line_dash="dotted",
                    line_alpha=1.0,
                )
            )
        self.kalman = pk

        # the energy stability indicator S (rths_hil.stability) beside the FEI: injected over
        # dissipated energy in the rule's window; its warning and limit levels as lines
        self.s_levels = stability_levels(safety)
        top = max(self.s_levels.values(), default=1.0)
        self.y_s = Range1d(-0.1 * top, 1.15 * top)
        rule = str(safety.get("stability", "off"))
        levels = ", ".join(
            f"{'warning' if k == 'warn' else 'limit'} {v:g}" for k, v in self.s_levels.items()
        )
        ps = timeline(
            "stability indicator S = injected / dissipated energy · "
            + (f"{levels} (rule: {rule})" if levels else "rule off"),
            220,
            fei_range,
            name=f"stability{sfx}",
            y_range=self.y_s,
        )
        sl = ps.line("t", "s", source=self.fei, color="#7c3aed", line_width=1.6)
        ps.add_layout(
            Legend(
                items=[("S", [sl])],
                location="top_left",
                orientation="horizontal",
                background_fill_alpha=0.6,
            )
        )
        for key, level in self.s_levels.items():
            ps.add_layout(
                Span(
                    location=level,
                    dimension="width",
                    line_color=S_LEVEL_COLORS[key],
                    line_dash="dashed",
                    line_width=1.5,
                    name=f"s_{key}{sfx}",
                )
            )
        self.stability = ps

        pf = figure(
            title="force–displacement (last 10 s)",
            name=f"fd{sfx}",
            height=260,
            width=w,
            tools=tools,
            x_axis_label="measured displacement (mm)",
            y_axis_label="force (kN)",
        )
        pf.line("measured", "force", source=self.fd, color="#374151")
        self.loop = pf

        factors = [
            "displacement",
            "velocity",
            "force",
            "FEI |A−1|",
            "FEI |d|",
            "stability S",
            "Kalman gain",
            "Kalman delay",
            "missed replies",
            "feedback watchdog",
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
        self.limits = LimitShares(ch, safety, cfg, paced, control)
        self.layout = column(self.title, row(p, q), row(pa, pd), row(ps, pk), row(pf, pb))

    # -- data ----------------------------------------------------------------------------------
    def window_data(self, rec: np.ndarray, names, idx: slice, group: str = "win") -> dict:
        """The columns of the 10 s plots' source ``group`` (``win``, ``fei``) at rows ``idx``."""
        ch = self.ch
        t = np.asarray(rec["time"][idx], dtype=float)
        if group == "win":
            sc = self.scale  # displacements in mm, forces in kN (the record stays SI)
            return {  # "measured": the tracked quantity, measured
                "t": t,
                "target": channel_values(rec, names, "target", ch, idx) * sc,
                "command": channel_values(rec, names, "command", ch, idx) * sc,
                "measured": channel_values(rec, names, self.tracked, ch, idx) * sc,
            }
        return {
            "t": t,
            "a": channel_values(rec, names, "fei_amplitude", ch, idx),
            "d": channel_values(rec, names, "fei_delay", ch, idx) * 1e3,
            "a_ex": channel_values(rec, names, "fei_exact_amplitude", ch, idx),
            "d_ex": channel_values(rec, names, "fei_exact_delay", ch, idx) * 1e3,
            "kf_g": channel_values(rec, names, "kf_gain", ch, idx),
            "kf_d": channel_values(rec, names, "kf_delay", ch, idx) * 1e3,
            "s": channel_values(rec, names, "stability", ch, idx),
        }

    def fit_axes(self, group: str) -> None:
        """Value axes of the 10 s plots of ``group`` around the data they hold."""

        def span(data, *keys: str) -> tuple[float, float]:
            x = np.concatenate([np.asarray(data[k], dtype=float) for k in keys])
            x = x[np.isfinite(x)]
            return (float(x.min()), float(x.max())) if x.size else (math.nan, math.nan)

        if group == "win":
            fit_range(self.y_disp, *span(self.win.data, "target", "command", "measured"), 0.1)
        else:
            fit_range(self.y_a, *span(self.fei.data, "a", "a_ex"), 0.02)
            fit_range(self.y_d, *span(self.fei.data, "d", "d_ex"), 1.0)
            fit_range(self.y_kd, *span(self.fei.data, "kf_d"), 1.0)
            fit_range(self.y_kg, *span(self.fei.data, "kf_g"), 0.02)
            # S: from 0 to its levels at least, so that the margin to them is always in view
            lo, hi = span(self.fei.data, "s")
            top = max(self.s_levels.values(), default=hi if math.isfinite(hi) else 1.0)
            if math.isfinite(lo):
                fit_range(self.y_s, min(lo, 0.0), max(hi, top), 0.5)

    def overview_update(self, rec: np.ndarray, names, rows: int, planned: int, final: bool):
        """Extend the whole-test plot with the buckets completed since the last call.

        Buckets of ``(planned or rows) / OVERVIEW_BUCKETS`` rows (about one pixel), each drawn
        as its minimum and maximum (:func:`envelope`); when the run outgrows the planned
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
        for key, col in (("target", "target"), ("measured", self.tracked)):
            x = channel_values(rec, names, col, self.ch, slice(a, b)) * self.scale  # mm or kN
            pad = (-x.size) % m  # the last, incomplete bucket (final only): NaN-padded
            data[key] = envelope(np.append(x, np.full(pad, np.nan)), m)
        self.ovw_upto = b
        if rebuild:
            self.ovw.data = data
        else:
            self.ovw.stream(data)

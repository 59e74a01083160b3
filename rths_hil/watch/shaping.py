"""What the live page shows, computed from record rows with numpy only (no Bokeh).

Decimation that never moves a point (:func:`stride`, :func:`block_max`, :func:`envelope`), the
spans where a channel's FEI is invalid (:class:`InvalidSpans`), the share of each safety limit in
use (:class:`LimitShares`), the value-axis rule (:func:`fit_range`) and the configuration a
channel ran with (:func:`channel_config`). The figures (:mod:`rths_hil.watch.figures`) draw
what these return; ``tests/watch/test_watch_shaping.py`` checks them against direct computations.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .source import channel_column

__all__ = [
    "InvalidSpans",
    "LimitShares",
    "actuator_label",
    "block_max",
    "channel_config",
    "channel_control",
    "channel_values",
    "consecutive",
    "envelope",
    "finite_or",
    "fit_range",
    "stability_levels",
    "stride",
    "true_runs",
]


def stride(n_rows: int, points: int) -> int:
    """Smallest step that shows ``n_rows`` rows in at most ``points`` points."""
    return max(1, math.ceil(n_rows / points))


def channel_values(rec: np.ndarray, names, base: str, ch: str, idx) -> np.ndarray:
    """Rows ``idx`` of channel ``ch``'s ``base`` column as floats (NaN when the record has
    no such column)."""
    name = channel_column(names, base, ch)
    if name is None:
        return np.full(len(idx) if not isinstance(idx, slice) else 0, np.nan)
    return np.asarray(rec[name][idx], dtype=float)


def block_max(x: np.ndarray, m: int) -> np.ndarray:
    """Max of each block of ``m`` samples (the last block may be short)."""
    if m == 1 or x.size == 0:
        return x
    n = x.size // m * m
    out = x[:n].reshape(-1, m).max(axis=1)
    if n < x.size:
        out = np.append(out, x[n:].max())
    return out


def true_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end indices (end exclusive) of the runs of True in ``mask``."""
    if mask.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def finite_or(x, default: float = 0.0) -> float:
    """``x`` as a finite float, else ``default`` (missing, text or non-finite metadata)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


def envelope(x: np.ndarray, m: int) -> np.ndarray:
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


def fit_range(rng: Any, lo: float, hi: float, min_span: float) -> None:
    """Move a value axis only when the data leaves it or uses less than a third of it.

    ``rng`` is anything with ``start`` and ``end`` (a Bokeh ``Range1d`` on the page).

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


class InvalidSpans:
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
        s, e = true_runs(inv)
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


def channel_config(cfg: dict, ch: str) -> dict:
    """The configuration one channel ran with: its ``[[actuators]]`` entry over the top level."""
    out = dict(cfg)
    for entry in cfg.get("actuators") or []:
        if isinstance(entry, dict) and entry.get("name") == ch and ch:
            for section, table in entry.items():
                if isinstance(table, dict):
                    out[section] = {**(cfg.get(section) or {}), **table}
    return out


def channel_control(meta: dict, ch: str) -> str:
    """The control mode of channel ``ch``: ``"displacement"``, ``"force"`` or ``"load"``.

    From the run's channel description (``meta["channels"][i]["control"]``) when it has one,
    else from the configuration the channel ran with (``control.mode``, or ``control`` given as
    a word); ``"displacement"`` when neither says.
    """
    for entry in meta.get("channels") or []:
        if isinstance(entry, dict) and str(entry.get("name") or "") == ch and entry.get("control"):
            return str(entry["control"])
    c = channel_config(meta.get("config", {}) or {}, ch).get("control")
    if isinstance(c, dict):
        return str(c.get("mode") or "displacement")
    return str(c) if isinstance(c, str) and c else "displacement"


def consecutive(flag: np.ndarray, carry: int) -> np.ndarray:
    """Length of the run of True ending at each sample (``carry``: the run before the first)."""
    n = flag.size
    pos = np.arange(1, n + 1)
    last_false = np.maximum.accumulate(np.where(flag, 0, pos))
    count = pos - last_false
    return np.where(last_false == 0, count + carry, count)


class LimitShares:
    """Share of each safety limit in use for one channel, updated incrementally.

    For each limit of ``[safety]`` (the loop's rules, :mod:`rths_hil.safety`): ``now`` is the
    share over the latest refresh period (the latest value for the FEI and Kalman estimates,
    the current run for consecutive counts), ``peak`` the largest share so far. 1 = the limit.

    A force-controlled channel (``control`` ``"force"`` or ``"load"``) commands a force: its
    target and command count against the force limit with the measured force, and its measured
    displacement and the structure's trial displacement along it (the record's ``trial``
    column) against the displacement limit (the rules of such a channel).
    """

    def __init__(
        self, ch: str, safety: dict, cfg: dict, paced: bool, control: str = "displacement"
    ) -> None:
        self.ch = ch
        self.force_mode = control != "displacement"
        self.safety = safety
        self.cfg = cfg
        self.paced = paced
        fs = finite_or(cfg.get("loop", {}).get("fs"), 1.0) if cfg else 1.0
        lp = (cfg.get("loop", {}) or {}) if cfg else {}
        self.thr = finite_or(lp.get("overrun_threshold"), 0.5) / fs
        # the wall-clock feedback watchdog of a paced run (rths_hil.safety.WatchdogRule):
        # ``watchdog_timeout``, or ``watchdog_missed`` periods; a missed reply waited
        # ``loop.feedback_timeout`` (0: 0.8 periods)
        wd_missed = finite_or(safety.get("watchdog_missed"), 0.0)
        self.wd_timeout = finite_or(safety.get("watchdog_timeout"), 0.0) or wd_missed / fs
        self.fb_wait = finite_or(lp.get("feedback_timeout"), 0.0) or 0.8 / fs
        # the bridge's stalls (the loop's ``stall`` events): step before which each happened
        # and the stall time up to and including it (s), ascending by step
        self.stall_steps = np.zeros(0, dtype=np.int64)
        self.stall_total = np.zeros(1)
        self._n_events = -1  # events seen by note_stalls
        self.reset()

    def reset(self) -> None:
        self.upto = 0
        self.peak: dict[str, float] = {}
        self.last: dict[str, float] = {}
        self.carry: dict[str, int] = {}
        self.last_ok = math.nan  # when the latest good reply arrived (s, loop clock)
        self.last_ok_stalled = 0.0  # the bridge's stall time before that reply's row (s)

    def note_stalls(self, events: list[dict]) -> None:
        """Take the run's ``stall`` events: the feedback watchdog does not count that time
        (:class:`rths_hil.safety.WatchdogRule`: a stall of the bridge is not controller
        silence)."""
        if len(events) == self._n_events:
            return
        self._n_events = len(events)
        st = sorted(
            (int(e["step"]), finite_or(e.get("length"), 0.0))
            for e in events
            if e.get("kind") == "stall" and isinstance(e.get("step"), int)
        )
        self.stall_steps = np.array([k for k, _ in st], dtype=np.int64)
        self.stall_total = np.r_[0.0, np.cumsum([x for _, x in st])]

    def _shares(self, rec, names, a: int, b: int, carry: bool = True) -> dict[str, np.ndarray]:
        """Share of each limit at each row of ``[a, b)`` (``carry``: continue from the rows
        before ``a``, and remember where ``b`` ends; otherwise start afresh at ``a``)."""
        sf, ch = self.safety, self.ch
        out: dict[str, np.ndarray] = {}

        def col(base: str) -> np.ndarray | None:
            name = channel_column(names, base, ch)
            return None if name is None else np.asarray(rec[name][a:b], dtype=float)

        commanded = ("target", "command")
        for label, bases, key in (
            (
                "displacement",
                ("measured", "trial") if self.force_mode else (*commanded, "measured"),
                "displacement_limit",
            ),
            ("velocity", ("velocity",), "velocity_limit"),
            ("force", (*commanded, "force") if self.force_mode else ("force",), "force_limit"),
        ):
            lim = finite_or(sf.get(key))
            cols = [c for c in (col(x) for x in bases) if c is not None]
            if lim > 0 and cols:
                out[label] = np.max(np.abs(np.vstack(cols)), axis=0) / lim
        for label, base, key, ref in (
            ("FEI |A−1|", "fei_amplitude", "fei_amplitude_tol", 1.0),
            ("FEI |d|", "fei_delay", "fei_delay_tol", 0.0),
        ):
            tol, x = finite_or(sf.get(key)), col(base)
            if tol > 0 and x is not None:
                out[label] = np.abs(x - ref) / tol
        # the energy stability indicator S beside the FEI, as a share of its limit (warning
        # or trip level: the rule's, docs/stability.md); below 0 (energy taken out) is none
        s, lim = col("stability"), finite_or(sf.get("stability_limit"))
        if s is not None and lim > 0 and sf.get("stability", "off") != "off":
            out["stability S"] = np.maximum(s, 0.0) / lim
        g = col("kf_gain")
        if (self.cfg.get("kalman", {}) or {}).get("enabled", True) and g is not None:
            gmin, gmax = (
                finite_or(sf.get("kf_gain_min"), 0.5),
                finite_or(sf.get("kf_gain_max"), 1.5),
            )
            ref = 1.0 if gmin < 1.0 < gmax else 0.5 * (gmin + gmax)
            up, down = max(gmax - ref, 1e-12), max(ref - gmin, 1e-12)
            out["Kalman gain"] = np.where(g >= ref, (g - ref) / up, (ref - g) / down)
            dmax, d = finite_or(sf.get("kf_delay_max")), col("kf_delay")
            if dmax > 0 and d is not None:
                out["Kalman delay"] = np.abs(d) / dmax
        ok = channel_column(names, "feedback_ok", ch)
        wd = finite_or(sf.get("watchdog_missed"))
        if ok is not None and wd > 0:
            miss = ~np.asarray(rec[ok][a:b], dtype=bool)
            run = consecutive(miss, self.carry.get("missed replies", 0))
            out["missed replies"] = run / wd
        fbt = channel_column(names, "feedback_time", ch)
        if self.paced and self.wd_timeout > 0 and ok is not None and fbt is not None:
            out["feedback watchdog"] = self._watchdog(rec, names, ok, fbt, a, b, carry)
        mo = finite_or(sf.get("max_overruns"))
        if self.paced and mo > 0 and "lateness" in names:
            over = np.asarray(rec["lateness"][a:b], dtype=float) > self.thr
            run = consecutive(over, self.carry.get("overruns", 0))
            out["overruns"] = run / mo
        return out

    def _watchdog(self, rec, names, ok: str, fbt: str, a: int, b: int, carry: bool):
        """Share of the wall-clock watchdog's timeout at each row: the time from the latest
        good reply before the row to the row's reply (or to the end of its wait when it had
        none), less the bridge's own stalls in between (:meth:`note_stalls`), over
        ``watchdog_timeout``. Reply times come from the record: the step's loop time plus its
        lateness plus ``feedback_time``."""
        t = np.asarray(rec["time"][a:b], dtype=float)
        t = t + np.asarray(rec["lateness"][a:b], dtype=float) if "lateness" in names else t
        good = np.asarray(rec[ok][a:b], dtype=bool)
        fb = np.asarray(rec[fbt][a:b], dtype=float)
        arrive = t + np.where(good & np.isfinite(fb), fb, self.fb_wait)
        idx = np.arange(t.size)
        last = np.maximum.accumulate(np.where(good, idx, -1))  # latest good row ≤ i
        before = np.r_[-1, last[:-1]]  # latest good row < i
        start = self.last_ok if carry else math.nan
        prev = np.where(before >= 0, arrive[np.maximum(before, 0)], start)
        # stall time of the bridge before each row: the stalls before steps a .. a + i
        stalled = self.stall_total[np.searchsorted(self.stall_steps, idx + a, side="right")]
        start_stalled = self.last_ok_stalled if carry else 0.0
        prev_stalled = np.where(before >= 0, stalled[np.maximum(before, 0)], start_stalled)
        if carry and good.any():
            self.last_ok = float(arrive[last[-1]])
            self.last_ok_stalled = float(stalled[last[-1]])
        return (arrive - prev - (stalled - prev_stalled)) / self.wd_timeout

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
                    scale = finite_or(
                        self.safety.get("watchdog_missed" if label[0] == "m" else "max_overruns"), 1
                    )
                    self.carry[label] = round(float(x[-1]) * scale)
            self.upto = k_end
        recent = self._shares(rec, names, max(0, k_end - now_rows), k_end, carry=False)
        labels, now_v, peak_v = [], [], []
        for label in self.peak:
            x = recent.get(label, np.zeros(0))
            x = x[np.isfinite(x)]
            if label in ("displacement", "velocity", "force", "feedback watchdog"):
                now = float(x.max()) if x.size else 0.0
            else:
                now = self.last.get(label, 0.0)
            labels.append(label)
            now_v.append(min(now, 1.1))
            peak_v.append(min(self.peak[label], 1.1))
        colors = ["#16a34a" if u < 0.7 else "#f59e0b" if u < 0.9 else "#dc2626" for u in now_v]
        return {"limit": labels, "used": now_v, "peak": peak_v, "color": colors}


def actuator_label(ch: str, meta: dict) -> str:
    """The heading of a channel's plots: the actuator's name, or "Actuator" for the one
    unnamed actuator of a single-channel test."""
    if not ch:
        chans = meta.get("channels") or []
        ch = str(chans[0].get("name") or "") if len(chans) == 1 else ""
    return f"Actuator {ch}" if ch else "Actuator"


def stability_levels(safety: dict) -> dict[str, float]:
    """The stability rule's levels of ``S`` to draw: ``{"warn": …, "limit": …}``.

    None when ``safety.stability`` is ``"off"``; else the warning level (a ``stability`` event)
    and the limit (a trip in ``"trip"``; in ``"warn"`` the level the run would trip at). A level
    that is not a positive number is left out.
    """
    mode = str(safety.get("stability", "off"))
    out: dict[str, float] = {}
    if mode == "off":
        return out
    for key, name in (("warn", "stability_warn"), ("limit", "stability_limit")):
        v = finite_or(safety.get(name))
        if v > 0:
            out[key] = v
    return out

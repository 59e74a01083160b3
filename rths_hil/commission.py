"""Commissioning of each actuator channel before a test: ``rths-hil commission CONFIG``.

A scripted check of every channel of a configuration against its controller (a twin for CI,
the hardware after the operator's confirmation), in this order, each step passed, failed or
skipped with the reason:

``identify``
    Open the driver, arm the controller, read position, force and status (the arming reply);
    the position must be readable, within ``safety.displacement_limit``, and the controller
    must report no fault. The driver, its profile and the twin or hardware are reported, and
    what the driver found out about the link when it opened (``link_note``: a Modbus server
    that answers one request at a time, to which the driver then sends one at a time).
``latency``
    Round trips at the loop rate for ``commission.latency_time`` seconds with the actuator
    **disabled** (commands with ``enable = False`` at the held position): histogram, p50, p99,
    maximum, missed replies, the longest gap between two replies, and the link time the link
    budget computes for one step (:mod:`rths_hil.linkbudget`). Fails when more than 1 % of the
    replies are missed or the p99 round trip is above the loop's feedback timeout
    (``loop.feedback_timeout``, default 0.8 period).
``enable``
    Enable at the held position for 0.2 s (status ``ENABLED``, no motion beyond 20 µm + 5 % of
    ``commission.amplitude``), then disable (status without ``ENABLED``).
``motion``
    A ramp–hold–ramp of ``commission.amplitude`` (cosine ramps at most ``commission.velocity``,
    0.5 s holds) from the held position and back. Tracking from the FEI of the whole motion
    (the FEI paper's Eq. 2.1–2.5, :func:`rths_hil.fei.fei`) and from the Kalman estimator
    (:class:`rths_hil.estimation.DelayGainEstimator`); fails when the hold misses the target by
    more than 10 % of the amplitude or the FEI amplitude is off by more than 10 %.
``plant``
    A logarithmic chirp about the held position (:func:`plant_path`: 0.5 Hz up to 20 Hz or
    ``fs/16``, :data:`CHIRP_TIME` s, amplitude at most half ``commission.amplitude`` and
    velocity at most ``commission.velocity``), and a least-squares fit of the delayed
    first-order model ``g·e^(−sτ)/(T s + 1)`` to it (:func:`identify_plant`): the channel's
    delay τ, lag T and gain g as the loop sees them (the link's own latency is part of τ).
    Fails when the model explains less than 90 % of the motion or a value sits at its bound;
    a chirp during which the controller latched (its watchdog, when the computer stalled) is
    acknowledged by arming and run once more.
``estop``
    Enabled at the held position, e-stop through the driver; for 0.2 s commands towards half
    the amplitude must be ignored (status ``ESTOP_ACTIVE`` in every reply after the first
    :data:`ESTOP_GRACE`, position held within 20 µm); an
    ``enable = False`` command must acknowledge it and an ``enable = True`` command re-enable.
    The controller is then armed again (a new run: whatever the driver kept going after its
    e-stop, e.g. a CANopen bus's heartbeat, stops).
``watchdog``
    Only when ``commission.watchdog_test`` and the controller's heartbeat timeout are known
    (``commission.watchdog_timeout``, or the twin's ``twin.watchdog``): enabled, then silent;
    the controller must have latched (``WATCHDOG`` with ``ESTOP_ACTIVE`` or ``FAULT``) after
    the timeout plus a margin. The latch is then acknowledged by arming, as a run does.
``limits``
    Skipped: the drivers' protocols carry no limit registers to read back.
``hand-back``
    Always, also after a failed step or an operator stop: the last position is held (when
    enabled) for ``end.hold`` seconds, the controller disabled, a latch left by a step
    acknowledged by arming, and the status read: passed when the controller reports neither
    ``ENABLED`` nor ``ESTOP_ACTIVE``, ``WATCHDOG`` or ``FAULT``.

**Operator stop.** Ctrl-C, SIGTERM or SIGHUP (:data:`rths_hil.hybrid.runner.STOP_SIGNALS`, as
``rths-hil run``) end the step under way at its next period; the steps not reached are
skipped, the hand-back step runs, the report is written and the command exits 130. A second
signal e-stops every channel at once.

**Tuned fragment.** When every channel's ``plant`` step passed, ``tuned.toml`` beside the
report (:func:`tuned_fragment`) sets each channel's compensation to the ``model`` method with
the identified τ, T, g and ``safety.watchdog_timeout`` to :data:`WATCHDOG_SHARE` of the
controller's own watchdog when it is known, else :data:`GAP_MARGIN` × the longest reply gap of
the latency step (at least the key's default); a test configuration takes it with
``include = ["…/tuned.toml"]`` (``docs/config.md``).

The report (``report.md``, one PNG per channel with the latency histogram, the motion and the
chirp with the fitted model) goes to ``commission/<timestamp>/``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rths_hil.drivers.base import Feedback, LinkDown, Status

from .config import Config
from .errors import InputError
from .hybrid.pacer import Pacer
from .hybrid.phases import cosine_ramp, ramp_duration
from .stopping import OperatorStop, Stopped

log = logging.getLogger(__name__)

__all__ = [
    "CHIRP_TIME",
    "GAP_MARGIN",
    "MAX_LATENCY_TIME",
    "WATCHDOG_SHARE",
    "ChannelReport",
    "PlantFit",
    "StepResult",
    "commission",
    "identify_plant",
    "plant_path",
    "tuned_fragment",
    "write_report",
]

_ENABLED = int(Status.ENABLED)
_ESTOP = int(Status.ESTOP_ACTIVE)
_FAULT = int(Status.FAULT)
_WATCHDOG = int(Status.WATCHDOG)
_LATCHED = _ESTOP | _FAULT | _WATCHDOG
STEPS = (
    "identify",
    "latency",
    "enable",
    "motion",
    "plant",
    "estop",
    "watchdog",
    "limits",
    "hand-back",
)
#: Steps that move or enable the actuator (the operator confirms each on hardware).
MOVING = ("enable", "motion", "plant", "estop", "watchdog")
_NO_LIMITS = "the protocol carries no limits to read back"
#: Longest latency window (s): at 4096 Hz 600 s of round trips are 20 MB of figures.
MAX_LATENCY_TIME = 600.0
#: Length of the identification chirp (s).
CHIRP_TIME = 4.0
#: The e-stop step's replies of the first this many seconds may predate the latch (a lagging
#: link); every later one must show it.
ESTOP_GRACE = 0.02
#: A command of the chirp that left this much late (s) starts a stall: the samples after it are
#: not fitted.
STALL = 0.005
#: … for this long (s): several time constants of a servo-hydraulic actuator.
STALL_MASK = 0.1
#: ``safety.watchdog_timeout`` of the tuned fragment: this share of the controller's own
#: watchdog when it is known …
WATCHDOG_SHARE = 0.75
#: … else this × the longest reply gap measured (at least the key's default).
GAP_MARGIN = 2.0


@dataclass
class StepResult:
    """One commissioning step: ``passed``, ``failed`` or ``skipped``, why, and its figures."""

    name: str
    status: str
    reason: str = ""
    figures: dict[str, Any] = field(default_factory=dict)


@dataclass
class PlantFit:
    """The delayed first-order model ``g·e^(−sτ)/(T s + 1)`` fitted to a motion.

    Attributes
    ----------
    delay : float
        Transport delay τ (s), the link's latency included.
    lag : float
        First-order time constant T (s).
    gain : float
        Static gain g.
    offset : float
        Measured position at rest minus ``g`` × the commanded one (m).
    fit : float
        Share of the measured motion's variance the model explains (1 = all).
    model : ndarray
        The model's response to the command (m), for the plot.
    """

    delay: float
    lag: float
    gain: float
    offset: float
    fit: float
    model: np.ndarray


@dataclass
class ChannelReport:
    """The steps of one channel and the traces for its plots."""

    name: str
    driver: str
    target: str  # "twin" or "hardware"
    steps: list[StepResult] = field(default_factory=list)
    latency: np.ndarray = field(default_factory=lambda: np.zeros(0))
    motion: tuple[np.ndarray, np.ndarray] | None = None
    chirp: tuple[np.ndarray, np.ndarray] | None = None
    plant: PlantFit | None = None
    #: longest time between two replies of the latency step (s), NaN when not measured
    reply_gap: float = math.nan
    #: the controller's heartbeat timeout when known (s), else 0
    controller_watchdog: float = 0.0
    plot: str = ""

    @property
    def failed(self) -> list[StepResult]:
        """The failed steps."""
        return [s for s in self.steps if s.status == "failed"]

    def step(self, name: str) -> StepResult | None:
        """The step called ``name``, or None."""
        return next((s for s in self.steps if s.name == name), None)


class _Controller:
    """Paced command/reply exchanges with one channel's controller (sequence after arming).

    Every paced motion checks the operator stop once per period (:class:`Stopped`); the
    hand-back's own exchanges do not (``check=False``).
    """

    def __init__(
        self, ch: Any, fs: float, timeout: float, heartbeat_steps: int, stop: OperatorStop
    ) -> None:
        self.ch = ch
        self.drv = ch.driver
        self.recv = ch.receive
        self.dt = 1.0 / fs
        #: one command per period: sleep until 0.3 ms before each deadline, then spin (no
        #: real-time scheduling here, so no forced sleep)
        self.pacer = Pacer(self.dt, 3e-4)
        self.timeout = timeout
        self.hb = heartbeat_steps
        self.stop = stop
        self.seq = 0
        self.last: Feedback | None = None
        #: how late each command of the last :meth:`run` left (s)
        self.lateness = np.zeros(0)
        #: the last command sent: position and enable flag (what the controller is doing)
        self.x = math.nan
        self.enabled = False

    def arm(self) -> Feedback | None:
        """The driver's arming command: a new run; acknowledges a latch (e-stop, watchdog)."""
        self.seq = 0
        self.enabled = False
        return self.drv.arm(max(self.timeout, 0.5), self.recv)

    def exchange(self, x: float, enable: bool) -> tuple[Feedback | None, float]:
        """One command and its reply: (feedback or None, round trip in s)."""
        self.seq += 1
        t = time.perf_counter()
        self.x, self.enabled = float(x), bool(enable)
        self.drv.send(self.seq, float(x), enable)
        fb = self.recv(self.timeout)
        rtt = time.perf_counter() - t
        if fb is not None:
            self.last = fb
        return fb, rtt

    def poll(self, x: float, enable: bool, tries: int = 5) -> Feedback | None:
        """A command answered at last: up to ``tries`` exchanges, each waiting ≥ 0.2 s."""
        timeout = self.timeout
        self.timeout = max(timeout, 0.2)
        try:
            for _ in range(tries):
                fb, _ = self.exchange(x, enable)
                if fb is not None:
                    return fb
            return None
        finally:
            self.timeout = timeout

    def run(
        self,
        path: np.ndarray,
        enable: bool,
        each: Callable[[int, Feedback | None, float], None],
        check: bool = True,
    ) -> None:
        """One command of ``path`` per period (sleep, then spin to the deadline)."""
        pacer = self.pacer
        pacer.start(lead=0.0)  # the first command a period from now
        self.lateness = late = np.zeros(len(path))
        for i, x in enumerate(path):
            if check:
                self.stop.check()
            late[i] = pacer.wait(i) - pacer.due
            fb, rtt = self.exchange(float(x), enable)
            if self.hb and i % self.hb == 0:
                self.drv.heartbeat()
            each(i, fb, rtt)

    def hold(
        self, x: float, seconds: float, enable: bool, check: bool = True
    ) -> list[Feedback | None]:
        out: list[Feedback | None] = []
        path = np.full(max(1, round(seconds / self.dt)), x)
        self.run(path, enable, lambda i, f, r: out.append(f), check)
        return out

    def idle_while(self, work: Callable[[], Any]) -> Any:
        """``work()`` in a thread while this one keeps commanding ``x`` disabled, the heartbeat
        going (a drive's heartbeat consumer watches even while disabled); its result."""
        import concurrent.futures

        x = self.x
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            fut = pool.submit(work)
            while not fut.done():
                self.hold(x, 0.05, False, check=False)
            return fut.result()

    def silent(self, seconds: float) -> float:
        """Send nothing for ``seconds`` (the operator stop still ends it); the time spent."""
        t0 = time.perf_counter()
        end = t0 + seconds
        while (now := time.perf_counter()) < end:
            self.stop.check()
            time.sleep(min(0.01, end - now))
        return time.perf_counter() - t0


def _status_names(status: int | None) -> str:
    if status is None:
        return "no reply"
    names = [b.name for b in Status if b & status and b.name]
    return "|".join(names) if names else "0"


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


def _last(fbs: list[Feedback | None]) -> Feedback | None:
    return next((f for f in reversed(fbs) if f is not None), None)


# ----------------------------------------------------------------------------------------------
# plant identification


def plant_path(
    x0: float, amplitude: float, velocity: float, fs: float, duration: float = CHIRP_TIME
) -> np.ndarray:
    """The identification motion: a logarithmic chirp about ``x0``, 0.2 s of hold either side.

    The frequency rises from 0.5 Hz to ``min(20 Hz, fs/16)`` over ``duration``; the amplitude
    at frequency ``f`` is ``min(amplitude/2, 0.8·velocity/(2πf))`` with cosine tapers over the
    first and last 5 %, and the whole path is scaled so that no step moves faster than
    ``velocity``.
    """
    from scipy.signal import chirp

    f0, f1 = 0.5, min(20.0, fs / 16.0)
    n = max(16, round(duration * fs))
    t = np.arange(n) / fs
    f = f0 * (f1 / f0) ** (t / duration)
    env = np.minimum(0.5 * amplitude, 0.8 * velocity / (2 * np.pi * f))
    taper = np.ones(n)
    m = max(1, n // 20)
    taper[:m] = 0.5 - 0.5 * np.cos(np.pi * np.arange(m) / m)
    taper[-m:] = taper[:m][::-1]
    x = env * taper * chirp(t, f0, duration, f1, method="logarithmic", phi=-90.0)
    peak_v = float(np.max(np.abs(np.diff(x)))) * fs if n > 1 else 0.0
    if peak_v > velocity:
        x *= velocity / peak_v
    hold = np.zeros(round(0.2 * fs))
    return x0 + np.concatenate([hold, x, hold])


def _first_order(u: np.ndarray, lag: float, fs: float) -> np.ndarray:
    """``1/(T s + 1)`` by the bilinear transform (as the ``model`` compensator's C)."""
    from scipy.signal import lfilter

    if lag < 0.05 / fs:
        return u
    c = 2.0 * lag * fs
    return lfilter([1.0 / (1.0 + c)] * 2, [1.0, (1.0 - c) / (1.0 + c)], u)


def identify_plant(
    command: np.ndarray,
    measured: np.ndarray,
    fs: float,
    max_time: float = 0.2,
    valid: np.ndarray | None = None,
) -> PlantFit:
    """Fit ``y = offset + g·(1/(T s + 1))·e^(−sτ)·u`` to a command/measured pair (least squares).

    ``g`` and ``offset`` enter linearly and are solved for each ``(τ, T)``; ``(τ, T)`` come
    from a grid of 5 ms over ``[0, max_time]²`` refined by
    :func:`scipy.optimize.least_squares` within ``[0, 2·max_time]``. The delay is fractional
    (linear interpolation of the command), the lag discretised with the bilinear transform.
    NaN samples (missed replies) and those ``valid`` marks False are left out.

    Parameters
    ----------
    command, measured : ndarray
        The commands sent and the positions measured, one per step (m).
    fs : float
        Step rate (Hz).
    max_time : float
        Upper end of the grid for τ and T (s).
    valid : ndarray of bool, optional
        The samples to fit (e.g. not those after a stall of the commanding computer, when
        the controller saw other command times than the model assumes).

    Returns
    -------
    PlantFit
    """
    from scipy.optimize import least_squares

    u = np.asarray(command, dtype=float)
    y = np.asarray(measured, dtype=float)
    ok = np.isfinite(y) & np.isfinite(u)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if u.size < 16 or ok.sum() < 16:
        raise ValueError("too few samples to identify the plant")
    t = np.arange(u.size) / fs
    du = u - u[0]
    yo = y[ok]
    ones = np.ones(yo.size)

    def response(p: np.ndarray) -> np.ndarray:
        tau, lag = float(p[0]), float(p[1])
        return _first_order(np.interp(t - tau, t, du, left=0.0), lag, fs)

    def solve(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = response(p)[ok]
        a = np.column_stack([s, ones])
        coef, *_ = np.linalg.lstsq(a, yo, rcond=None)
        return a @ coef - yo, coef

    grid = np.arange(0.0, max_time + 1e-12, 5e-3)
    best, p0 = math.inf, np.zeros(2)
    for tau in grid:
        for lag in grid:
            r, _ = solve(np.array([tau, lag]))
            cost = float(r @ r)
            if cost < best:
                best, p0 = cost, np.array([tau, lag])
    hi = 2.0 * max_time
    fit = least_squares(
        lambda p: solve(p)[0], p0, bounds=([0.0, 0.0], [hi, hi]), x_scale=[1e-3, 1e-3],
        diff_step=[1e-4, 1e-4],
    )  # fmt: skip
    r, (g, off) = solve(fit.x)
    var = float(np.var(yo))
    explained = 1.0 - float(r @ r) / (yo.size * var) if var > 0 else math.nan
    return PlantFit(
        delay=float(fit.x[0]),
        lag=float(fit.x[1]),
        gain=float(g),
        offset=float(off),
        fit=explained,
        model=off + g * response(fit.x),
    )


# ----------------------------------------------------------------------------------------------
# the steps


def _identify(ctl: _Controller, rep: ChannelReport, amp: float, lim: float) -> float | None:
    fb = ctl.arm()
    figs: dict[str, Any] = {
        "driver": rep.driver,
        "profile": type(ctl.drv).__name__,
        "controller": rep.target,
        "identity": getattr(ctl.drv, "identity", None) or "not readable over this protocol",
    }
    note = getattr(ctl.drv, "link_note", None)  # e.g. a Modbus server that answers one
    if isinstance(note, str) and note:  # request at a time: the driver fell back
        figs["link"] = note
    warning = ctl.drv.link_check(1.0 / ctl.dt)  # e.g. its round trip against the period
    if warning:
        figs["link check"] = warning
        log.warning("%s: %s", rep.target, warning)
    why = ""
    if fb is None:
        why = "no reply to the arming command"
    else:
        figs.update(position=fb.displacement, force=fb.force, status=_status_names(fb.status))
        if fb.status & _FAULT:
            why = "the controller reports a fault"
        elif not math.isfinite(fb.displacement):
            why = "the position is not readable"
        elif not -lim <= fb.displacement <= lim:
            why = "the position is outside the limit"
        elif lim != math.inf and abs(fb.displacement) + amp > lim:
            why = "no room for the motion within the limit"
    rep.steps.append(StepResult("identify", "failed" if why else "passed", why, figs))
    if why or fb is None:
        return None
    ctl.x = float(fb.displacement)
    return float(fb.displacement)


def _latency(ctl: _Controller, rep: ChannelReport, n: int, x0: float, link_time: float | None):
    rtt = np.full(n, np.nan)
    arrived = np.full(n, np.nan)
    perf = time.perf_counter

    def on_lat(i, f, r):
        if f is not None:
            rtt[i] = r
            arrived[i] = perf()

    t0 = perf()
    ctl.run(np.full(n, x0), False, on_lat)
    t1 = perf()
    got = rtt[np.isfinite(rtt)]
    missed = int(n - got.size)
    rep.latency = got
    times = np.concatenate([[t0], arrived[np.isfinite(arrived)], [t1]])
    rep.reply_gap = float(np.max(np.diff(times))) if times.size > 2 else math.nan
    figs = {
        "replies": int(got.size),
        "missed": missed,
        "p50_ms": _pct(got, 50) * 1e3,
        "p99_ms": _pct(got, 99) * 1e3,
        "max_ms": float(got.max()) * 1e3 if got.size else math.nan,
        "longest_gap_ms": rep.reply_gap * 1e3,
        "timeout_ms": ctl.timeout * 1e3,
        "link_time_ms": None if link_time is None else link_time * 1e3,
    }
    if missed > 0.01 * n:
        rep.steps.append(
            StepResult("latency", "failed", f"{missed} of {n} replies missed (> 1 %)", figs)
        )
    elif _pct(got, 99) > ctl.timeout:
        why = "p99 round trip above the feedback timeout"
        rep.steps.append(StepResult("latency", "failed", why, figs))
    else:
        rep.steps.append(StepResult("latency", "passed", "", figs))


def _enable(ctl: _Controller, rep: ChannelReport, x0: float, tol: float) -> None:
    on = ctl.hold(x0, 0.2, True)
    last_on = _last(on)
    # disabled for at least 50 ms: a controller served one request at a time answers the
    # disabling step's requests over several periods
    off = _last(ctl.hold(x0, max(3 * ctl.dt, 0.05), False))
    figs = {
        "enabled_status": _status_names(None if last_on is None else last_on.status),
        "disabled_status": _status_names(None if off is None else off.status),
        "drift_um": None if last_on is None else abs(last_on.displacement - x0) * 1e6,
    }
    why = ""
    if last_on is None or not last_on.status & _ENABLED:
        why = "the controller did not report ENABLED"
    elif abs(last_on.displacement - x0) > tol:
        why = "the actuator moved when enabled in place"
    elif off is None:
        why = "no reply to the disabling commands (replies missed, not a controller that stays on)"
    elif off.status & _ENABLED:
        why = (
            f"the controller still reports ENABLED after the disable ({_status_names(off.status)})"
        )
    rep.steps.append(StepResult("enable", "failed" if why else "passed", why, figs))


def _motion(ctl: _Controller, rep: ChannelReport, plan: Any, x0: float) -> None:
    com = plan.cfg["commission"]
    amp = com["amplitude"]
    T = ramp_duration(amp, com["velocity"], 0.2)
    nr = max(1, math.ceil(T * plan.fs))
    nh = round(0.5 * plan.fs)
    up = cosine_ramp(x0, x0 + amp, nr)
    path = np.concatenate(
        [np.full(nh // 5, x0), up, np.full(nh, x0 + amp), up[::-1], np.full(nh, x0)]
    )
    meas = np.full(path.size, np.nan)

    def on_mot(i, f, r):
        meas[i] = f.displacement if f is not None else np.nan

    rep.motion = (path, meas)
    ctl.run(path, True, on_mot)
    ctl.exchange(x0, False)
    ok = np.isfinite(meas)
    figs: dict[str, Any] = {
        "amplitude_mm": amp * 1e3,
        "ramp_s": nr / plan.fs,
        "missed": int((~ok).sum()),
    }
    hold_end = nh // 5 + nr + nh
    if ok.sum() < 0.9 * path.size:
        rep.steps.append(StepResult("motion", "failed", "too many replies missed", figs))
        return
    filled = meas.copy()
    idx = np.flatnonzero(ok)
    filled[~ok] = np.interp(np.flatnonzero(~ok), idx, meas[idx])
    from .estimation import DelayGainEstimator
    from .fei import fei

    def evaluate() -> tuple[Any, float, float]:
        est = DelayGainEstimator(fs=plan.fs)
        g = d = math.nan
        for u, y in zip(path.tolist(), filled.tolist(), strict=True):
            g, d = est.update(u, y)
        return fei(path, filled, plan.fs), g, d

    r, g, d = ctl.idle_while(evaluate)
    hold_err = abs(filled[hold_end - 1] - (x0 + amp))
    figs.update(
        fei_amplitude=r.amplitude,
        fei_delay_ms=r.delay * 1e3,
        kalman_gain=g,
        kalman_delay_ms=d * 1e3,
        hold_error_um=hold_err * 1e6,
    )
    if hold_err > 0.1 * amp:
        rep.steps.append(
            StepResult("motion", "failed", "the hold missed the target by > 10 %", figs)
        )
    elif not r.valid or abs(r.amplitude - 1.0) > 0.1:
        rep.steps.append(
            StepResult("motion", "failed", "FEI amplitude off by more than 10 %", figs)
        )
    else:
        rep.steps.append(StepResult("motion", "passed", "", figs))


def _plant(ctl: _Controller, rep: ChannelReport, plan: Any, x0: float, chirp_time: float) -> None:
    com = plan.cfg["commission"]
    path = plant_path(x0, com["amplitude"], com["velocity"], plan.fs, chirp_time)
    figs: dict[str, Any] = {"chirp_s": chirp_time}
    for attempt in (1, 2):
        meas = np.full(path.size, np.nan)
        latched: list[int] = []

        def on_step(i, f, r, meas=meas, latched=latched):
            if f is not None:
                meas[i] = f.displacement
                if f.status & _LATCHED:
                    latched.append(int(f.status))

        rep.chirp = (path, meas)
        ctl.run(path, True, on_step)
        ctl.exchange(x0, False)
        if not latched:
            break
        # the controller latched under the chirp (its watchdog, when this computer stalled
        # past it): acknowledged by arming, and the chirp once more
        figs[f"latched_attempt_{attempt}"] = _status_names(latched[0])
        ctl.arm()
    ok = np.isfinite(meas)
    figs["missed"] = int((~ok).sum())
    if latched:
        why = f"the controller latched during the chirp (status {_status_names(latched[0])})"
        rep.steps.append(StepResult("plant", "failed", why, figs))
        return
    if ok.sum() < 0.9 * path.size:
        rep.steps.append(StepResult("plant", "failed", "too many replies missed", figs))
        return
    max_time = 0.2
    # a command that left late (this computer stalled): a controller in real time held the
    # one before longer than the model assumes; the samples up to STALL_MASK after it are
    # left out (a twin steps its plant per command: its timing is the commands')
    valid = np.ones(path.size, dtype=bool)
    if rep.target == "hardware":
        stalled = np.flatnonzero(ctl.lateness > max(STALL, 2.0 / plan.fs))
        for i in stalled:
            valid[i : i + round(STALL_MASK * plan.fs)] = False
        figs["stalled_commands"] = int(stalled.size)
        figs["fitted_share"] = float(valid.mean())
    if valid.mean() < 0.3:
        why = "this computer stalled too often under the chirp to fit a model (check-host)"
        rep.steps.append(StepResult("plant", "failed", why, figs))
        return
    fit = ctl.idle_while(
        lambda: identify_plant(path, meas, plan.fs, max_time=max_time, valid=valid)
    )
    rep.plant = fit
    figs.update(
        delay_ms=fit.delay * 1e3,
        lag_ms=fit.lag * 1e3,
        gain=fit.gain,
        equivalent_delay_ms=(fit.delay + fit.lag) * 1e3,
        explained=fit.fit,
    )
    if not fit.fit >= 0.9:
        why = f"the delayed first-order model explains {fit.fit:.0%} of the motion (< 90 %)"
        rep.steps.append(StepResult("plant", "failed", why, figs))
    elif max(fit.delay, fit.lag) >= 2 * max_time - 1e-6 or not 0.2 < fit.gain < 5.0:
        why = "an identified value sits at its bound (the controller does not follow the chirp)"
        rep.steps.append(StepResult("plant", "failed", why, figs))
    else:
        rep.steps.append(StepResult("plant", "passed", "", figs))


def _estop(ctl: _Controller, rep: ChannelReport, x0: float, amp: float) -> None:
    pre = ctl.hold(x0, 0.1, True)
    held_at = next((f.displacement for f in reversed(pre) if f is not None), x0)
    ctl.drv.estop()
    during = ctl.hold(x0 + 0.5 * amp, 0.2, True)
    answered = [f for f in during if f is not None]  # a reply lost on a loaded link is no vote
    # the answers of the first ESTOP_GRACE may have left the controller before the e-stop
    # reached it (a lagging link); from then on every one must show the latch
    grace = round(ESTOP_GRACE / ctl.dt)
    settled = [f for f in during[grace:] if f is not None]
    latched = bool(settled) and all(f.status & _ESTOP for f in settled)
    first = next((i for i, f in enumerate(during) if f is not None and f.status & _ESTOP), None)
    moved = max((abs(f.displacement - held_at) for f in answered), default=math.inf)
    # acknowledged by enable = False: the last answer of ESTOP_GRACE of such commands (the
    # first may be lost or predate it on a lagging link)
    ack = _last(ctl.hold(held_at, ESTOP_GRACE, False)) or ctl.poll(held_at, False)
    re_on = ctl.hold(held_at, 0.1, True)
    last_re = _last(re_on)
    re_ok = last_re is not None and bool(last_re.status & _ENABLED)
    ctl.exchange(held_at, False)
    # a new run for what follows: whatever the driver keeps going after its e-stop (a
    # CANopen bus's own heartbeat, which would feed the controller's watchdog) stops
    ctl.arm()
    figs = {
        "latched": bool(latched),
        "latched_after_ms": None if first is None else first * ctl.dt * 1e3,
        "moved_um": moved * 1e6,
        "acknowledged": ack is not None and not ack.status & _ESTOP,
        "re_enabled": re_ok,
    }
    why = ""
    if not latched:
        why = "the controller did not latch the e-stop"
    elif moved > 2e-5:
        why = "the actuator moved while latched"
    elif not figs["acknowledged"]:
        why = "enable = False did not acknowledge the latch"
    elif not re_ok:
        why = "the controller did not re-enable"
    rep.steps.append(StepResult("estop", "failed" if why else "passed", why, figs))


def _watchdog(ctl: _Controller, rep: ChannelReport, com: dict, x0: float) -> None:
    timeout = rep.controller_watchdog
    if not com["watchdog_test"]:
        rep.steps.append(StepResult("watchdog", "skipped", "commission.watchdog_test = false"))
        return
    if not timeout:
        why = "the controller's heartbeat timeout is not known (commission.watchdog_timeout)"
        rep.steps.append(StepResult("watchdog", "skipped", why))
        return
    ctl.hold(x0, 0.1, True)
    quiet = ctl.silent(timeout + max(0.25, 0.5 * timeout))
    fb = ctl.poll(x0, True)
    st = None if fb is None else int(fb.status)
    # a latch by the watchdog: WATCHDOG with the e-stop latched (or a drive's fault state)
    ok = st is not None and bool(st & _WATCHDOG) and bool(st & (_ESTOP | _FAULT))
    # acknowledged as a run does it: the arming command (a profile's acknowledge action, a
    # drive's fault reset), then disabled
    armed = ctl.arm()
    after = _last(ctl.hold(x0, 3 * ctl.dt, False, check=False)) or ctl.poll(x0, False)
    st2 = None if after is None else int(after.status)
    figs = {
        "timeout_s": timeout,
        "silent_s": quiet,
        "status": _status_names(st),
        "armed_status": _status_names(None if armed is None else int(armed.status)),
        "acknowledged_status": _status_names(st2),
    }
    if not ok:
        rep.steps.append(
            StepResult("watchdog", "failed", "no watchdog latch after its timeout", figs)
        )
    elif st2 is None or st2 & _LATCHED:
        why = "the watchdog latch was not acknowledged by arming"
        rep.steps.append(StepResult("watchdog", "failed", why, figs))
    else:
        rep.steps.append(StepResult("watchdog", "passed", "", figs))


def _hand_back(ctl: _Controller, rep: ChannelReport, x0: float, hold: float) -> None:
    """Hold (when enabled), disable, acknowledge a latch, read the status: the last step."""
    x = ctl.x if math.isfinite(ctl.x) else x0
    figs: dict[str, Any] = {"position_mm": None}
    if ctl.enabled:
        ctl.hold(x, max(hold, 2 * ctl.dt), True, check=False)
        figs["held_s"] = max(hold, 2 * ctl.dt)
    fb = _last(ctl.hold(x, 3 * ctl.dt, False, check=False)) or ctl.poll(x, False)
    st = None if fb is None else int(fb.status)
    if st is None or st & _LATCHED:
        figs["latched_status"] = _status_names(st)
        armed = ctl.arm()
        fb = _last(ctl.hold(x, 3 * ctl.dt, False, check=False)) or armed
        st = None if fb is None else int(fb.status)
        figs["acknowledged"] = st is not None and not st & _LATCHED
    figs["status"] = _status_names(st)
    if fb is not None:
        figs["position_mm"] = fb.displacement * 1e3
    if st is None:
        why = "no reply to the disabling command"
    elif st & _ENABLED:
        why = f"the controller is still ENABLED (status {_status_names(st)})"
    elif st & _LATCHED:
        why = f"the controller is left latched (status {_status_names(st)})"
    else:
        why = ""
    rep.steps.append(StepResult("hand-back", "failed" if why else "passed", why, figs))
    if why:
        log.warning("%s: hand-back: %s", rep.name or "actuator", why)


def _channel(
    ch: Any,
    plan: Any,
    link_time: float | None,
    confirm: Callable[[str], bool],
    stop: OperatorStop,
    progress: Callable[[str], None],
    chirp_time: float = CHIRP_TIME,
) -> ChannelReport:
    com = plan.cfg["commission"]
    rep = ChannelReport(ch.name, ch.plan.driver_name, "twin" if ch.twin is not None else "hardware")
    rep.controller_watchdog = float(
        com["watchdog_timeout"] or ((plan_twin_watchdog(ch) or 0.0) if ch.twin is not None else 0.0)
    )
    ctl = _Controller(ch, plan.fs, plan.timeout, plan.heartbeat_steps, stop)
    amp = com["amplitude"]
    label = rep.name or "actuator"
    why_skipped = ""
    x0: float | None = None
    current = "identify"
    aborted = False

    def start(name: str, text: str = "") -> None:
        nonlocal current
        current = name
        progress(f"{label}: {text or name}")

    try:
        stop.check()
        start("identify")
        x0 = _identify(ctl, rep, amp, ch.monitor.disp_limit)
        if x0 is None:
            why_skipped = "identify failed"
            return rep
        start("latency", f"latency ({com['latency_time']:g} s, disabled)")
        _latency(ctl, rep, max(1, round(com["latency_time"] * plan.fs)), x0, link_time)
        if not confirm(
            f"{label}: enable the controller and move the actuator by {amp * 1e3:g} mm at "
            f"most {com['velocity'] * 1e3:g} mm/s, test its e-stop and watchdog"
        ):
            why_skipped = "not confirmed by the operator"
            return rep
        tol = 2e-5 + 0.05 * amp
        start("enable")
        _enable(ctl, rep, x0, tol)
        start("motion")
        _motion(ctl, rep, plan, x0)
        start("plant")
        _plant(ctl, rep, plan, x0, chirp_time)
        start("estop")
        _estop(ctl, rep, x0, amp)
        start("watchdog")
        _watchdog(ctl, rep, com, x0)
    except Stopped as exc:
        why_skipped = f"operator stop ({exc})"
    except (InputError, LinkDown, OSError, ValueError) as exc:  # the step fails, not the run
        log.warning("%s: %s: %s", label, current, exc)
        if rep.step(current) is None:
            rep.steps.append(StepResult(current, "failed", f"error: {exc}"))
        why_skipped = f"{current} ended with an error"
    except BaseException:  # a second signal: commission() e-stops every channel at once
        aborted = True
        raise
    finally:
        if not aborted:  # (after a second signal: no hand-back, the e-stop)
            done = {s.name for s in rep.steps}
            for name in STEPS[:-1]:
                if name == "limits":
                    rep.steps.append(StepResult("limits", "skipped", _NO_LIMITS))
                elif name not in done:
                    rep.steps.append(StepResult(name, "skipped", why_skipped or "not reached"))
            if x0 is not None or ctl.enabled:
                progress(f"{label}: hand-back")
                try:
                    _hand_back(ctl, rep, x0 if x0 is not None else ctl.x, plan.cfg["end"]["hold"])
                except (InputError, LinkDown, OSError) as exc:
                    with contextlib.suppress(Exception):
                        ctl.drv.estop()
                    why = f"error: {exc}; the controller was e-stopped"
                    rep.steps.append(StepResult("hand-back", "failed", why))
            else:
                rep.steps.append(StepResult("hand-back", "skipped", why_skipped or "not armed"))
            rep.steps.sort(key=lambda s: STEPS.index(s.name))
    return rep


def plan_twin_watchdog(ch: Any) -> float | None:
    """The in-process twin's heartbeat timeout (s) or None."""
    return getattr(ch.twin.controller, "heartbeat_timeout", None)


def commission(
    cfg: Config,
    out: Path,
    *,
    confirm: Callable[[str], bool] = lambda what: True,
    plan: Any = None,
    stop: OperatorStop | None = None,
    progress: Callable[[str], None] | None = None,
    chirp_time: float = CHIRP_TIME,
) -> list[ChannelReport]:
    """Commission every channel of ``cfg`` (module docstring); write the report into ``out``.

    Parameters
    ----------
    cfg : Config
    out : Path
        Report directory (created).
    confirm : callable
        Asked before the steps that enable or move an actuator; False skips them.
    plan : TestPlan, optional
        The configuration's plan in paced mode (built when not given).
    stop : OperatorStop, optional
        The operator-stop signals (caught here for the call when not given; the CLI catches
        them from its start). After a stop the channels not reached are skipped.
    progress : callable, optional
        Called with ``"<channel>: <step>"`` as each step starts.
    chirp_time : float
        Length of the identification chirp (s); shorter is a quicker, coarser fit.

    Returns
    -------
    list of ChannelReport

    Raises
    ------
    InputError
        ``commission.latency_time`` above :data:`MAX_LATENCY_TIME`.
    """
    from .hybrid.channel import Channel
    from .hybrid.plan import build_plan

    lt = cfg["commission"]["latency_time"]
    if not lt <= MAX_LATENCY_TIME:
        raise InputError(
            f"commission.latency_time: at most {MAX_LATENCY_TIME:g} s of round trips, got {lt:g} s"
        )
    if plan is None:
        plan = build_plan(cfg, out, mode="paced")
    forced = [cp for cp in plan.channels if cp.control != "displacement"]
    if forced:  # its motions are displacements: a force set-point would take them as N
        cp = forced[0]
        raise InputError(
            f"{cfg.source}: control.mode: commissioning moves each actuator in displacement "
            f"control; {'channel ' + cp.name if cp.name else 'the actuator'} is "
            f"{cp.control}-controlled: commission it with control.mode = 'displacement'"
        )
    say = progress or (lambda text: None)
    reports: list[ChannelReport] = []
    with contextlib.ExitStack() as stack:
        if stop is None:
            stop = stack.enter_context(OperatorStop())
        chans = []
        try:
            for cp in plan.channels:
                cp.twin_inline = False  # the twin's own thread runs its watchdog
                if cp.twin_enabled and not cp.twin_watchdog:
                    cp.twin_watchdog = 0.5
                ch = Channel(cp, plan.fs)
                ch.open(stack, background_exact=False)
                chans.append(ch)
            for ch, load in zip(chans, _link_times(plan), strict=False):
                if stop.stopped:
                    rep = ChannelReport(
                        ch.name, ch.plan.driver_name, "twin" if ch.twin is not None else "hardware"
                    )
                    why = f"operator stop ({stop.signal})"
                    rep.steps = [StepResult(name, "skipped", why) for name in STEPS]
                    reports.append(rep)
                    continue
                reports.append(_channel(ch, plan, load, confirm, stop, say, chirp_time))
        except BaseException:  # a second signal, a driver's error: e-stop every channel
            for ch in chans:
                with contextlib.suppress(Exception):
                    ch.driver.estop()
            raise
    out.mkdir(parents=True, exist_ok=True)
    write_report(reports, plan, out)
    if reports and all(r.plant is not None and _passed(r, "plant") for r in reports):
        (out / "tuned.toml").write_text(tuned_fragment(reports, plan), encoding="utf-8")
    return reports


def _passed(rep: ChannelReport, name: str) -> bool:
    s = rep.step(name)
    return s is not None and s.status == "passed"


def _link_times(plan: Any) -> list[float | None]:
    """Per channel: the link time of one step's traffic from the link budget.

    Known when every channel is on one link with a rate (``None`` otherwise: a virtual bus,
    a pseudo-terminal, or several links, which the budget does not map to channels).
    """
    links = list(getattr(plan, "links", []) or [])
    lt = links[0].per_channel if len(links) == 1 and links[0].rate else None
    return [lt for _ in plan.channels]


def _watchdog_timeout(rep: ChannelReport, fs: float) -> tuple[float, str]:
    """The fragment's ``safety.watchdog_timeout`` for a channel and how it was chosen.

    The controller's own watchdog known: :data:`WATCHDOG_SHARE` of it — the bridge bears the
    controller's and the link's pauses (a driver's give-up on a dropped request included) up
    to shortly before the controller would latch by itself. Unknown: :data:`GAP_MARGIN` × the
    longest reply gap, never tighter than the key's default (a latency window of a few
    seconds does not see every pause of a controller's network stack nor every stall of this
    computer). At least three periods.
    """
    from .config import SCHEMA

    gap = rep.reply_gap if math.isfinite(rep.reply_gap) else 0.0
    lower = max(GAP_MARGIN * gap, 3.0 / fs)
    wd = rep.controller_watchdog
    if wd:
        value = WATCHDOG_SHARE * wd
        how = f"{WATCHDOG_SHARE:g} × the controller's watchdog ({wd:g} s)"
        if lower > value:
            how += (
                f"; the longest reply gap ({gap * 1e3:.2f} ms) × {GAP_MARGIN:g} is longer: "
                "the link's pauses come close to the controller's watchdog"
            )
            log.warning("%s: %s", rep.name or "actuator", how)
        return round(value, 4), how
    floor = float(SCHEMA["safety"]["watchdog_timeout"].default)
    value = max(lower, floor)
    how = (
        f"{GAP_MARGIN:g} × the longest reply gap ({gap * 1e3:.2f} ms), at least the default "
        f"{floor * 1e3:g} ms and 3 periods (the controller's watchdog unknown)"
    )
    return round(value, 4), how


def tuned_fragment(reports: list[ChannelReport], plan: Any) -> str:
    """The configuration fragment of the identified plants (``tuned.toml``; module docstring).

    One ``[compensation]`` and ``[safety]`` table for a configuration without
    ``[[actuators]]``, else one ``[[actuators]]`` entry per channel (merged by name into the
    including file's, ``docs/config.md``).
    """
    import tomli_w

    def tables(rep: ChannelReport) -> tuple[dict[str, Any], dict[str, Any]]:
        p = rep.plant
        assert p is not None
        comp = {
            "method": "model",
            "delay": round(p.delay, 6),
            "model_delay": -1.0,
            "model_time_constant": round(p.lag, 6),
            "model_gain": round(p.gain, 5),
            "amplitude": 1.0,
        }
        wd, _ = _watchdog_timeout(rep, plan.fs)
        return comp, {"watchdog_timeout": wd}

    head = [
        "# Written by rths-hil commission: the plant of each channel as the loop sees it",
        f"# ({plan.cfg.source or 'the default configuration'}, {plan.fs:g} Hz). Include it with",
        '#   include = ["<this directory>/tuned.toml"]',
        "# in the test's configuration (its own keys win over these).",
    ]
    for rep in reports:
        p = rep.plant
        assert p is not None
        _, how = _watchdog_timeout(rep, plan.fs)
        head.append(
            f"# {rep.name or 'actuator'}: delay {p.delay * 1e3:.2f} ms, lag {p.lag * 1e3:.2f} ms, "
            f"gain {p.gain:.4f} (fit {p.fit:.1%}); watchdog_timeout = {how}"
        )
    if len(reports) == 1 and not plan.cfg.get("actuators"):
        comp, safety = tables(reports[0])
        doc: dict[str, Any] = {"compensation": comp, "safety": safety}
    else:
        entries = []
        for rep in reports:
            comp, safety = tables(rep)
            entries.append({"name": rep.name, "compensation": comp, "safety": safety})
        doc = {"actuators": entries}
    return "\n".join(head) + "\n\n" + tomli_w.dumps(doc)


def write_report(reports: list[ChannelReport], plan: Any, out: Path) -> Path:
    """``report.md`` and, unless ``output.plot`` is false, one PNG per channel in ``out``;
    return the report's path."""
    draw = bool(plan.cfg["output"]["plot"])
    if draw:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    lines = [
        "# Commissioning report",
        "",
        f"Configuration: `{plan.cfg.source}`; loop rate {plan.fs:g} Hz.",
        "",
    ]
    verdict = "PASSED" if not any(r.failed for r in reports) else "FAILED"
    lines += [f"**{verdict}**", ""]
    tuned = all(r.plant is not None and _passed(r, "plant") for r in reports) and bool(reports)
    if tuned:
        lines += [
            "The identified plants are in `tuned.toml`: add "
            '`include = ["<this directory>/tuned.toml"]` to the test\'s configuration.',
            "",
        ]
    for rep in reports:
        name = rep.name or "actuator"
        png = f"{name}.png"
        if draw:
            fig, axes = plt.subplots(1, 3, figsize=(15, 3.8), constrained_layout=True)
            if rep.latency.size:
                axes[0].hist(rep.latency * 1e3, bins=50, color="C0")
            axes[0].set_xlabel("round trip (ms), actuator disabled")
            axes[0].set_ylabel("replies")
            axes[0].set_title(f"{name}: latency at {plan.fs:g} Hz")
            for ax, trace, title in (
                (axes[1], rep.motion, "ramp–hold–ramp"),
                (axes[2], rep.chirp, "chirp and fitted model"),
            ):
                if trace is not None:
                    cmd, meas = trace
                    t = np.arange(cmd.size) / plan.fs
                    ax.plot(t, 1e3 * cmd, lw=1.0, label="command")
                    ax.plot(t, 1e3 * meas, lw=0.8, label="measured")
                    if ax is axes[2] and rep.plant is not None:
                        ax.plot(t, 1e3 * rep.plant.model, lw=0.8, ls="--", label="model")
                    ax.legend(loc="upper right")
                ax.set_xlabel("time (s)")
                ax.set_ylabel("displacement (mm)")
                ax.set_title(f"{name}: {title}")
            fig.savefig(out / png, dpi=90)
            plt.close(fig)
            rep.plot = png
        lines += [
            f"## {name} ({rep.driver}, {rep.target})",
            "",
            "| step | result | why | figures |",
            "|---|---|---|---|",
        ]
        for s in rep.steps:
            figs = ", ".join(f"{k} = {_fmt(v)}" for k, v in s.figures.items())
            lines.append(f"| {s.name} | {s.status} | {s.reason or '—'} | {figs or '—'} |")
        lines += ["", f"![{name}]({png})", ""] if draw else [""]
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)

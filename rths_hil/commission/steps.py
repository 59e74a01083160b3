"""The commissioning steps of one channel, each adding its :class:`StepResult` to the report."""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np

from ..hybrid.phases import cosine_ramp, ramp_duration
from .controller import (
    ENABLED,
    ESTOP,
    FAULT,
    LATCHED,
    WATCHDOG,
    Controller,
    last_reply,
    status_names,
)
from .plant import identify_plant, plant_path
from .report import ChannelReport, StepResult

log = logging.getLogger(__name__)

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
NO_LIMITS = "the protocol carries no limits to read back"
#: The e-stop step's replies of the first this many seconds may predate the latch (a lagging
#: link); every later one must show it.
ESTOP_GRACE = 0.02
#: A command of the chirp that left this much late (s) starts a stall: the samples after it are
#: not fitted.
STALL = 0.005
#: … for this long (s): several time constants of a servo-hydraulic actuator.
STALL_MASK = 0.1


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


def identify(ctl: Controller, rep: ChannelReport, amp: float, lim: float) -> float | None:
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
        figs.update(position=fb.displacement, force=fb.force, status=status_names(fb.status))
        if fb.status & FAULT:
            why = "the controller reports a fault"
        elif not math.isfinite(fb.displacement):
            why = "the position is not readable"
        elif not -lim <= fb.displacement <= lim:
            why = "the position is outside the limit"
        elif lim != math.inf and abs(fb.displacement) + amp > lim:
            why = "no room for the motion within the limit"
    rep.result("identify", why, figs)
    if why or fb is None:
        return None
    ctl.x = float(fb.displacement)
    return float(fb.displacement)


def latency(ctl: Controller, rep: ChannelReport, n: int, x0: float, link_time: float | None):
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
    why = ""
    if missed > 0.01 * n:
        why = f"{missed} of {n} replies missed (> 1 %)"
    elif _pct(got, 99) > ctl.timeout:
        why = "p99 round trip above the feedback timeout"
    rep.result("latency", why, figs)


def enable(ctl: Controller, rep: ChannelReport, x0: float, tol: float) -> None:
    on = ctl.hold(x0, 0.2, True)
    last_on = last_reply(on)
    # disabled for at least 50 ms: a controller served one request at a time answers the
    # disabling step's requests over several periods
    off = last_reply(ctl.hold(x0, max(3 * ctl.dt, 0.05), False))
    figs = {
        "enabled_status": status_names(None if last_on is None else last_on.status),
        "disabled_status": status_names(None if off is None else off.status),
        "drift_um": None if last_on is None else abs(last_on.displacement - x0) * 1e6,
    }
    why = ""
    if last_on is None or not last_on.status & ENABLED:
        why = "the controller did not report ENABLED"
    elif abs(last_on.displacement - x0) > tol:
        why = "the actuator moved when enabled in place"
    elif off is None:
        why = "no reply to the disabling commands (replies missed, not a controller that stays on)"
    elif off.status & ENABLED:
        why = f"the controller still reports ENABLED after the disable ({status_names(off.status)})"
    rep.result("enable", why, figs)


def motion(ctl: Controller, rep: ChannelReport, plan: Any, x0: float) -> None:
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
        rep.result("motion", "too many replies missed", figs)
        return
    filled = meas.copy()
    idx = np.flatnonzero(ok)
    filled[~ok] = np.interp(np.flatnonzero(~ok), idx, meas[idx])
    from ..estimation import DelayGainEstimator
    from ..fei import fei

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
    why = ""
    if hold_err > 0.1 * amp:
        why = "the hold missed the target by > 10 %"
    elif not r.valid or abs(r.amplitude - 1.0) > 0.1:
        why = "FEI amplitude off by more than 10 %"
    rep.result("motion", why, figs)


def plant(ctl: Controller, rep: ChannelReport, plan: Any, x0: float, chirp_time: float) -> None:
    com = plan.cfg["commission"]
    path = plant_path(x0, com["amplitude"], com["velocity"], plan.fs, chirp_time)
    figs: dict[str, Any] = {"chirp_s": chirp_time}
    for attempt in (1, 2):
        meas = np.full(path.size, np.nan)
        latched: list[int] = []

        def on_step(i, f, r, meas=meas, latched=latched):
            if f is not None:
                meas[i] = f.displacement
                if f.status & LATCHED:
                    latched.append(int(f.status))

        rep.chirp = (path, meas)
        ctl.run(path, True, on_step)
        ctl.exchange(x0, False)
        if not latched:
            break
        # the controller latched under the chirp (its watchdog, when this computer stalled
        # past it): acknowledged by arming, and the chirp once more
        figs[f"latched_attempt_{attempt}"] = status_names(latched[0])
        ctl.arm()
    ok = np.isfinite(meas)
    figs["missed"] = int((~ok).sum())
    if latched:
        why = f"the controller latched during the chirp (status {status_names(latched[0])})"
        rep.result("plant", why, figs)
        return
    if ok.sum() < 0.9 * path.size:
        rep.result("plant", "too many replies missed", figs)
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
        rep.result("plant", why, figs)
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
    why = ""
    if not fit.fit >= 0.9:
        why = f"the delayed first-order model explains {fit.fit:.0%} of the motion (< 90 %)"
    elif max(fit.delay, fit.lag) >= 2 * max_time - 1e-6 or not 0.2 < fit.gain < 5.0:
        why = "an identified value sits at its bound (the controller does not follow the chirp)"
    rep.result("plant", why, figs)


def estop(ctl: Controller, rep: ChannelReport, x0: float, amp: float) -> None:
    pre = ctl.hold(x0, 0.1, True)
    held_at = next((f.displacement for f in reversed(pre) if f is not None), x0)
    ctl.drv.estop()
    during = ctl.hold(x0 + 0.5 * amp, 0.2, True)
    answered = [f for f in during if f is not None]  # a reply lost on a loaded link is no vote
    # the answers of the first ESTOP_GRACE may have left the controller before the e-stop
    # reached it (a lagging link); from then on every one must show the latch
    grace = round(ESTOP_GRACE / ctl.dt)
    settled = [f for f in during[grace:] if f is not None]
    latched = bool(settled) and all(f.status & ESTOP for f in settled)
    first = next((i for i, f in enumerate(during) if f is not None and f.status & ESTOP), None)
    moved = max((abs(f.displacement - held_at) for f in answered), default=math.inf)
    # acknowledged by enable = False: the last answer of ESTOP_GRACE of such commands (the
    # first may be lost or predate it on a lagging link)
    ack = last_reply(ctl.hold(held_at, ESTOP_GRACE, False)) or ctl.poll(held_at, False)
    re_on = ctl.hold(held_at, 0.1, True)
    last_re = last_reply(re_on)
    re_ok = last_re is not None and bool(last_re.status & ENABLED)
    ctl.exchange(held_at, False)
    # a new run for what follows: whatever the driver keeps going after its e-stop (a
    # CANopen bus's own heartbeat, which would feed the controller's watchdog) stops
    ctl.arm()
    figs = {
        "latched": bool(latched),
        "latched_after_ms": None if first is None else first * ctl.dt * 1e3,
        "moved_um": moved * 1e6,
        "acknowledged": ack is not None and not ack.status & ESTOP,
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
    rep.result("estop", why, figs)


def watchdog(ctl: Controller, rep: ChannelReport, com: dict, x0: float) -> None:
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
    ok = st is not None and bool(st & WATCHDOG) and bool(st & (ESTOP | FAULT))
    # acknowledged as a run does it: the arming command (a profile's acknowledge action, a
    # drive's fault reset), then disabled
    armed = ctl.arm()
    after = last_reply(ctl.hold(x0, 3 * ctl.dt, False, check=False)) or ctl.poll(x0, False)
    st2 = None if after is None else int(after.status)
    figs = {
        "timeout_s": timeout,
        "silent_s": quiet,
        "status": status_names(st),
        "armed_status": status_names(None if armed is None else int(armed.status)),
        "acknowledged_status": status_names(st2),
    }
    why = ""
    if not ok:
        why = "no watchdog latch after its timeout"
    elif st2 is None or st2 & LATCHED:
        why = "the watchdog latch was not acknowledged by arming"
    rep.result("watchdog", why, figs)


def hand_back(ctl: Controller, rep: ChannelReport, x0: float, hold: float) -> None:
    """Hold (when enabled), disable, acknowledge a latch, read the status: the last step."""
    x = ctl.x if math.isfinite(ctl.x) else x0
    figs: dict[str, Any] = {"position_mm": None}
    if ctl.enabled:
        ctl.hold(x, max(hold, 2 * ctl.dt), True, check=False)
        figs["held_s"] = max(hold, 2 * ctl.dt)
    fb = last_reply(ctl.hold(x, 3 * ctl.dt, False, check=False)) or ctl.poll(x, False)
    st = None if fb is None else int(fb.status)
    if st is None or st & LATCHED:
        figs["latched_status"] = status_names(st)
        armed = ctl.arm()
        fb = last_reply(ctl.hold(x, 3 * ctl.dt, False, check=False)) or armed
        st = None if fb is None else int(fb.status)
        figs["acknowledged"] = st is not None and not st & LATCHED
    figs["status"] = status_names(st)
    if fb is not None:
        figs["position_mm"] = fb.displacement * 1e3
    if st is None:
        why = "no reply to the disabling command"
    elif st & ENABLED:
        why = f"the controller is still ENABLED (status {status_names(st)})"
    elif st & LATCHED:
        why = f"the controller is left latched (status {status_names(st)})"
    else:
        why = ""
    rep.result("hand-back", why, figs)
    if why:
        log.warning("%s: hand-back: %s", rep.name or "actuator", why)

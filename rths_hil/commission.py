"""Commissioning of each actuator channel before a test: ``rths-hil commission CONFIG``.

A scripted check of every channel of a configuration against its controller (a twin for CI,
the hardware after the operator's confirmation), in this order, each step passed, failed or
skipped with the reason:

``identify``
    Open the driver, arm the controller, read position, force and status (the arming reply);
    the position must be readable, within ``safety.displacement_limit``, and the controller
    must report no fault. The driver, its profile and the twin or hardware are reported.
``latency``
    Round trips at the loop rate for ``commission.latency_time`` seconds with the actuator
    **disabled** (commands with ``enable = False`` at the held position): histogram, p50, p99,
    maximum, missed replies, and the link time the link budget computes for one step
    (:mod:`rths_hil.linkbudget`). Fails when more than 1 % of the replies are missed or the p99
    round trip is above the loop's feedback timeout (``loop.feedback_timeout``, default 0.8
    period).
``enable``
    Enable at the held position for 0.2 s (status ``ENABLED``, no motion beyond 20 µm + 5 % of
    ``commission.amplitude``), then disable (status without ``ENABLED``).
``motion``
    A ramp–hold–ramp of ``commission.amplitude`` (cosine ramps at most ``commission.velocity``,
    0.5 s holds) from the held position and back. Tracking from the FEI of the whole motion
    (the FEI paper's Eq. 2.1–2.5, :func:`rths_hil.fei.fei`) and from the Kalman estimator
    (:class:`rths_hil.estimation.DelayGainEstimator`); fails when the hold misses the target by
    more than 10 % of the amplitude or the FEI amplitude is off by more than 10 %.
``estop``
    Enabled at the held position, e-stop through the driver; for 0.2 s commands towards half
    the amplitude must be ignored (status ``ESTOP_ACTIVE``, position held within 20 µm); an
    ``enable = False`` command must acknowledge it and an ``enable = True`` command re-enable.
``watchdog``
    Only when ``commission.watchdog_test`` and the controller's heartbeat timeout are known
    (``commission.watchdog_timeout``, or the twin's ``twin.watchdog``): enabled, then silent;
    the controller must have latched (``ESTOP_ACTIVE | WATCHDOG``) after the timeout plus a
    margin; it is then acknowledged.
``limits``
    Skipped: the drivers' protocols carry no limit registers to read back.

Every channel is left disabled and not latched. The report (``report.md``, one PNG per channel
with the latency histogram and the motion) goes to ``commission/<timestamp>/``.
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

from rths_hil.drivers.base import Feedback, Status

from .config import Config
from .hybrid.phases import cosine_ramp, ramp_duration

log = logging.getLogger(__name__)

__all__ = ["ChannelReport", "StepResult", "commission", "write_report"]

_ENABLED = int(Status.ENABLED)
_ESTOP = int(Status.ESTOP_ACTIVE)
_FAULT = int(Status.FAULT)
_WATCHDOG = int(Status.WATCHDOG)
STEPS = ("identify", "latency", "enable", "motion", "estop", "watchdog", "limits")
#: Steps that move or enable the actuator (the operator confirms each on hardware).
MOVING = ("enable", "motion", "estop", "watchdog")


@dataclass
class StepResult:
    """One commissioning step: ``passed``, ``failed`` or ``skipped``, why, and its figures."""

    name: str
    status: str
    reason: str = ""
    figures: dict[str, Any] = field(default_factory=dict)


@dataclass
class ChannelReport:
    """The steps of one channel and the traces for its plots."""

    name: str
    driver: str
    target: str  # "twin" or "hardware"
    steps: list[StepResult] = field(default_factory=list)
    latency: np.ndarray = field(default_factory=lambda: np.zeros(0))
    motion: tuple[np.ndarray, np.ndarray] | None = None
    plot: str = ""

    @property
    def failed(self) -> list[StepResult]:
        """The failed steps."""
        return [s for s in self.steps if s.status == "failed"]


class _Controller:
    """Paced command/reply exchanges with one channel's controller (sequence after arming)."""

    def __init__(self, ch: Any, fs: float, timeout: float, heartbeat_steps: int) -> None:
        self.ch = ch
        self.drv = ch.driver
        self.recv = ch.receive
        self.dt = 1.0 / fs
        self.timeout = timeout
        self.hb = heartbeat_steps
        self.seq = 0
        self.last: Feedback | None = None

    def arm(self) -> Feedback | None:
        self.seq = 0
        return self.drv.arm(max(self.timeout, 0.5), self.recv)

    def exchange(self, x: float, enable: bool) -> tuple[Feedback | None, float]:
        """One command and its reply: (feedback or None, round trip in s)."""
        self.seq += 1
        t = time.perf_counter()
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
        self, path: np.ndarray, enable: bool, each: Callable[[int, Feedback | None, float], None]
    ) -> None:
        """One command of ``path`` per period (sleep, then spin to the deadline)."""
        perf = time.perf_counter
        t0 = perf() + self.dt
        for i, x in enumerate(path):
            deadline = t0 + i * self.dt
            gap = deadline - perf() - 3e-4
            if gap > 0:
                time.sleep(gap)
            while perf() < deadline:
                pass
            fb, rtt = self.exchange(float(x), enable)
            if self.hb and i % self.hb == 0:
                self.drv.heartbeat()
            each(i, fb, rtt)

    def hold(self, x: float, seconds: float, enable: bool) -> list[Feedback | None]:
        out: list[Feedback | None] = []
        path = np.full(max(1, round(seconds / self.dt)), x)
        self.run(path, enable, lambda i, f, r: out.append(f))
        return out


def _status_names(status: int | None) -> str:
    if status is None:
        return "no reply"
    names = [b.name for b in Status if b & status and b.name]
    return "|".join(names) if names else "0"


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


# ----------------------------------------------------------------------------------------------


def _channel(  # noqa: C901
    ch: Any,
    plan: Any,
    link_time: float | None,
    confirm: Callable[[str], bool],
) -> ChannelReport:
    com = plan.cfg["commission"]
    rep = ChannelReport(ch.name, ch.plan.driver_name, "twin" if ch.twin is not None else "hardware")
    ctl = _Controller(ch, plan.fs, plan.timeout, plan.heartbeat_steps)
    add = rep.steps.append
    amp = com["amplitude"]
    lim = ch.monitor.disp_limit

    # identify -----------------------------------------------------------------------------
    fb = ctl.arm()
    figs: dict[str, Any] = {
        "driver": ch.plan.driver_name,
        "profile": type(ch.driver).__name__,
        "controller": rep.target,
        "identity": getattr(ch.driver, "identity", None) or "not readable over this protocol",
    }
    if fb is None:
        add(StepResult("identify", "failed", "no reply to the arming command", figs))
    else:
        figs.update(position=fb.displacement, force=fb.force, status=_status_names(fb.status))
        if fb.status & _FAULT:
            add(StepResult("identify", "failed", "the controller reports a fault", figs))
        elif not math.isfinite(fb.displacement):
            add(StepResult("identify", "failed", "the position is not readable", figs))
        elif not -lim <= fb.displacement <= lim:
            add(StepResult("identify", "failed", "the position is outside the limit", figs))
        elif lim != math.inf and abs(fb.displacement) + amp > lim:
            add(StepResult("identify", "failed", "no room for the motion within the limit", figs))
        else:
            add(StepResult("identify", "passed", "", figs))
    if rep.steps[-1].status == "failed":
        for name in STEPS[1:]:
            add(StepResult(name, "skipped", "identify failed"))
        return rep
    x0 = float(fb.displacement)

    # latency (disabled) -------------------------------------------------------------------
    n = max(1, round(com["latency_time"] * plan.fs))
    rtt = np.full(n, np.nan)

    def on_lat(i, f, r):
        rtt[i] = r if f is not None else np.nan

    ctl.run(np.full(n, x0), False, on_lat)
    got = rtt[np.isfinite(rtt)]
    missed = int(n - got.size)
    rep.latency = got
    figs = {
        "replies": int(got.size),
        "missed": missed,
        "p50_ms": _pct(got, 50) * 1e3,
        "p99_ms": _pct(got, 99) * 1e3,
        "max_ms": float(got.max()) * 1e3 if got.size else math.nan,
        "timeout_ms": ctl.timeout * 1e3,
        "link_time_ms": None if link_time is None else link_time * 1e3,
    }
    if missed > 0.01 * n:
        add(StepResult("latency", "failed", f"{missed} of {n} replies missed (> 1 %)", figs))
    elif _pct(got, 99) > ctl.timeout:
        add(StepResult("latency", "failed", "p99 round trip above the feedback timeout", figs))
    else:
        add(StepResult("latency", "passed", "", figs))

    if not confirm(
        f"{rep.name or 'the actuator'}: enable the controller and move the actuator by "
        f"{amp * 1e3:g} mm at most {com['velocity'] * 1e3:g} mm/s, test its e-stop and watchdog"
    ):
        for name in MOVING:
            add(StepResult(name, "skipped", "not confirmed by the operator"))
        add(StepResult("limits", "skipped", "the protocol carries no limits to read back"))
        return rep
    tol = 2e-5 + 0.05 * amp

    # enable / disable edge ----------------------------------------------------------------
    on = ctl.hold(x0, 0.2, True)
    last_on = next((f for f in reversed(on) if f is not None), None)
    off, _ = ctl.exchange(x0, False)
    figs = {
        "enabled_status": _status_names(None if last_on is None else last_on.status),
        "disabled_status": _status_names(None if off is None else off.status),
        "drift_um": None if last_on is None else abs(last_on.displacement - x0) * 1e6,
    }
    if last_on is None or not last_on.status & _ENABLED:
        add(StepResult("enable", "failed", "the controller did not report ENABLED", figs))
    elif abs(last_on.displacement - x0) > tol:
        add(StepResult("enable", "failed", "the actuator moved when enabled in place", figs))
    elif off is None or off.status & _ENABLED:
        add(StepResult("enable", "failed", "the controller did not disable", figs))
    else:
        add(StepResult("enable", "passed", "", figs))

    # ramp - hold - ramp -------------------------------------------------------------------
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

    ctl.run(path, True, on_mot)
    ctl.exchange(x0, False)
    rep.motion = (path, meas)
    ok = np.isfinite(meas)
    figs = {"amplitude_mm": amp * 1e3, "ramp_s": nr / plan.fs, "missed": int((~ok).sum())}
    hold_end = nh // 5 + nr + nh
    if ok.sum() < 0.9 * path.size:
        add(StepResult("motion", "failed", "too many replies missed", figs))
    else:
        filled = meas.copy()
        idx = np.flatnonzero(ok)
        filled[~ok] = np.interp(np.flatnonzero(~ok), idx, meas[idx])
        from .estimation import DelayGainEstimator
        from .fei import fei

        r = fei(path, filled, plan.fs)
        est = DelayGainEstimator(fs=plan.fs)
        g = d = math.nan
        for u, y in zip(path.tolist(), filled.tolist(), strict=True):
            g, d = est.update(u, y)
        hold_err = abs(filled[hold_end - 1] - (x0 + amp))
        figs.update(
            fei_amplitude=r.amplitude,
            fei_delay_ms=r.delay * 1e3,
            kalman_gain=g,
            kalman_delay_ms=d * 1e3,
            hold_error_um=hold_err * 1e6,
        )
        if hold_err > 0.1 * amp:
            add(StepResult("motion", "failed", "the hold missed the target by > 10 %", figs))
        elif not r.valid or abs(r.amplitude - 1.0) > 0.1:
            add(StepResult("motion", "failed", "FEI amplitude off by more than 10 %", figs))
        else:
            add(StepResult("motion", "passed", "", figs))

    # e-stop: latch, hold, acknowledge, re-enable ------------------------------------------
    pre = ctl.hold(x0, 0.1, True)
    held_at = next((f.displacement for f in reversed(pre) if f is not None), x0)
    ch.driver.estop()
    during = ctl.hold(x0 + 0.5 * amp, 0.2, True)
    answered = [f for f in during if f is not None]  # a reply lost on a loaded link is no vote
    latched = bool(answered) and all(f.status & _ESTOP for f in answered)
    moved = max((abs(f.displacement - held_at) for f in during if f is not None), default=math.inf)
    ack, _ = ctl.exchange(held_at, False)
    re_on = ctl.hold(held_at, 0.1, True)
    last_re = next((f for f in reversed(re_on) if f is not None), None)
    re_ok = last_re is not None and bool(last_re.status & _ENABLED)
    ctl.exchange(held_at, False)
    figs = {
        "latched": bool(latched),
        "moved_um": moved * 1e6,
        "acknowledged": ack is not None and not ack.status & _ESTOP,
        "re_enabled": re_ok,
    }
    if not latched:
        add(StepResult("estop", "failed", "the controller did not latch the e-stop", figs))
    elif moved > 2e-5:
        add(StepResult("estop", "failed", "the actuator moved while latched", figs))
    elif not figs["acknowledged"]:
        add(StepResult("estop", "failed", "enable = False did not acknowledge the latch", figs))
    elif not re_ok:
        add(StepResult("estop", "failed", "the controller did not re-enable", figs))
    else:
        add(StepResult("estop", "passed", "", figs))

    # controller watchdog ------------------------------------------------------------------
    timeout = com["watchdog_timeout"] or (
        (plan_twin_watchdog(ch) or 0.0) if ch.twin is not None else 0.0
    )
    if not com["watchdog_test"]:
        add(StepResult("watchdog", "skipped", "commission.watchdog_test = false"))
    elif not timeout:
        why = "the controller's heartbeat timeout is not known (commission.watchdog_timeout)"
        add(StepResult("watchdog", "skipped", why))
    else:
        ctl.hold(x0, 0.1, True)
        t_quiet = time.perf_counter()
        time.sleep(timeout + max(0.25, 0.5 * timeout))
        quiet = time.perf_counter() - t_quiet
        fb = ctl.poll(x0, True)
        st = None if fb is None else int(fb.status)
        ok = st is not None and st & (_ESTOP | _WATCHDOG) == (_ESTOP | _WATCHDOG)
        ack, _ = ctl.exchange(x0, False)
        figs = {"timeout_s": timeout, "silent_s": quiet, "status": _status_names(st)}
        if ok:
            add(StepResult("watchdog", "passed", "", figs))
        else:
            add(StepResult("watchdog", "failed", "no watchdog latch after its timeout", figs))

    add(StepResult("limits", "skipped", "the protocol carries no limits to read back"))
    ctl.exchange(x0, False)  # left disabled, not latched
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

    Returns
    -------
    list of ChannelReport
    """
    from .hybrid.channel import Channel
    from .hybrid.plan import build_plan

    if plan is None:
        plan = build_plan(cfg, out, mode="paced")
    reports = []
    with contextlib.ExitStack() as stack:
        chans = []
        for cp in plan.channels:
            cp.twin_inline = False  # the twin's own thread runs its watchdog
            if cp.twin_enabled and not cp.twin_watchdog:
                cp.twin_watchdog = 0.5
            ch = Channel(cp, plan.fs)
            ch.open(stack, background_exact=False)
            chans.append(ch)
        for ch, load in zip(chans, _link_times(plan), strict=False):
            reports.append(_channel(ch, plan, load, confirm))
    out.mkdir(parents=True, exist_ok=True)
    write_report(reports, plan, out)
    return reports


def _link_times(plan: Any) -> list[float | None]:
    """Per channel: the link time of one step's traffic from the link budget.

    Known when every channel is on one link with a rate (``None`` otherwise: a virtual bus,
    a pseudo-terminal, or several links, which the budget does not map to channels).
    """
    links = list(getattr(plan, "links", []) or [])
    lt = links[0].per_channel if len(links) == 1 and links[0].rate else None
    return [lt for _ in plan.channels]


def write_report(reports: list[ChannelReport], plan: Any, out: Path) -> Path:
    """``report.md`` and one PNG per channel in ``out``; return the report's path."""
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
    for rep in reports:
        name = rep.name or "actuator"
        png = f"{name}.png"
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), constrained_layout=True)
        if rep.latency.size:
            axes[0].hist(rep.latency * 1e3, bins=50, color="C0")
        axes[0].set_xlabel("round trip (ms), actuator disabled")
        axes[0].set_ylabel("replies")
        axes[0].set_title(f"{name}: latency at {plan.fs:g} Hz")
        if rep.motion is not None:
            cmd, meas = rep.motion
            t = np.arange(cmd.size) / plan.fs
            axes[1].plot(t, 1e3 * cmd, lw=1.0, label="command")
            axes[1].plot(t, 1e3 * meas, lw=0.8, label="measured")
            axes[1].legend(loc="upper right")
        axes[1].set_xlabel("time (s)")
        axes[1].set_ylabel("displacement (mm)")
        axes[1].set_title(f"{name}: ramp–hold–ramp")
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
        lines += ["", f"![{name}]({png})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)

"""A commissioning session: every channel opened, its steps run in order, the report written."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rths_hil.drivers.base import LinkDown

from ..config import Config
from ..errors import InputError
from ..stopping import OperatorStop, Stopped
from . import steps
from .controller import Controller
from .plant import CHIRP_TIME
from .report import ChannelReport, StepResult, identified, write_report
from .steps import NO_LIMITS, STEPS
from .tuned import tuned_fragment

log = logging.getLogger(__name__)

__all__ = ["MAX_LATENCY_TIME", "commission", "plan_twin_watchdog"]

#: Longest latency window (s): at 4096 Hz 600 s of round trips are 20 MB of figures.
MAX_LATENCY_TIME = 600.0


def run_channel(
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
    ctl = Controller(ch, plan.fs, plan.timeout, plan.heartbeat_steps, stop)
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
        x0 = steps.identify(ctl, rep, amp, ch.monitor.disp_limit)
        if x0 is None:
            why_skipped = "identify failed"
            return rep
        start("latency", f"latency ({com['latency_time']:g} s, disabled)")
        steps.latency(ctl, rep, max(1, round(com["latency_time"] * plan.fs)), x0, link_time)
        if not confirm(
            f"{label}: enable the controller and move the actuator by {amp * 1e3:g} mm at "
            f"most {com['velocity'] * 1e3:g} mm/s, test its e-stop and watchdog"
        ):
            why_skipped = "not confirmed by the operator"
            return rep
        tol = 2e-5 + 0.05 * amp
        start("enable")
        steps.enable(ctl, rep, x0, tol)
        start("motion")
        steps.motion(ctl, rep, plan, x0)
        start("plant")
        steps.plant(ctl, rep, plan, x0, chirp_time)
        start("estop")
        steps.estop(ctl, rep, x0, amp)
        start("watchdog")
        steps.watchdog(ctl, rep, com, x0)
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
                    rep.steps.append(StepResult("limits", "skipped", NO_LIMITS))
                elif name not in done:
                    rep.steps.append(StepResult(name, "skipped", why_skipped or "not reached"))
            if x0 is not None or ctl.enabled:
                progress(f"{label}: hand-back")
                try:
                    steps.hand_back(
                        ctl, rep, x0 if x0 is not None else ctl.x, plan.cfg["end"]["hold"]
                    )
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
    out: str | Path,
    *,
    confirm: Callable[[str], bool] = lambda what: True,
    plan: Any = None,
    stop: OperatorStop | None = None,
    progress: Callable[[str], None] | None = None,
    chirp_time: float | None = None,
) -> list[ChannelReport]:
    """Commission every channel of ``cfg`` (module docstring); write the report into ``out``.

    Parameters
    ----------
    cfg : Config
    out : str or Path
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
    chirp_time : float, optional
        Length of the identification chirp (s; ``commission.chirp_time`` when not given);
        shorter is a quicker, coarser fit.

    Returns
    -------
    list of ChannelReport

    Raises
    ------
    InputError
        ``commission.latency_time`` above :data:`MAX_LATENCY_TIME`.
    """
    from ..hybrid.channel import Channel
    from ..hybrid.plan import build_plan

    out = Path(out)
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
                chirp = cfg["commission"]["chirp_time"] if chirp_time is None else chirp_time
                reports.append(run_channel(ch, plan, load, confirm, stop, say, chirp))
        except BaseException:  # a second signal, a driver's error: e-stop every channel
            for ch in chans:
                if ch.driver is not None:  # opened
                    with contextlib.suppress(Exception):
                        ch.driver.estop()
            raise
    out.mkdir(parents=True, exist_ok=True)
    write_report(reports, plan, out)
    if identified(reports):
        (out / "tuned.toml").write_text(tuned_fragment(reports, plan), encoding="utf-8")
    return reports


def _link_times(plan: Any) -> list[float | None]:
    """Per channel: the link time of one step's traffic from the link budget.

    Known when every channel is on one link with a rate (``None`` otherwise: a virtual bus,
    a pseudo-terminal, or several links, which the budget does not map to channels).
    """
    links = list(getattr(plan, "links", []) or [])
    lt = links[0].per_channel if len(links) == 1 and links[0].rate else None
    return [lt for _ in plan.channels]

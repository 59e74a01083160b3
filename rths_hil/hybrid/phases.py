"""Start and end of a test on an actuator: from where it is, back to a disabled controller.

A test does not begin at rest on a real rig: the actuator sits where a previous test, the
operator's jog or the specimen's installation left it. Commanding the structure's first target
(usually 0) at step 0 would make it jump there at the servo's full speed — a load spike on the
specimen before the test has begun. And at the end of a completed test the controller must be
handed back disabled, not left enabled until its own heartbeat watchdog latches an e-stop.

Start (:meth:`Phases.start`, after each controller is armed)
    The arming reply tells where each actuator is (position, force, status). The test is
    refused (:class:`~rths_hil.errors.InputError`, exit 2) when a position is outside
    ``safety.displacement_limit``, not readable, or the controller reports a fault. Then, with
    ``start.mode = "ramp"`` (the default), every actuator moves from where it is to its first
    command along a cosine ramp ``x(s) = a + (b − a)·(1 − cos πs)/2``, ``s ∈ [0, 1]``, whose
    duration is ``max(start.ramp_time, π·|b − a| / (2·v))`` with ``v = min(start.velocity,
    safety.velocity_limit / 2)`` (the cosine's peak velocity is ``π·|b − a| / (2·T)``), and holds
    there ``start.hold`` seconds; no ramp when every actuator is within ``start.tolerance`` of
    its first command (a twin at rest: the run is then exactly the one without this phase).
    With ``start.mode = "offset"`` the test runs about where the actuator is: each command
    sent is the loop's command plus the start position, each measured displacement the loop
    sees is the measurement minus it (so the record's command and measured columns are about
    the start position, and the displacement limit applies to them).
Force and load channels (``control.mode``, docs/channels.md)
    Their paths are forces (N): the start ramp goes from the force the arming reply measured
    (the first force set-point is that force: no jump) to the channel's first target (a load
    channel's load), over at least ``control.load_ramp`` (default ``start.ramp_time``); no
    ramp when it is within ``start.tolerance · structure.k_specimen``; ``start.mode =
    "offset"`` does not offset a force. At the end they ramp down to 0 N over
    ``control.load_ramp`` (whatever ``end.rest``) before the hand-back. Every channel's ramp
    takes the longest duration any channel needs; a force path is checked against the force
    limit, with no velocity.
End (:meth:`Phases.end`; completed run, operator stop, Ctrl-C, SIGTERM, SIGHUP)
    Each actuator ramps from its last command to ``end.rest_position`` (``end.rest =
    "position"``) or holds there (``"hold"``, the default), is commanded there for ``end.hold``
    seconds with the heartbeat going, and is then disabled with the protocol's own command
    (``enable = False``: the controller holds, reports neither ``ENABLED`` nor
    ``ESTOP_ACTIVE``, and its heartbeat watchdog no longer runs). A trip does not come here: it
    e-stops at once.

Both phases step like the loop: one command per channel per period (paced) or per reply
(lockstep), replies read, the heartbeat sent, and each channel's safety monitor checks the
commands, the feedback (link, watchdog, sequence, controller status, limits) at every step; a
trip ends the phase and the runner e-stops every channel. Paced, the start ramp begins a period
after arming, the loop's step 0 continues its grid and the end phase the loop's
(:attr:`Phases.next_deadline`, :func:`.pacer.first_deadline`): from arming to the hand-back
no controller waits more than a period for its next command (the runner does its set-up
before arming). The first command that enables a controller is where its actuator is (the
ramp's first point; :meth:`rths_hil.drivers.base.Driver.arm` writes nothing it would follow).
Their steps are not rows of the record (the record is the test); they are events:
``start_position`` (per channel), ``start_ramp`` and ``end_ramp`` (from/to positions, times,
steps, peak velocity, final measured positions), ``handback`` (per channel: position, force,
status, disabled, latched). Start-phase steps are
numbered ``-m … -1`` for the safety monitors and events (the loop's step 0 follows), end-phase
steps continue after the last loop step. On the wire the sequence numbers run on without a gap:
the loop's step ``k`` goes out as ``k + m`` (:class:`Link`).

Real hardware (a channel without a twin) is only driven after the operator's confirmation
(:func:`require_confirmation`), and never in lockstep unless its profile says the controller
advances one step per command (``driver.stepped``; :func:`preflight`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rths_hil.drivers.base import Feedback

from ..errors import InputError
from ..safety import StallRule, Trip
from .pacer import Pacer, ReplyBudget
from .setup import dot
from .stepio import ENABLED, ESTOP, FAULT, StepIO

if TYPE_CHECKING:  # pragma: no cover
    from ..records.recorder import Recorder
    from ..safety.channels import Safety
    from .channel import Channel
    from .plan import TestPlan
    from .result import RunResult

log = logging.getLogger(__name__)

#: The hand-back's disabling command is repeated, one exchange per step, until each channel
#: has confirmed or this long (s; or the loop's timeout when longer) has passed since the first.
HANDBACK_WAIT = 0.2

__all__ = [
    "Link",
    "Phases",
    "cosine_ramp",
    "hardware_channels",
    "preflight",
    "ramp_duration",
    "require_confirmation",
]


# ----------------------------------------------------------------------------------------------
# hardware: confirmation and lockstep


def hardware_channels(plan: TestPlan) -> list[str]:
    """Names of the channels that drive real hardware (no twin configured); ``""`` = unnamed."""
    return [cp.name for cp in plan.channels if not cp.twin_enabled]


def _channel_label(name: str) -> str:
    return f"actuators.{name}" if name else "the actuator"


def preflight(plan: TestPlan) -> None:
    """Refuse a lockstep run against hardware whose controller is not stepped by our commands.

    Lockstep is virtual time: it sends the next command as soon as a reply comes. A real
    controller runs on its own clock, so the test would run several times faster than the
    structure's time on the specimen. Allowed only when the channel's ``driver.stepped`` says
    the controller advances one step per command (a simulator, a stepped test rig).
    """
    if plan.mode != "lockstep":
        return
    for cp in plan.channels:
        if not cp.twin_enabled and not cp.cfg["driver"]["stepped"]:
            where = cp.cfg.source + (f": actuators.{cp.name}" if cp.name else "")
            raise InputError(
                f"{where}: lockstep against real hardware (twin.enabled = false) runs faster "
                "than the controller's clock; use paced mode, or set driver.stepped = true if "
                "this controller advances one step per command"
            )


def require_confirmation(plan: TestPlan, confirmed: bool, command: str) -> None:
    """Refuse to drive hardware without ``--confirm-hardware`` or ``loop.confirm_hardware``.

    Raises
    ------
    InputError
        Some channel has no twin and neither the flag nor the configuration confirms it.
    """
    hw = hardware_channels(plan)
    if not hw or confirmed or plan.cfg["loop"]["confirm_hardware"]:
        return
    names = ", ".join(_channel_label(n) for n in hw)
    raise InputError(
        f"{plan.cfg.source}: {names} drives real hardware (twin.enabled = false): "
        f"pass --confirm-hardware to `rths-hil {command}` (or set loop.confirm_hardware = true)"
    )


# ----------------------------------------------------------------------------------------------
# ramps


def ramp_duration(distance: float, velocity: float, minimum: float) -> float:
    """Duration of a cosine ramp over ``distance`` (m) whose peak velocity is ≤ ``velocity``.

    The cosine ramp ``x(s) = a + Δ·(1 − cos πs)/2`` over ``T`` seconds peaks at
    ``π·|Δ| / (2·T)``, so ``T = max(minimum, π·|Δ| / (2·velocity))``.
    """
    return max(float(minimum), math.pi * abs(distance) / (2.0 * velocity))


def cosine_ramp(a: float, b: float, steps: int) -> np.ndarray:
    """``steps + 1`` points from ``a`` to ``b`` (both included) along a cosine ramp."""
    if steps <= 0:
        return np.array([float(b)])
    s = np.arange(steps + 1) / steps
    x = a + (b - a) * 0.5 * (1.0 - np.cos(np.pi * s))
    x[0], x[-1] = a, b
    return x


def _ramp_velocity(chans: list[Channel], velocity: float) -> float:
    """The ramps' peak velocity: ``velocity``, at most half of any channel's velocity limit."""
    v = float(velocity)
    for ch in chans:
        lim = ch.monitor.vel_limit
        if lim != math.inf:
            v = min(v, 0.5 * lim)
    return v


# ----------------------------------------------------------------------------------------------
# the loop's view of a controller


class Link:
    """A channel's send/receive as the loop sees them: sequence shift and position offset.

    ``send(k, c, enable)`` sends sequence ``k + shift`` and displacement ``c + offset``;
    ``receive`` gives the feedback with ``seq − shift`` and ``displacement − offset``. Installed
    on a channel (its ``send``/``receive``) only when a start ramp or an offset needs it, so a
    run without either calls the driver directly.
    """

    __slots__ = ("offset", "raw_receive", "raw_send", "shift")

    def __init__(
        self,
        raw_send: Callable[..., None],
        raw_receive: Callable[[float], Feedback | None],
        shift: int = 0,
        offset: float = 0.0,
    ) -> None:
        self.raw_send = raw_send
        self.raw_receive = raw_receive
        self.shift = int(shift)
        self.offset = float(offset)

    def send(self, k: int, c: float, enable: bool = True) -> None:
        """Send the loop's command ``c`` of step ``k``."""
        self.raw_send(k + self.shift, c + self.offset, enable)

    def receive(self, timeout: float) -> Feedback | None:
        """The feedback in the loop's numbering and coordinates (or ``None``)."""
        fb = self.raw_receive(timeout)
        if fb is not None:
            fb.seq -= self.shift
            fb.displacement -= self.offset
        return fb


def _hold(ch: Channel, displacement: float, force: float) -> None:
    """Make ``ch``'s measurement (loop coordinates) what the loop holds on a missed reply.

    Without it a reply missed on the loop's first step would hold the channel's initial 0 m and
    0 N: a channel holding a 600 kN load would record 0 N, a force-controlled one would hand its
    structure 0 N. An unread force (NaN) leaves the held force as it was.
    """
    if math.isfinite(displacement):
        ch.measured = displacement
    if math.isfinite(force):
        ch.force = force


@dataclass
class _Where:
    """A channel at the start: where the actuator is and what step 0 commands."""

    position: float
    force: float
    status: int | None
    first: float  # the loop's step-0 command (loop coordinates)
    offset: float = 0.0


# ----------------------------------------------------------------------------------------------
# the phases


class Phases:
    """The start and end phases of one run (module docstring).

    Parameters
    ----------
    plan : TestPlan
        The run's plan (configuration, rate, mode, timeouts, heartbeat).
    channels : list of Channel
        The run's channels, open and armed.
    safety : Safety
        The run's safety (a fired rule becomes the trip).
    rec : Recorder
        The run's recorder (events).
    stopped : callable
        The operator stop flag: true once a stop signal came.
    pacer : Pacer, optional
        Paced: the wait for each deadline (default: the loop's settings,
        :meth:`Pacer.for_loop` with ``plan.spin``, finding stalls of the bridge longer than
        ``stall.min_stall``).
    stall : StallRule, optional
        Paced: the run's rule on the bridge's own stalls (the loop's): a ramp that did not run
        for longer than ``stall.min_stall`` slips its time base (it goes on at its own pace,
        no burst of the commands it missed), its watchdogs are told, the stall is an event,
        and one longer than ``max_stall`` trips. ``None``: stalls are not looked for.
    """

    def __init__(
        self,
        plan: TestPlan,
        channels: list[Channel],
        safety: Safety,
        rec: Recorder,
        stopped: Callable[[], bool],
        pacer: Pacer | None = None,
        stall: StallRule | None = None,
    ) -> None:
        self.plan = plan
        self.rec = rec
        self.chans = channels
        self.safety = safety
        self.stopped = stopped
        self.stall = stall
        #: the ramps' stalls of the bridge: (step, length s), as the loop's
        self.stalls: list[tuple[int, float]] = []
        min_stall = stall.min_stall if stall is not None else math.inf
        self.pacer = pacer or Pacer.for_loop(plan.dt, plan.spin, min_stall=min_stall)
        cfg = self.plan.cfg
        self.start_cfg = cfg["start"]
        self.end_cfg = cfg["end"]
        self.dt = self.plan.dt
        self.paced = self.plan.mode == "paced"
        self.raw = [(ch.send, ch.receive) for ch in self.chans]
        self.links: list[Link] | None = None
        self.shift = 0  # sequence number of the loop's step 0
        self.offsets = [0.0] * len(self.chans)
        self.where: list[_Where] = []
        self.handback_ok: bool | None = None
        self.sent = [0.0] * len(self.chans)  # the last absolute command sent to each channel
        #: paced: the deadline after the last step a phase sent (the next phase's grid), or
        #: ``None`` (no step sent yet, or lockstep)
        self.next_deadline: float | None = None

    # ------------------------------------------------------------------------------------------
    def first_commands(self) -> list[float]:
        """Each channel's command at the loop's step 0 (without stepping anything).

        Called before the controllers are armed (the runner computes the loop's own state of
        step 0 right after it), so nothing of it sits between arming and the start ramp.
        """
        st = self.plan.structure
        out = []
        if st.external:  # an external analysis gives its first target only when it runs
            xs = None
        else:
            xs = st.reset()
        for ch in self.chans:
            if xs is None:
                x = 0.0
            elif ch.dof >= 0:
                x = float(xs[ch.dof])
            else:
                x = float(dot(ch.row, xs))  # the channel's row of T (.setup)
            if ch.force_mode:  # the force of step 0 (from rest, or the load's)
                ch.trial = ch.trial_next = x
                x = ch.force_target(x, 0)
            ch.compensator.reset(x)
            out.append(float(ch.compensator.step(x)))
            ch.compensator.reset(x)
        return out

    def _locate(self, armed: list[Feedback | None], firsts: list[float]) -> list[_Where]:
        """Where each actuator is (the arming reply); refuse an unsafe start."""
        where = []
        for ch, fb, first in zip(self.chans, armed, firsts, strict=True):
            label = self.plan.cfg.source + ": " + _channel_label(ch.name)
            if fb is None:
                if ch.twin is None:
                    raise InputError(
                        f"{label}: the controller did not answer the arming command, so where "
                        "the actuator is cannot be read; refusing to start"
                    )
                # a twin that does not answer (an injected fault) sits at its rest position;
                # the loop's watchdog deals with the silence
                home = float(getattr(ch.twin.controller, "home", 0.0))
                where.append(_Where(home, math.nan, None, first))
                continue
            pos, force, status = float(fb.displacement), float(fb.force), int(fb.status)
            if status & FAULT:
                raise InputError(
                    f"{label}: the controller reports a fault (status 0x{status:02x}) at the "
                    "start; clear it on the controller before starting"
                )
            if not math.isfinite(pos):
                raise InputError(
                    f"{label}: the actuator position is not readable (status 0x{status:02x}); "
                    "refusing to start"
                )
            lim = ch.monitor.disp_limit
            if not -lim <= pos <= lim:
                raise InputError(
                    f"{label}: the actuator is at {pos * 1e3:+.3f} mm, outside the displacement "
                    f"limit ±{lim * 1e3:.3f} mm; bring it back within the limit on the "
                    "controller before starting"
                )
            where.append(_Where(pos, force, status, first))
        return where

    # ------------------------------------------------------------------------------------------
    def start(self, armed: list[Feedback | None], firsts: list[float] | None = None) -> Trip | None:
        """Read where each actuator is, refuse an unsafe start, ramp (or offset) to step 0.

        ``firsts``: :meth:`first_commands`, computed before arming (computed here when not
        given). Returns the trip that stopped the start ramp, or ``None`` (the loop may start;
        paced, :attr:`next_deadline` is where its grid continues the ramp's).

        Raises
        ------
        InputError
            An actuator outside the displacement limit, unreadable, or a controller fault.
        """
        rec = self.rec
        if firsts is None:
            firsts = self.first_commands()
        self.where = where = self._locate(armed, firsts)
        offset_mode = self.start_cfg["mode"] == "offset"
        for ch, w in zip(self.chans, where, strict=True):
            if offset_mode and w.status is not None and not ch.force_mode:
                w.offset = w.position
            rec.event(
                "start_position", 0.0, 0, channel=ch.name, position=w.position,
                force=w.force, status=w.status, first_command=w.first, offset=w.offset,
                mode=self.start_cfg["mode"], control=ch.control,
            )  # fmt: skip
        self.offsets = [w.offset for w in where]
        for ch, w in zip(self.chans, where, strict=True):
            ch.monitor.set_offset(w.offset)  # offset mode: the absolute stroke is watched too
            # what a missed reply holds until the first one comes: the measurement at arming
            # (loop coordinates), then each reply of the start ramp (_drive)
            _hold(ch, w.position - w.offset, w.force)
        # absolute commands: from where each actuator is to its step-0 command; a force
        # channel's from the force it measures (0 N unread) to its first force
        forced = np.array([ch.force_mode for ch in self.chans], dtype=bool)
        a = np.array(
            [
                (w.force if math.isfinite(w.force) else 0.0) if f else w.position
                for w, f in zip(where, forced, strict=True)
            ]
        )
        b = np.array([w.first + w.offset for w in where])
        self.sent = a.tolist()
        # a force within the force that moves the assumed specimen by start.tolerance
        tol = self.start_cfg["tolerance"]
        tol_f = tol * float(self.plan.cfg["structure"]["k_specimen"])
        trip = None
        gap = np.abs(b - a)
        if np.any(gap[~forced] > tol) or np.any(gap[forced] > tol_f):
            v = _ramp_velocity(self.chans, self.start_cfg["velocity"])
            dist = float(np.max(gap[~forced], initial=0.0))
            duration = ramp_duration(dist, v, self.start_cfg["ramp_time"])
            if np.any(forced):  # the load's ramp: at least control.load_ramp
                duration = max(duration, max(ch.plan.load_ramp for ch in self.chans))
            n_ramp = max(1, math.ceil(duration / self.dt))
            n_hold = round(self.start_cfg["hold"] / self.dt)
            paths = [
                np.concatenate([cosine_ramp(ai, bi, n_ramp), np.full(n_hold, bi)])
                for ai, bi in zip(a, b, strict=True)
            ]
            m = len(paths[0])
            k0 = -m
            t_start = k0 * self.dt
            # peak velocity of a displacement ramp; a force ramp's peak rate (N/s) apart
            rates = [float(np.max(np.abs(np.diff(p)))) / self.dt for p in paths]
            peak = [None if f else r for r, f in zip(rates, forced, strict=True)]
            force_rate = [r if f else None for r, f in zip(rates, forced, strict=True)]
            wall = time.perf_counter()
            trip, meas = self._drive(paths, seq0=0, k0=k0)
            wall = time.perf_counter() - wall
            # reset the feedback watchdogs: the loop's lead-in is not a missing reply
            for ch in self.chans:
                wd = ch.monitor.watchdog
                if wd is not None:
                    wd.reset()
            rec.event(
                "start_ramp", t_start, k0, channels=[ch.name for ch in self.chans],
                start=a.tolist(), end=b.tolist(), duration=n_ramp * self.dt,
                hold=n_hold * self.dt, steps=m, peak_velocity=peak, peak_force_rate=force_rate,
                velocity_limit=v, wall_duration=wall,
                measured_end=meas, completed=trip is None and not self.stopped(),
            )  # fmt: skip
            self.shift = m
        if self.shift or any(self.offsets):
            self._link()
        return trip

    def _link(self) -> None:
        """Put a :class:`Link` between each channel and its driver (shift and offset)."""
        self.links = []
        for ch, (send, recv), off in zip(self.chans, self.raw, self.offsets, strict=True):
            link = Link(send, recv, self.shift, off)
            ch.send, ch.receive = link.send, link.receive
            self.links.append(link)

    # ------------------------------------------------------------------------------------------
    def end(self, result: RunResult, t_first: float | None = None) -> Trip | None:
        """Ramp to the rest position (or hold), keep commanding, then disable each controller.

        Called after a completed run or an operator stop. ``t_first`` (paced): the loop's next
        deadline, which the end phase's grid continues (no silent gap before the hand-back).
        Returns a trip if a safety rule fired on the way (then the runner e-stops), else
        ``None``; records ``end_ramp`` and ``handback`` events and sets :attr:`handback_ok`.
        """
        rec = self.rec
        dt = self.dt
        k0 = result.steps
        seq0 = k0 + self.shift
        # absolute last commands (what each controller is holding now)
        if k0 > 0:
            last = np.array(
                [ch.last_command + off for ch, off in zip(self.chans, self.offsets, strict=True)]
            )
        else:  # stopped before step 0: the last command of the start ramp, or where it was
            last = np.array(self.sent)
        self.sent = last.tolist()
        if self.end_cfg["rest"] == "position":
            rest = np.full(len(self.chans), float(self.end_cfg["rest_position"]))
        else:
            rest = last.copy()
        forced = np.array([ch.force_mode for ch in self.chans], dtype=bool)
        rest[forced] = 0.0  # a force channel unloads before the hand-back
        v = _ramp_velocity(self.chans, self.start_cfg["velocity"])
        gap = np.abs(rest - last)
        dist = float(np.max(gap[~forced], initial=0.0))
        n_ramp = 0
        if dist > 0.0:
            n_ramp = max(1, math.ceil(ramp_duration(dist, v, 0.0) / dt))
        if np.any(gap[forced] > 0.0):  # the load's ramp down: control.load_ramp
            ramp = max(ch.plan.load_ramp for ch, f in zip(self.chans, forced, strict=True) if f)
            n_ramp = max(n_ramp, max(1, math.ceil(ramp / dt)))
        n_hold = round(self.end_cfg["hold"] / dt)
        paths = [
            np.concatenate([cosine_ramp(ai, bi, n_ramp)[1:], np.full(n_hold, bi)])
            for ai, bi in zip(last, rest, strict=True)
        ]
        m = len(paths[0])
        trip, meas = None, [math.nan] * len(self.chans)
        wall = time.perf_counter()
        if m:
            trip, meas = self._drive(paths, seq0=seq0, k0=k0, t_first=t_first)
        wall = time.perf_counter() - wall
        grid = None  # paced: the disabling exchanges on the loop's grid, steps m, m + 1, …
        if self.paced and (m or t_first is not None):
            if not m:
                self.pacer.start(t_first)
            grid = m
        rec.event(
            "end_ramp", k0 * dt, k0, channels=[ch.name for ch in self.chans], start=last.tolist(),
            end=rest.tolist(), rest=self.end_cfg["rest"], duration=n_ramp * dt,
            hold=n_hold * dt, steps=m, wall_duration=wall, measured_end=meas,
            completed=trip is None,
        )  # fmt: skip
        seq = seq0 + m
        if trip is None:
            self.handback_ok, used = self._disable(seq, k0 + m, rest, grid)
            seq += used
        # the loop's numbering for whatever is sent next (an e-stop's confirmation poll)
        self.shift = seq - k0
        self._link()
        return trip

    def _stalled(self, t: float, k: int, start: float, end: float) -> Trip | None:
        """A ramp did not run from ``start`` to ``end`` (perf_counter s): a stall of the bridge.

        As in the loop (:meth:`.step.Step.stalled`): every channel's watchdog is told, the stall
        is an event, and one longer than ``safety.max_stall`` trips. Otherwise the ramp's time
        base slips by the lateness: the step waited for goes out now and the rest at the
        ramp's own pace (the commands it missed are not sent in a burst, which would move the
        actuator faster than the ramp's velocity).
        """
        length = end - start
        lateness = end - self.pacer.due
        for ch in self.chans:
            wd = ch.monitor.watchdog
            if wd is not None:
                wd.stalled(start, end)
        self.stalls.append((k, length))
        trip = self.stall.check(length) if self.stall is not None else None
        action = "trip" if trip is not None else "slip"
        phase = "start" if k < 0 else "end"
        self.rec.event("stall", t, k, length=length, lateness=lateness, action=action, phase=phase)
        (log.warning if length >= 0.01 or trip is not None else log.info)(
            "the bridge stalled for %.1f ms in the %s phase (%s)", length * 1e3, phase, action
        )
        if trip is not None:
            return self.safety.fire(trip, None, t, k)
        self.pacer.slip(lateness)
        return None

    def _disable(
        self, seq: int, k: int, rest: np.ndarray, grid: int | None = None
    ) -> tuple[bool, int]:
        """Disable every controller; True when each replied disabled and unlatched.

        One exchange as the loop's step: ``enable=False`` to every channel, then every reply
        (on a shared CANopen bus, one SYNC for all axes); repeated, one exchange per step,
        while a channel has not confirmed, for up to :data:`HANDBACK_WAIT` (or the loop's
        timeout). A reply may be one the controller sent before it took the command (a
        CANopen TPDO carries no step, each axis answers every SYNC, and a loaded link's answers
        trail the SYNCs), and a drive may take a cycle to leave its enabled state: such an
        answer is no refusal. Each channel's first disabled, unlatched reply confirms it.
        ``grid`` (paced): the pacer step of the first exchange. Returns whether all confirmed
        and the number of exchanges (sequence numbers ``seq``, ``seq + 1``, …).
        """
        n = len(self.chans)
        fbs: list[Feedback | None] = [None] * n
        ok = [False] * n
        timeout = max(self.plan.timeout, HANDBACK_WAIT)
        used = 0
        t_end = math.inf
        while not all(ok) and time.perf_counter() < t_end:
            if grid is not None:
                self.pacer.wait(grid + used)
            if not used:
                t_end = time.perf_counter() + timeout
            sent = [True] * n
            for j, ((send, _), x) in enumerate(zip(self.raw, rest, strict=True)):
                try:
                    send(seq + used, float(x), False)
                except InputError:
                    sent[j] = False
            for j, (_, recv) in enumerate(self.raw):
                try:
                    fb = recv(timeout) if sent[j] else None
                except InputError:
                    fb = None
                if fb is not None and not ok[j]:  # a confirmation stands; later ones drained
                    fbs[j] = fb
                    ok[j] = fb is not None and not int(fb.status) & (ENABLED | ESTOP)
            used += 1
        for ch, fb, good in zip(self.chans, fbs, ok, strict=True):
            status = None if fb is None else int(fb.status)
            disabled = status is not None and not status & ENABLED
            latched = status is not None and bool(status & ESTOP)
            self.rec.event(
                "handback", k * self.dt, k, channel=ch.name, replied=fb is not None,
                position=None if fb is None else fb.displacement,
                force=None if fb is None else fb.force, status=status, disabled=disabled,
                latched=latched, exchanges=used,
            )  # fmt: skip
            if not good:
                log.warning(
                    "%s: the controller did not confirm the hand-back (status %s)",
                    _channel_label(ch.name),
                    "no reply" if status is None else f"0x{status:02x}",
                )
        return all(ok), used

    # ------------------------------------------------------------------------------------------
    def _drive(
        self, paths: list[np.ndarray], seq0: int, k0: int, t_first: float | None = None
    ) -> tuple[Trip | None, list[float]]:
        """Step absolute command paths (one per channel) as the loop steps; the safety checks.

        Sequence ``seq0 + i`` and safety step ``k0 + i`` for the path's ``i``-th command. Paced:
        one step per period (sleep, then spin to the deadline), the first at ``t_first`` (the
        previous phase's next deadline) or a moment from now (:func:`.pacer.first_deadline`),
        and :attr:`next_deadline` set after each; lockstep: the next command when the replies
        are in. Each step checks every channel's command, then sends them all and collects the
        replies (:class:`~.stepio.StepIO`, each within the loop's timeout), as the loop does;
        a trip before the sends sends none of the step. Returns the first trip (or ``None``)
        and each channel's last measured displacement (absolute; a force-controlled channel's
        measured force). A force channel's path is forces (N): checked against its force
        limit, no velocity.
        """
        plan = self.plan
        chans = self.chans
        paced = self.paced
        pacer = self.pacer
        dt = self.dt
        hb = plan.heartbeat_steps
        stopped = self.stopped
        fire = self.safety.fire
        m = len(paths[0])
        meas_abs = [math.nan] * len(chans)
        sent = self.sent
        cmds = list(sent)
        # each reply within the loop's timeout; the drivers' own send and receive (absolute)
        io = StepIO(self.raw, ReplyBudget(dt, plan.timeout, False), shared=False)
        replies, clocks = io.replies, io.clocks
        lanes = list(zip(chans, paths, self.offsets, strict=True))
        if paced:
            pacer.start(t_first)
        for i in range(m):
            k = k0 + i
            t = k * dt
            if k < 0 and stopped():
                # a stop during the start ramp: the loop sees it at once and ends the test
                return None, meas_abs
            if paced:
                now = pacer.wait(i)
                began = pacer.stall(now)
                if began is not None:  # the bridge did not run: not the controllers' silence
                    trip = self._stalled(t, k, began, now)
                    if trip is not None:
                        return trip, meas_abs
                pacer.sent(now)
                self.next_deadline = pacer.deadline(i + 1)
            for j, (ch, p, off) in enumerate(lanes):  # every command checked, then all sent
                c = cmds[j] = float(p[i])
                v = 0.0 if ch.force_mode else (c - sent[j]) / dt  # a force ramp: no motion
                trip = ch.monitor.check_command(t, k, c - off, v, c - off)
                if trip is not None:
                    return fire(trip, ch, t, k), meas_abs
            seq = seq0 + i
            io.send(seq, cmds, True)
            sent[:] = cmds
            io.collect(time.perf_counter())
            for j, (ch, _, off) in enumerate(lanes):
                fb = replies[j]
                ch.reply_clock = clocks[j]
                c = cmds[j]
                if fb is None:
                    trip = ch.monitor.check_feedback(
                        t, k, False, seq, -1, 0, c - off, math.nan, math.nan,
                        getattr(ch.driver, "link_down", None),
                    )  # fmt: skip
                else:
                    meas_abs[j] = fb.force if ch.force_mode else fb.displacement
                    _hold(ch, fb.displacement - off, fb.force)
                    trip = ch.monitor.check_feedback(
                        t, k, True, seq, fb.seq, fb.status, c - off,
                        fb.displacement - off, fb.force,
                    )  # fmt: skip
                if trip is not None:
                    return fire(trip, ch, t, k), meas_abs
            if hb and i % hb == 0:
                for ch in chans:
                    ch.heartbeat()
        return None, meas_abs

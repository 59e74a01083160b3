"""The phases of one loop step, bound once per run: wait and send, replies, structure,
evaluators, record, accounting (the step order of ``docs/loop.md``).

:class:`Step` holds what every phase needs (channels, safety, structure, recorder, the
:class:`~.pacer.Pacer`, the :class:`~.pacer.ReplyBudget` and the replies'
:class:`~.stepio.StepIO`) so that :meth:`Runner._loop <rths_hil.hybrid.runner.Runner._loop>`
only strings the phases together.
The phases keep the per-step path short: plain floats, no allocation but the structure's own.
"""

from __future__ import annotations

import logging
import math
import resource
import time
from typing import TYPE_CHECKING

import numpy as np

from ..records.run import row_writer
from ..safety import Trip
from .channel import Channel, step_mixed
from .pacer import Pacer, ReplyBudget
from .setup import dot
from .stepio import StepIO

if TYPE_CHECKING:  # pragma: no cover
    from ..records.recorder import Recorder
    from ..safety import StallRule
    from ..safety.channels import Safety
    from .plan import TestPlan

log = logging.getLogger(__name__)

__all__ = ["Step", "dot"]

_THREAD = resource.RUSAGE_THREAD
_perf = time.perf_counter


class Step:
    """The step phases of one run (``docs/loop.md``, "Step order").

    Parameters
    ----------
    plan : TestPlan
        The run's plan.
    channels : list of Channel
        The run's channels (open, armed, started).
    safety : Safety
        The run's safety; its phases are called once per step phase.
    stall_rule : StallRule or None
        Paced: the rule on the bridge's own stalls.
    rec : Recorder
        The run's recorder (rows and events).
    bufs : tuple
        The per-step arrays of :meth:`Runner._buffers`.
    console : float
        Seconds between peaks' use by the console (0: no console, the peaks are not kept).
    """

    __slots__ = (
        "ag",
        "budget",
        "bufs",
        "chans",
        "check_timing",
        "clocks",
        "collect",
        "console",
        "dt",
        "hb_next",
        "hb_steps",
        "io",
        "lat_list",
        "missed",
        "mixed",
        "multi",
        "n",
        "n_dof",
        "paced",
        "pacer",
        "plan",
        "ready_list",
        "rec",
        "safety",
        "slip",
        "st",
        "stall_rule",
        "stalled_list",
        "stalls",
        "was_over",
        "work_list",
        "write_row",
    )

    def __init__(
        self,
        plan: TestPlan,
        channels: list[Channel],
        safety: Safety,
        stall_rule: StallRule | None,
        rec: Recorder,
        bufs: tuple,
        console: float,
    ) -> None:
        self.plan = plan
        self.n = plan.n_steps
        self.dt = dt = plan.dt
        self.paced = paced = plan.mode == "paced"
        # a memoryview of the plan's float64 array: Python floats on indexing, no copy (an
        # hour at 4096 Hz is 118 MB; a list would be 32 B per sample)
        self.ag = np.ascontiguousarray(plan.ag, dtype=float).data
        self.chans = channels
        self.multi = len(channels) > 1
        self.safety = safety
        self.check_timing = safety.timing
        self.st = st = plan.structure
        self.n_dof = st.n_dof
        self.mixed = any(ch.force_mode for ch in channels)  # force or load channels
        self.rec = rec
        # (time, step, ground_accel, lateness, skew, dofs), every column by name
        self.write_row = row_writer(rec, channels, st)
        self.stall_rule = stall_rule
        min_stall = stall_rule.min_stall if stall_rule is not None else math.inf
        # paced: the deadlines t0 + k·Δt, the wait, lateness, overruns and our own stalls
        self.pacer = Pacer.for_loop(dt, plan.spin, plan.overrun_threshold, min_stall)
        self.budget = ReplyBudget(
            dt, plan.timeout, paced and not plan.cfg["loop"]["feedback_timeout"]
        )
        # every channel's replies within the budget (their sends are the runner's)
        self.io = io = StepIO([(ch.send, ch.receive) for ch in channels], self.budget)
        self.collect, self.clocks = io.collect, io.clocks
        self.slip = plan.after_stall == "slip"
        self.stalls: list[tuple[int, float]] = []
        self.hb_steps = plan.heartbeat_steps
        # the step of the next heartbeat (every hb_steps; at once after a stall; none: inf)
        self.hb_next = 0 if self.hb_steps else math.inf
        self.missed = 0
        self.was_over = False
        self.console = console
        # lateness (paced), work, ready and stalled (paced), allocated before arming
        self.bufs = bufs
        self.lat_list, _, self.work_list, self.ready_list, self.stalled_list = bufs

    # ---- wait for the deadline -------------------------------------------------------------
    def wait(self, k: int, tk: float) -> tuple[float, float, Trip | None]:
        """Paced: wait for deadline ``k``; a stall of the bridge or a catch-up after one.

        Returns the send time, the lateness so far and the stall's trip (then step ``k`` is
        not sent).
        """
        pacer = self.pacer
        now = pacer.wait(k)
        self.ready_list[k] = pacer.ready  # > 0: the previous step's work ran past it
        lat = now - pacer.due
        if lat > pacer.threshold:  # late: a stall of the bridge, or an overrun to catch up
            began = pacer.stall(now)
            if began is not None:
                trip = self.stalled(tk, k, began, now, lat)
                if trip is not None:
                    return now, lat, trip  # step k is not sent: every channel is e-stopped
                # the controllers' heartbeat watchdogs heard nothing during the stall: their
                # heartbeat goes with this step, not up to a period of loop.heartbeat later
                self.hb_next = k
                if self.slip:  # shift the time base: step k is on time from here
                    pacer.slip(lat)
                    self.rec.event("clock", tk, k, wall_t0=time.time() - tk, slip=lat)
            elif not self.slip:
                now = self.catch_up(now)
        return now, lat, None

    def stalled(self, tk: float, k: int, start: float, end: float, lateness: float) -> Trip | None:
        """The loop did not run from ``start`` to ``end`` (perf_counter s): a stall of the bridge.

        Every channel's watchdog is told (the time is not controller silence), the stall is an
        event with its length and what the loop does next, and a stall longer than
        ``safety.max_stall`` trips.
        """
        length = end - start
        for ch in self.chans:
            wd = ch.monitor.watchdog
            if wd is not None:
                wd.stalled(start, end)
        self.stalls.append((k, length))
        assert self.stall_rule is not None  # paced
        trip = self.stall_rule.check(length)
        action = "trip" if trip is not None else self.plan.after_stall
        self.rec.event("stall", tk, k, length=length, lateness=lateness, action=action)
        # every stall is an event; the console hears of the long ones (the summary counts all)
        (log.warning if length >= 0.01 or trip is not None else log.info)(
            "the bridge stalled for %.1f ms before step %d (%s)", length * 1e3, k, action
        )
        return None if trip is None else self.safety.fire(trip, None, tk, k)

    def catch_up(self, now: float) -> float:
        """Catch-up after a stall: wait until no channel's command moves faster (in wall-clock
        time, from the previous send) than its velocity limit allows; return the send time."""
        need = 0.0
        for ch in self.chans:
            lim = ch.monitor.vel_limit
            if lim != math.inf:
                need = max(need, abs(ch.command - ch.last_command) / lim)
        pacer = self.pacer
        return pacer.spin_until(pacer.prev_send + need, now)

    # ---- every channel's reply -------------------------------------------------------------
    def replies(self, k: int, now: float, tk: float) -> float:
        """Receive every channel's reply of step ``k`` (sent at ``now``) within the budget
        (:meth:`.stepio.StepIO.collect`).

        A reply ends a reply gap (one event); a missed one holds the measurement, counts and
        opens or extends the channel's gap. Returns the skew between the channels' replies
        (s; NaN with one channel or no reply).
        """
        # (after a slip, step k is on time: the grid's t0 moved)
        replies = self.collect(now, self.pacer.t0 + tk)
        t_first = t_last = 0.0
        for ch, fb, t in zip(self.chans, replies, self.clocks, strict=False):
            ch.reply_clock = t
            if fb is not None:
                if ch.gap_steps:  # a reply ends a gap: one event (the degradation)
                    self.gap_ended(ch, t)
                ch.ok_clock = t
                t -= now
                ch.feedback_ok = True
                ch.measured = fb.displacement
                ch.force = fb.force
                ch.reply_seq = fb.seq
                ch.reply_status = fb.status
                ch.feedback_time = t
                # the replies are read one after the other: the first that came is the
                # earliest, the last the latest
                if t_first == 0.0:
                    t_first = t
                t_last = t
            else:  # a missed reply: the measurement is held (``measured``, ``force``)
                self.missing(ch, k)
        return t_last - t_first if self.multi and t_first > 0.0 else math.nan

    def missing(self, ch: Channel, k: int) -> None:
        """Channel ``ch`` missed its reply of step ``k``."""
        ch.feedback_ok = False
        ch.reply_seq = -1
        ch.reply_status = 0
        ch.feedback_time = math.nan
        ch.missed_replies += 1
        self.missed += 1
        if not ch.gap_steps:
            ch.gap_start = k
        ch.gap_steps += 1
        drv = ch.driver
        if drv is not None:  # a channel runs bound (Channel.bind)
            ch.link_down = drv.link_down  # a dead link trips at once

    def gap_ended(self, ch: Channel, now: float, ended: bool = True) -> None:
        """A reply gap of ``ch`` ended at ``now`` (perf_counter s): one ``reply_gap`` event.

        The event gives the gap's first missed step and its loop time (``start``), the missed
        replies (``count``), the silence (``length``, s: from the good reply before the gap to
        the one that ended it, or to the end of the loop when ``ended`` is false; NaN when no
        reply had come before it) and the channel; the channel keeps the count and the longest.
        """
        k0, n = ch.gap_start, ch.gap_steps
        length = now - ch.ok_clock
        ch.gap_steps = 0
        ch.gaps += 1
        if n > ch.longest_gap_steps:
            ch.longest_gap_steps = n
        if length > ch.longest_gap:
            ch.longest_gap = length
        dt = self.dt
        self.rec.event(
            "reply_gap", k0 * dt, k0, channel=ch.name, start=k0 * dt, count=n, length=length,
            ended=ended, link_down=ch.link_down,
        )  # fmt: skip

    def heartbeat(self, k: int) -> None:
        """Every channel's heartbeat, due at step :attr:`hb_next` (the loop calls it from
        then: every ``hb_steps``, at once after a stall)."""
        if not self.hb_steps:  # no heartbeats (a stall set hb_next)
            self.hb_next = math.inf
            return
        self.hb_next = k + self.hb_steps
        for ch in self.chans:
            ch.heartbeat()

    # ---- structure: commit step k with the measured forces, next targets -------------------
    def advance(self, k: int, tk: float, xs, trip: Trip | None) -> tuple:
        """Commit step ``k`` with the measured forces; each channel's next target and command.

        The structure's step ``k`` with the channels' forces (``Tᵀ·f``; force or load
        channels: :func:`.channel.step_mixed`), then each channel's next target, velocity,
        restoring force and compensated command (``T·u``). After a trip the targets and
        commands are held. Returns the next DOF targets and the trip of the command phase (or
        of an external structure); an external structure that ends the test sets the last
        step.
        """
        chans = self.chans
        if trip is not None:
            for ch in chans:
                ch.target_next, ch.command_next = ch.target, ch.command
            return xs, trip
        st = self.st
        n_dof = self.n_dof
        if self.mixed:  # force or load channels (.channel.step_mixed)
            x_next = step_mixed(st, k, self.ag[k], chans, n_dof)
        else:
            if n_dof == 1 and not self.multi:
                x_next = st.step(k, self.ag[k], (chans[0].force * chans[0].row[0],))
            else:
                f = [0.0] * n_dof
                for ch in chans:
                    if ch.dof >= 0:
                        f[ch.dof] += ch.force
                    else:
                        for i, r in enumerate(ch.row):
                            f[i] += r * ch.force
                x_next = st.step(k, self.ag[k], f)
            v_d, r_d = st.v, st.r
            for ch in chans:
                d = ch.dof
                if d >= 0:
                    ch.target_next = x_next[d]
                    ch.velocity = v_d[d]
                    ch.restoring_force = r_d[d]
                else:
                    ch.target_next = dot(ch.row, x_next)
                    ch.velocity = dot(ch.row, v_d)
                    ch.restoring_force = dot(ch.row, r_d)
                ch.alpha = ch.compensator.alpha
                ch.command_next = ch.compensate(ch.target_next)
        trip = self.safety.command(tk, k)
        if st.finished and trip is None:
            trip = st.trip  # an external structure's fault
            if trip is None:
                self.n = k + 1  # the structure ends the test after this step
        return x_next, trip

    # ---- evaluators and their rules --------------------------------------------------------
    def evaluate(self, k: int, tk: float, lat: float, trip: Trip | None) -> Trip | None:
        """Every channel's evaluators, their rules, the stability warnings and (paced) the
        overrun rule; returns the step's trip."""
        for ch in self.chans:
            ch.evaluate(k)
        safety = self.safety
        if trip is None:
            trip = safety.evaluators(tk, k)
        if safety.events:  # the stability indicator's warnings
            for ev in safety.events:
                self.rec.event("stability", tk, k, **ev)
            safety.events.clear()
        if self.paced:
            over = self.pacer.over
            # the rule counts consecutive overruns: nothing to tell it while none
            if (over or self.was_over) and trip is None:
                trip = self.check_timing(tk, k, over, lat)
            self.was_over = over
        return trip

    # ---- record row k ----------------------------------------------------------------------
    def record(self, tk: float, k: int, lat: float, skew: float, xs) -> None:
        """Row ``k`` (every column by name, :func:`~rths_hil.records.run.row_writer`); then
        each channel's next target and command become the current ones."""
        self.write_row(tk, k, self.ag[k], lat, skew, xs)
        if self.console:
            self.peaks()
        for ch in self.chans:
            ch.last_command = ch.command
            ch.target = ch.target_next
            ch.command = ch.command_next

    def peaks(self) -> None:
        """Each channel's peaks, for the console's safety margin only."""
        for ch in self.chans:
            a = ch.measured if ch.force_mode else ch.target
            if a < 0:
                a = -a
            if a > ch.peak_displacement:
                ch.peak_displacement = a
            a = ch.velocity
            if a < 0:
                a = -a
            if a > ch.peak_velocity:
                ch.peak_velocity = a
            a = ch.force
            if a < 0:
                a = -a
            if a > ch.peak_force:
                ch.peak_force = a

    # ---- the step's own time ---------------------------------------------------------------
    def account(self, k: int, t_work: float, c_send: float, v_send: int) -> None:
        """Step ``k``'s work (from its replies to its row) and, paced, the time its thread was
        preempted without blocking (from its send); the reply budget's reserve."""
        t_end = _perf()
        self.work_list[k] = w = t_end - t_work
        if self.budget.auto:  # the reserve of the automatic wait (ReplyBudget.note)
            self.budget.note(w)
        if self.paced and resource.getrusage(_THREAD).ru_nvcsw == v_send:  # never blocked
            off_cpu = t_end - self.pacer.prev_send - (time.thread_time() - c_send)
            self.stalled_list[k] = max(0.0, off_cpu)

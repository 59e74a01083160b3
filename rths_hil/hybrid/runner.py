"""The step: what runs at every deadline, for every channel.

A :class:`Runner` takes a :class:`~rths_hil.hybrid.plan.TestPlan`, opens the channels and the
recorder, and steps. Each step ``k``::

    wait for the deadline (paced) ─┐
    send every channel's command   │  nothing computed between the deadline and the sends
    receive every channel's reply  │  (per-channel reply time and the skew between channels)
    safety: feedback phase         │  watchdog, sequence, controller status, NaN, limits, stuck
    structure: commit k with Tᵀ·f  │  -> DOF targets of k+1 -> each channel's T·u -> compensate
    safety: command phase          │  targets, velocities and commands of k+1, before any is sent
    evaluators per channel         │  streaming FEI, exact FEI, Kalman, adaptive α
    safety: evaluator phase        │  FEI and Kalman rules; overruns (paced)
    recorder: row k, by name       ┘

The CR integration is explicit in displacement (Chen & Ricles 2008): the targets of step k+1
depend only on the state of step k, so every command of step k+1 is ready before its deadline.

Safety is called once per phase (:class:`~rths_hil.safety.channels.Safety`); a fired rule comes
back as a :class:`~rths_hil.safety.Trip` naming the channel, the rule and the values, and the
runner then e-stops **every** channel through its driver (each twin or controller latches and
holds), confirms each latch with one status poll, records the events and returns; the CLI exits
with 3.

Modes, pacing and the overrun policy are those of ``docs/loop.md`` (:mod:`.timing`). What the
run returns is a :class:`~rths_hil.hybrid.result.RunResult`; the record's files and rows are
made in :mod:`.record`.
"""

from __future__ import annotations

import array
import contextlib
import gc
import logging
import math
import os
import resource
import signal
import sys
import time
from collections.abc import Callable

import numpy as np

from ..errors import InputError
from ..records.recorder import Recorder, RecordWriteError
from ..records.run import open_recorder, row_writer
from ..safety import OverrunRule, StallRule, Trip
from ..safety.channels import Safety
from ..stopping import OperatorStop
from ..structures.stages import StageContext
from .channel import Channel, step_mixed
from .phases import Phases, preflight
from .plan import TestPlan
from .result import RunResult
from .timing import MIN_SLEEP, first_deadline, p99

log = logging.getLogger(__name__)

__all__ = ["STOP_SIGNALS", "Runner"]

#: Signals that end a run through the operator-stop path (the same as Ctrl-C): every signal
#: whose default action terminates the process and that a terminal, a session manager or an
#: operator sends — a closed terminal or ssh session (SIGHUP) included.
STOP_SIGNALS = tuple(
    getattr(signal, name)
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2")
    if hasattr(signal, name)
)


# ----------------------------------------------------------------------------------------------
# the runner


class Runner:
    """Open the channels and the recorder of a :class:`TestPlan` and step it.

    Parameters
    ----------
    plan : TestPlan
    live : callable, optional
        Called with a status dict every ``loop.console`` seconds (the console line): the
        worst channel's FEI, its safety margin and the loop's rate and lateness.
    """

    def __init__(self, plan: TestPlan, live: Callable[[dict], None] | None = None) -> None:
        self.plan = plan
        self.live = live
        self.channels = [Channel(cp, plan.fs) for cp in plan.channels]
        paced = plan.mode == "paced"
        overrun = OverrunRule(plan.max_overruns) if paced else None
        self.safety = Safety(self.channels, overrun)
        #: the bridge's own stalls (paced): a gap between two sends longer than a period by
        #: at least ``min_stall`` — 2 ms, or two periods at rates below 1 kHz
        self.stall = StallRule(plan.max_stall, max(2e-3, 2.0 * plan.dt)) if paced else None
        self.result: RunResult | None = None
        #: the operator stop: the first stop signal's name (``stop_signal``), a second one
        #: raises KeyboardInterrupt (the e-stop path); installed for the run
        self._stop = OperatorStop()
        #: paced: the deadline after the loop's last step (the end phase continues the grid)
        self.next_deadline: float | None = None

    # ------------------------------------------------------------------------------------------
    def open_channel(self, ch: Channel, stack: contextlib.ExitStack) -> None:
        """Open one channel's transport (a subclass may give it another driver)."""
        ch.open(stack, background_exact=self.plan.mode == "paced")

    def _realtime(self, stack: contextlib.ExitStack, priority: int) -> None:
        """SCHED_FIFO for this thread (and the threads it starts: twins)."""
        from ..config import SCHEMA

        try:
            old = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (AttributeError, PermissionError, OSError) as exc:
            explicit = priority != SCHEMA["loop"]["priority"].default
            (log.warning if explicit else log.info)(
                "cannot set SCHED_FIFO priority %d (%s); running without", priority, exc
            )
            return
        stack.callback(os.sched_setscheduler, 0, old[0], old[1])

    def _pin(self, stack: contextlib.ExitStack, cpu: int) -> None:
        """Run this thread (and the threads it starts: twins) on CPU ``cpu`` only."""
        old = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {cpu})
        stack.callback(os.sched_setaffinity, 0, old)
        log.info("loop pinned to CPU %d", cpu)

    @property
    def stop_signal(self) -> str | None:
        """The first stop signal of the run (``"SIGINT"``, ``"SIGTERM"`` …) or None."""
        return self._stop.signal

    def _install_signals(self, stack: contextlib.ExitStack) -> None:
        stack.enter_context(self._stop)  # main thread only, restored at the end of the run

    def run(self) -> RunResult:  # noqa: C901
        """Run the test; return a :class:`RunResult` (never raises on a safety trip)."""
        plan = self.plan
        preflight(plan)
        with contextlib.ExitStack() as stack:
            self._install_signals(stack)
            if plan.mode == "paced" and plan.priority > 0:
                self._realtime(stack, plan.priority)
            if plan.mode == "paced" and plan.cpu >= 0:
                self._pin(stack, plan.cpu)
            for ch in self.channels:
                self.open_channel(ch, stack)
            stack.callback(plan.structure.close)
            first = self.channels[0]
            multi = len(self.channels) > 1
            rec = open_recorder(plan, self.channels)
            stack.callback(rec.close)
            for ch in self.channels:
                ch.warm_up()
            rec.event(
                "start",
                0.0,
                0,
                mode=plan.mode,
                fs=plan.fs,
                steps=plan.n_steps,
                rules=self.safety.rules,
                channels=[ch.name for ch in self.channels],
            )
            # Everything that takes time is done before any controller is armed: from the
            # arming command to the hand-back every controller gets a command (and its
            # heartbeat) every period, with no silent gap between the phases (docs/loop.md)
            phases = Phases(self, rec)
            firsts = phases.first_commands()  # the loop's step-0 commands ...
            start = self._start_state()  # ... and the loop's state of step 0 (in this order)
            bufs = self._buffers()
            self._quiet_interpreter(stack)
            # a new run on each controller: restart its sequence count, acknowledge a latch
            replies = []
            for ch in self.channels:
                armed = ch.driver.arm(max(plan.timeout, 0.5), ch.receive)
                replies.append(armed)
                rec.event(
                    "arm", 0.0, 0, channel=ch.name, replied=armed is not None,
                    status=None if armed is None else int(armed.status),
                    link=getattr(ch.driver, "link_note", None),
                )  # fmt: skip
            # from where each actuator is to step 0 (a ramp, or an offset), see .phases
            try:
                trip0 = phases.start(replies, firsts)
            except InputError as exc:
                rec.event("refused", 0.0, 0, reason=str(exc))
                raise
            except BaseException:
                self._estop_on_error(rec, 0)
                raise
            if trip0 is None:
                result = self._loop(rec, start, bufs, phases.next_deadline)
            else:
                result = self._not_started(trip0)
                rec.event("trip", **{k: v for k, v in trip0.as_event().items() if k != "kind"})
            result.start_steps = phases.shift
            if result.status in ("completed", "operator_stop"):
                # back to rest (or hold) and hand the controllers back disabled
                try:
                    trip1 = phases.end(result, self.next_deadline)
                except BaseException:
                    self._estop_on_error(rec, result.steps)
                    raise
                result.handback = phases.handback_ok
                if trip1 is not None:
                    result.status, result.trip = "trip", trip1
                    rec.event("trip", **{k: v for k, v in trip1.as_event().items() if k != "kind"})
            if result.status == "completed":
                try:  # the last rows: a write failure here is still a safety event
                    rec.flush()
                except RecordWriteError as exc:
                    result.status = "trip"
                    result.trip = Trip("record", str(exc)).at(result.steps * plan.dt, result.steps)
                    rec.event("trip", **dict(list(result.trip.as_event().items())[1:]))
            if result.status == "trip":
                result.estop_confirmed = self._estop_all(rec, result)
            ls = result.lateness_stats()
            if multi:
                result.driver_stats = {c.name: c.driver.stats.as_dict() for c in self.channels}
                result.twin_stats = {
                    c.name: c.twin.stats.as_dict() for c in self.channels if c.twin is not None
                }
            else:
                result.driver_stats = first.driver.stats.as_dict()
                if first.twin is not None:
                    result.twin_stats = first.twin.stats.as_dict()
            rec.event(
                "end",
                result.steps * plan.dt,
                result.steps,
                status=result.status,
                wall_duration=result.wall_time,
                steps_per_second=result.steps_per_second,
                lateness=ls,
                overrun_causes=result.overrun_causes(),
                missed_replies=result.missed_replies,
                reply_gaps=self.reply_gaps(),
                stalls=result.stall_summary(),
                estop_confirmed=result.estop_confirmed,
                driver_stats=result.driver_stats,
                twin_stats=result.twin_stats,
                final_alpha=result.final_alpha,
                handback=result.handback,
                start_steps=result.start_steps,
                exact_windows=first.exact_fei.windows if first.exact_fei is not None else 0,
                stability=self.stability_energy(),
            )
        self.result = result
        return result

    def _quiet_interpreter(self, stack: contextlib.ExitStack) -> None:
        """From arming to the end: the cyclic GC paused (collected once now, before arming)
        and, paced, a 100 µs thread switch interval (the in-process twins and the exact-FEI
        worker hand the interpreter back quickly); restored when the run ends."""
        old_switch = sys.getswitchinterval()
        gc_was = gc.isenabled()
        if self.plan.mode == "paced":
            sys.setswitchinterval(1e-4)
        gc.collect()
        gc.disable()
        stack.callback(sys.setswitchinterval, old_switch)
        if gc_was:
            stack.callback(gc.enable)

    def _buffers(self) -> tuple:
        """The loop's per-step arrays, allocated before the controllers are armed.

        ``(lateness, lateness view, work, ready, stalled)``; paced: lateness in a C double
        array (the console's p99 reads it as an ndarray without a copy), ``ready`` and
        ``stalled`` (the time the thread was taken off the CPU inside each step from its send
        to the end of its record without blocking: the wall time minus the thread's CPU time,
        0 after a voluntary context switch — a preemption by the machine, not the work,
        :func:`~.timing.attribute_overruns`); lockstep: none of these but ``work``.
        """
        n = self.plan.n_steps
        paced = self.plan.mode == "paced"
        lat_list = array.array("d", [0.0]) * n if paced else None  # no n-byte temporary
        lat_view = np.frombuffer(lat_list, dtype=float) if paced else np.zeros(0)
        work_list = array.array("d", [0.0]) * n
        ready_list = [0.0] * n if paced else None
        stalled_list = array.array("d", [0.0]) * n if paced else None
        return lat_list, lat_view, work_list, ready_list, stalled_list

    def _estop_on_error(self, rec: Recorder, k: int) -> None:
        """An exception (a second Ctrl-C) in a start or end phase: e-stop every channel."""
        for ch in self.channels:
            ch.estop()
        rec.event("error", k * self.plan.dt, k, error=repr(sys.exc_info()[1]))

    def _not_started(self, trip: Trip) -> RunResult:
        """The result of a run whose start ramp tripped (no loop step was taken)."""
        plan = self.plan
        return RunResult(
            status="trip",
            steps=0,
            planned_steps=plan.n_steps,
            trip=trip,
            run_dir=plan.run_dir,
            mode=plan.mode,
            fs=plan.fs,
            wall_time=0.0,
            lateness=np.zeros(0),
            overruns=0,
            missed_replies=0,
            estop_confirmed=None,
            final_alpha=self.channels[0].compensator.alpha,
            overrun_threshold=plan.overrun_threshold if plan.mode == "paced" else math.nan,
            work=np.zeros(0),
            channels=[ch.name for ch in self.channels],
        )

    def _estop_all(self, rec: Recorder, result: RunResult) -> bool:
        """E-stop every channel at once, then confirm each latch with one status poll."""
        for ch in self.channels:
            ch.estop()
        with contextlib.suppress(RecordWriteError):  # already a trip; keep what was flushed
            rec.flush()
        confirmed = True
        for ch in self.channels:
            ok = ch.confirm_estop(result.steps)
            confirmed = confirmed and ok
            rec.event(
                "estop",
                result.steps * self.plan.dt,
                result.steps - 1,
                channel=ch.name,
                confirmed=ok,
                status=ch.estop_status,
            )
        return confirmed

    # ------------------------------------------------------------------------------------------
    def _start_state(self) -> tuple[list[float], Trip | None]:
        """The state of step 0: the DOF targets, each channel's target and first command.

        The structure stage gets the running test first (an OpenSees site waits for its
        client in ``reset``); the commands of step 0 are checked before any is sent.
        """
        st = self.plan.structure
        st.attach(
            StageContext(
                self.plan.run_dir,
                sorted(self.channels, key=lambda ch: ch.dof),
                lambda: self.stop_signal is not None,
            )
        )
        xs = st.reset()
        for ch in self.channels:
            ch.target = xs[ch.dof] if ch.dof >= 0 else _dot(ch.row, xs)
            if ch.force_mode:  # a force target from the trial displacement, or the load
                ch.trial = ch.trial_next = ch.target
                ch.target = ch.force_target(ch.target, 0)
            ch.compensator.reset(ch.target)
            ch.alpha = ch.compensator.alpha
            ch.command = ch.compensate(ch.target)
            ch.target_next, ch.command_next = ch.target, ch.command
            ch.velocity = st.v[ch.dof] if ch.dof >= 0 else _dot(ch.row, st.v)
        trip = self.safety.command(0.0, 0)
        for ch in self.channels:
            ch.last_command = ch.command
        return xs, trip

    def _loop(  # noqa: C901
        self,
        rec: Recorder,
        start: tuple[list[float], Trip | None],
        bufs: tuple,
        t_first: float | None = None,
    ) -> RunResult:
        """Step from 0 until the end, a trip or an operator stop (the step; ``docs/loop.md``).

        ``start``: :meth:`_start_state`'s result; ``bufs``: :meth:`_buffers`'; ``t_first``
        (paced): the next deadline of the start phase, which the loop's grid continues.
        """
        plan = self.plan
        n = plan.n_steps
        dt = plan.dt
        paced = plan.mode == "paced"
        # a memoryview of the plan's float64 array: Python floats on indexing, no copy (an
        # hour at 4096 Hz is 118 MB; a list would be 32 B per sample)
        ag = memoryview(np.ascontiguousarray(plan.ag, dtype=float))
        chans = self.channels
        multi = len(chans) > 1
        safety = self.safety
        st = plan.structure
        n_dof = st.n_dof
        mixed = any(ch.force_mode for ch in chans)  # force or load channels
        st_step = st.step
        write_row = row_writer(rec, chans, st)  # (time, step, ground_accel, lateness, skew, dofs)

        check_feedback = safety.feedback
        check_command = safety.command
        check_evaluators = safety.evaluators
        check_timing = safety.timing
        timeout = plan.timeout
        # paced with the automatic reply wait (loop.feedback_timeout = 0): the replies are
        # waited for at most until the step's own work after them still ends before the next
        # deadline, i.e. until deadline + Δt − reserve, where reserve is the recent peak of that
        # work (+50 %, decaying by 0.2 % a step, between 5 % and 25 % of Δt; a step whose work
        # took longer than Δt is a stall, not work to reserve for). A reply later than
        # that is a missed reply (degradation: the measurement is held), not an overrun that
        # the following steps inherit (a controller that answers one request at a time fills
        # most of the period at 1 kHz).
        budget = paced and not plan.cfg["loop"]["feedback_timeout"]
        reserve_min, reserve_max = 0.05 * dt, 0.25 * dt
        reserve = 0.2 * dt
        spin = plan.spin
        min_sleep = MIN_SLEEP * dt
        thr = plan.overrun_threshold
        hb_steps = plan.heartbeat_steps
        hb_next = 0  # the step of the next heartbeat (every hb_steps; at once after a stall)
        stall_rule = self.stall
        min_stall = stall_rule.min_stall if stall_rule is not None else math.inf
        slip = plan.after_stall == "slip"
        stalls: list[tuple[int, float]] = []
        perf = time.perf_counter
        sleep = time.sleep
        nan = math.nan

        # lateness (paced; lockstep: zero by definition, see the result below), work, ready and
        # stalled (paced), allocated before arming (:meth:`_buffers`)
        lat_list, lat_view, work_list, ready_list, stalled_list = bufs
        cpu = time.thread_time
        usage = resource.getrusage
        THREAD = resource.RUSAGE_THREAD
        console = plan.console_interval if self.live is not None else 0.0
        next_console = math.inf

        xs, trip = start
        overruns = 0
        missed = 0
        status = "completed"
        k = 0
        lat = 0.0
        skew = nan
        was_over = False
        t_start = perf()
        # paced: on the start ramp's grid when it ran, else a moment from now (first_deadline)
        t0 = first_deadline(dt, t_first) if paced else t_start
        prev_send = t0 - dt  # the previous step's send (perf_counter): stalls are gaps from it
        # wall-clock time of deadline 0: row k was sent at wall_t0 + k·Δt + lateness[k]
        rec.event("clock", 0.0, 0, wall_t0=time.time() + (t0 - perf()))
        if console > 0:
            next_console = t_start + console
            last_console_k, last_console_t = 0, t_start
        wall = 0.0
        try:
            while k < n and trip is None:
                if self.stop_signal is not None:
                    status = "operator_stop"
                    trip = Trip("operator", f"operator stop ({self.stop_signal})").at(k * dt, k)
                    rec.event("operator_stop", k * dt, k, signal=self.stop_signal)
                    break
                tk = k * dt
                # ---- wait for the deadline, then send every command at once --------------------
                if paced:
                    deadline = t0 + tk
                    now = perf()
                    gap = deadline - now
                    ready_list[k] = -gap  # > 0: the previous step's work ran past the deadline
                    rem = gap - spin
                    if rem < min_sleep and gap > 2.0 * min_sleep:
                        rem = min_sleep  # give the CPU away every period (RT bandwidth limit)
                    if rem > 0:
                        sleep(rem)
                        now = perf()
                    while now < deadline:
                        now = perf()
                    lat = now - deadline
                    if lat > thr:  # late: a stall of the bridge, or an overrun to catch up
                        if lat > min_stall and now - prev_send - dt > min_stall:
                            trip = self._stall(rec, tk, k, prev_send + dt, now, lat, stalls)
                            if trip is not None:
                                break  # step k is not sent: every channel is e-stopped
                            # the controllers' heartbeat watchdogs heard nothing during the
                            # stall: their heartbeat goes with this step, not up to a period
                            # of loop.heartbeat later
                            hb_next = k
                            if slip:  # shift the time base: step k is on time from here
                                t0 += lat
                                rec.event("clock", tk, k, wall_t0=time.time() - tk, slip=lat)
                        elif not slip:
                            now = self._catch_up_spacing(now, prev_send)
                            lat = now - deadline
                    c_send = cpu()  # the step's work starts: the thread's CPU clock, its
                    v_send = usage(THREAD).ru_nvcsw  # voluntary context switches so far
                    for ch in chans:
                        ch.send(k, ch.command, True)
                    prev_send = now
                    lat_list[k] = lat
                else:
                    for ch in chans:
                        ch.send(k, ch.command, True)
                    now = perf()
                # ---- every channel's reply --------------------------------------------------
                t_lim = now + timeout
                if budget:
                    t_cut = t0 + tk + dt - reserve  # (t0: after a slip, step k is on time)
                    if t_cut < t_lim:
                        t_lim = t_cut
                t_first = t_last = 0.0
                for ch in chans:
                    rem = t_lim - perf() if multi or budget else timeout
                    fb = ch.receive(rem if rem > 0.0 else 0.0)
                    t = ch.reply_clock = perf()
                    if fb is not None:
                        if ch.gap_steps:  # a reply ends a gap: one event (the degradation)
                            self._gap_ended(rec, ch, t)
                        ch.ok_clock = t
                        t -= now
                        ch.feedback_ok = True
                        ch.measured = fb.displacement
                        ch.force = fb.force
                        ch.reply_seq = fb.seq
                        ch.reply_status = fb.status
                        ch.feedback_time = t
                        if t > t_last:
                            t_last = t
                        if t_first == 0.0 or t < t_first:
                            t_first = t
                    else:  # a missed reply: the measurement is held (``measured``, ``force``)
                        ch.feedback_ok = False
                        ch.reply_seq = -1
                        ch.reply_status = 0
                        ch.feedback_time = nan
                        ch.missed_replies += 1
                        missed += 1
                        if not ch.gap_steps:
                            ch.gap_start = k
                        ch.gap_steps += 1
                        ch.link_down = ch.driver.link_down  # a dead link trips at once
                t_work = perf()
                if multi:
                    skew = t_last - t_first if t_first > 0.0 else nan
                trip = check_feedback(tk, k)
                if hb_steps and k >= hb_next:
                    hb_next = k + hb_steps
                    for ch in chans:
                        ch.heartbeat()
                # ---- structure: commit step k with the measured forces, next targets ---------
                if trip is None:
                    if mixed:  # force or load channels (.channel.step_mixed)
                        x_next = step_mixed(st, k, ag[k], chans, n_dof)
                    else:
                        if n_dof == 1 and not multi:
                            x_next = st_step(k, ag[k], (chans[0].force * chans[0].row[0],))
                        else:
                            f = [0.0] * n_dof
                            for ch in chans:
                                if ch.dof >= 0:
                                    f[ch.dof] += ch.force
                                else:
                                    for i, r in enumerate(ch.row):
                                        f[i] += r * ch.force
                            x_next = st_step(k, ag[k], f)
                        v_d, r_d = st.v, st.r
                        for ch in chans:
                            d = ch.dof
                            if d >= 0:
                                ch.target_next = x_next[d]
                                ch.velocity = v_d[d]
                                ch.restoring_force = r_d[d]
                            else:
                                ch.target_next = _dot(ch.row, x_next)
                                ch.velocity = _dot(ch.row, v_d)
                                ch.restoring_force = _dot(ch.row, r_d)
                            ch.alpha = ch.compensator.alpha
                            ch.command_next = ch.compensate(ch.target_next)
                    trip = check_command(tk, k)
                    if st.finished and trip is None:
                        trip = st.trip  # an external structure's fault
                        if trip is None:
                            n = k + 1  # the structure ends the test after this step
                else:
                    x_next = xs
                    for ch in chans:
                        ch.target_next, ch.command_next = ch.target, ch.command
                # ---- evaluators -------------------------------------------------------------
                for ch in chans:
                    ch.evaluate(k)
                if trip is None:
                    trip = check_evaluators(tk, k)
                if safety.events:  # the stability indicator's warnings
                    for ev in safety.events:
                        rec.event("stability", tk, k, **ev)
                    safety.events.clear()
                if paced:
                    over = lat > thr
                    if over:
                        overruns += 1
                    # the rule counts consecutive overruns: nothing to tell it while none
                    if (over or was_over) and trip is None:
                        trip = check_timing(tk, k, over, lat)
                    was_over = over
                # ---- record row k (every column by name, see .record.row_writer) -------------
                write_row(tk, k, ag[k], lat, skew, xs)
                for ch in chans:
                    if console:  # peaks, for the console's safety margin only
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
                    ch.last_command = ch.command
                    ch.target = ch.target_next
                    ch.command = ch.command_next
                xs = x_next
                t_end = perf()
                w = t_end - t_work
                work_list[k] = w
                if budget and w < dt:  # the reserve for the work after the replies (above)
                    w *= 1.5
                    reserve = w if w > reserve else reserve * 0.998
                    if reserve < reserve_min:
                        reserve = reserve_min
                    elif reserve > reserve_max:
                        reserve = reserve_max
                if paced and usage(THREAD).ru_nvcsw == v_send:  # the thread never blocked
                    stalled_list[k] = max(0.0, t_end - prev_send - (cpu() - c_send))
                k += 1
                if console > 0:
                    now = perf()
                    if now >= next_console:
                        rate = (k - last_console_k) / (now - last_console_t)
                        recent = lat_view[last_console_k:k]
                        self.live(self._status(tk, k, n, rate, recent, overruns, paced))
                        last_console_k, last_console_t = k, now
                        next_console = now + console
            wall = perf() - t_start
        except RecordWriteError as exc:  # disk full or gone: a safety event, not a crash
            wall = perf() - t_start
            trip = Trip("record", str(exc), values={"rows_on_disk": rec.rows}).at(k * dt, k)
            for ch in chans:
                ch.last_command = ch.command
            k += 1  # step k was sent and answered; only its row is lost
        except BaseException:
            for ch in chans:
                ch.estop()
            rec.event("error", k * dt, k, error=repr(sys.exc_info()[1]))
            raise
        # paced: the end phase continues this grid (no silent gap before the hand-back)
        self.next_deadline = t0 + k * dt if paced else None
        for ch in chans:  # a gap still open at the end (the trip it caused, or the last steps)
            if ch.gap_steps:
                self._gap_ended(rec, ch, perf(), ended=False)
        if trip is not None and status != "operator_stop":
            status = "trip"
            rec.event("trip", **{k2: v2 for k2, v2 in trip.as_event().items() if k2 != "kind"})
        # paced: a view (keeps lat_list alive, no copy); lockstep: zeros without memory
        lateness = lat_view[:k] if paced else np.broadcast_to(np.float64(0.0), (k,))
        ready = np.array(ready_list[:k], dtype=float) if paced else np.zeros(0)
        return RunResult(
            status=status,
            steps=k,
            planned_steps=plan.n_steps,
            trip=trip,
            run_dir=plan.run_dir,
            mode=plan.mode,
            fs=plan.fs,
            wall_time=wall,
            lateness=lateness,
            overruns=overruns,
            missed_replies=missed,
            estop_confirmed=None,
            final_alpha=chans[0].compensator.alpha,
            ready=ready,
            overrun_threshold=thr if paced else math.nan,
            work=np.frombuffer(work_list, dtype=float)[:k],
            stalled=np.frombuffer(stalled_list, dtype=float)[:k] if paced else np.zeros(0),
            channels=[ch.name for ch in chans],
            stalls=stalls,
        )

    def _gap_ended(self, rec: Recorder, ch: Channel, now: float, ended: bool = True) -> None:
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
        dt = self.plan.dt
        rec.event(
            "reply_gap", k0 * dt, k0, channel=ch.name, start=k0 * dt, count=n, length=length,
            ended=ended, link_down=ch.link_down,
        )  # fmt: skip

    def reply_gaps(self) -> dict:
        """The run's reply gaps for the ``end`` event and the summary.

        ``count`` (gaps), ``missed`` (missed replies), ``longest`` (s of silence) and
        ``longest_steps`` over the channels, and ``channels`` (the same per channel) when
        there are several.
        """

        def one(ch: Channel) -> dict:
            return {
                "count": ch.gaps,
                "missed": ch.missed_replies,
                "longest": ch.longest_gap,
                "longest_steps": ch.longest_gap_steps,
            }

        per = {ch.name: one(ch) for ch in self.channels}
        out = {
            "count": sum(v["count"] for v in per.values()),
            "missed": sum(v["missed"] for v in per.values()),
            "longest": max(v["longest"] for v in per.values()),
            "longest_steps": max(v["longest_steps"] for v in per.values()),
        }
        if len(per) > 1:
            out["channels"] = per
        return out

    def _stall(
        self,
        rec: Recorder,
        tk: float,
        k: int,
        start: float,
        end: float,
        lateness: float,
        stalls: list,
    ) -> Trip | None:
        """The loop did not run from ``start`` to ``end`` (perf_counter s): a stall of the bridge.

        Every channel's watchdog is told (the time is not controller silence), the stall is an
        event with its length and what the loop does next, and a stall longer than
        ``safety.max_stall`` trips.
        """
        length = end - start
        for ch in self.channels:
            wd = ch.monitor.watchdog
            if wd is not None:
                wd.stalled(start, end)
        stalls.append((k, length))
        trip = self.stall.check(length)
        action = "trip" if trip is not None else self.plan.after_stall
        rec.event("stall", tk, k, length=length, lateness=lateness, action=action)
        # every stall is an event; the console hears of the long ones (the summary counts all)
        (log.warning if length >= 0.01 or trip is not None else log.info)(
            "the bridge stalled for %.1f ms before step %d (%s)", length * 1e3, k, action
        )
        return None if trip is None else self.safety.fire(trip, None, tk, k)

    def _catch_up_spacing(self, now: float, prev_send: float) -> float:
        """Catch-up after a stall: wait until no channel's command moves faster (in wall-clock
        time, from the previous send) than its velocity limit allows; return the send time."""
        need = 0.0
        for ch in self.channels:
            lim = ch.monitor.vel_limit
            if lim != math.inf:
                need = max(need, abs(ch.command - ch.last_command) / lim)
        perf = time.perf_counter
        while now < prev_send + need:
            now = perf()
        return now

    def stability_energy(self) -> dict:
        """Per channel with the stability indicator: the energy the tracking error injected
        and the structure's damping dissipated over the run (J), their ratio, the damping
        along the actuator (N·s/m), the window (s) and the levels."""
        out = {}
        for ch in self.channels:
            ind = ch.stability_ind
            rule = ch.monitor.stability
            if ind is None or rule is None:
                continue
            out[ch.name] = {
                "injected": ind.injected,
                "dissipated": ind.dissipated,
                "ratio": ind.total_ratio,
                "damping": ind.damping,
                "window": ind.window,
                "warn": rule.warn,
                "limit": rule.limit,
                "trip": rule.trip,
            }
        return out

    def _status(self, tk, k, n, rate, recent, overruns, paced) -> dict:
        """The console's status dict: the worst channel (nearest a limit) and its FEI."""
        name, quantity, margin = self.safety.margin()
        ch = next((c for c in self.channels if c.name == name), self.channels[0])
        if len(self.channels) > 1 and margin == math.inf:  # no limits: the largest |FEI delay|
            ch = max(
                self.channels,
                key=lambda c: abs(c.fei_delay) if c.fei_delay == c.fei_delay else -1.0,
            )
        return {
            "t": tk,
            "k": k,
            "n": n,
            "rate": rate,
            "p99_lateness": p99(recent) if paced and recent.size else 0.0,
            "overruns": overruns,
            "missed": sum(c.missed_replies for c in self.channels),
            "channel": ch.name,
            "amplitude": ch.fei_amplitude,
            "delay": ch.fei_delay,
            "valid": ch.fei_valid,
            "stability": ch.stability,
            "peak_displacement": ch.peak_displacement,
            "margin": (quantity, margin),
            "alpha": ch.compensator.alpha,
            "compensation": ch.compensator.enabled,
            "open_ended": self.plan.cfg["structure"]["kind"] == "openfresco",
            "mode": self.plan.mode,
        }


def _dot(row: list[float], x) -> float:
    """T-row · vector for short rows (plain floats)."""
    s = 0.0
    for r, v in zip(row, x, strict=False):
        if r:
            s += r * v
    return s

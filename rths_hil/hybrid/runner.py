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

The phases of a step are :class:`~.step.Step`'s methods; the paced wait is a
:class:`~.pacer.Pacer`. Modes, pacing and the overrun policy are those of ``docs/loop.md``
(:mod:`.pacer`, :mod:`.timing`). What the run returns is a
:class:`~rths_hil.hybrid.result.RunResult`; the record's files and rows are made in
:mod:`.record`.
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
from ..records.run import open_recorder
from ..safety import OverrunRule, StallRule, Trip
from ..safety.channels import Safety
from ..stopping import OperatorStop
from ..structures.stages import StageContext
from .channel import Channel
from .phases import Phases, preflight
from .plan import TestPlan
from .result import RunResult
from .step import Step, dot
from .timing import p99

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

    def run(self) -> RunResult:
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
            phases = Phases(
                plan,
                self.channels,
                self.safety,
                rec,
                lambda: self.stop_signal is not None,
                stall=self.stall,
            )
            firsts = phases.first_commands()  # the loop's step-0 commands ...
            start = self._start_state()  # ... and the loop's state of step 0 (in this order)
            bufs = self._buffers()
            self._quiet_interpreter(stack)
            self._check_links(rec)
            if self.stop_signal is None:
                result = self._armed_run(rec, phases, firsts, start, bufs)
            else:
                # a stop signal before any controller was armed (a Ctrl-C while the run was
                # built, rths_hil.stopping): none is armed, acknowledged or commanded
                result = self._not_started(self._operator_stop(rec, 0))
                result.status = "operator_stop"
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

    def _armed_run(
        self,
        rec: Recorder,
        phases: Phases,
        firsts: list[float],
        start: tuple[list[float], Trip | None],
        bufs: tuple,
    ) -> RunResult:
        """Arm every controller, ramp to step 0, run the loop and hand the controllers back."""
        plan = self.plan
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
        result.stalls = sorted([*phases.stalls, *result.stalls])  # the ramps' and the loop's
        return result

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
    def _check_links(self, rec: Recorder) -> None:
        """Say what each link, as measured when it opened, means at the loop rate (a warning
        on the terminal and a ``link`` event; e.g. a controller too slow for the rate)."""
        for ch in self.channels:
            warning = ch.driver.link_check(self.plan.fs)
            if warning:
                log.warning("channel %s: %s", ch.name, warning)
                rec.event("link", 0.0, 0, channel=ch.name, warning=warning)

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
            ch.target = xs[ch.dof] if ch.dof >= 0 else dot(ch.row, xs)
            if ch.force_mode:  # a force target from the trial displacement, or the load
                ch.trial = ch.trial_next = ch.target
                ch.target = ch.force_target(ch.target, 0)
            ch.compensator.reset(ch.target)
            ch.alpha = ch.compensator.alpha
            ch.command = ch.compensate(ch.target)
            ch.target_next, ch.command_next = ch.target, ch.command
            ch.velocity = st.v[ch.dof] if ch.dof >= 0 else dot(ch.row, st.v)
        trip = self.safety.command(0.0, 0)
        for ch in self.channels:
            ch.last_command = ch.command
        return xs, trip

    def _loop(
        self,
        rec: Recorder,
        start: tuple[list[float], Trip | None],
        bufs: tuple,
        t_first: float | None = None,
    ) -> RunResult:
        """Step from 0 until the end, a trip or an operator stop (the step; ``docs/loop.md``).

        ``start``: :meth:`_start_state`'s result; ``bufs``: :meth:`_buffers`'; ``t_first``
        (paced): the next deadline of the start phase, which the loop's grid continues. The
        phases of a step are :class:`~.step.Step`'s.
        """
        plan = self.plan
        dt = plan.dt
        paced = plan.mode == "paced"
        chans = self.channels
        console = plan.console_interval if self.live is not None else 0.0
        step = Step(plan, chans, self.safety, self.stall, rec, bufs, console)
        pacer = step.pacer
        wait, sent, replies = step.wait, pacer.sent, step.replies
        check_feedback, heartbeat, advance = self.safety.feedback, step.heartbeat, step.advance
        evaluate, record, account = step.evaluate, step.record, step.account
        lat_list = bufs[0]
        stop = self._stop
        perf = time.perf_counter
        cpu = time.thread_time
        usage = resource.getrusage
        THREAD = resource.RUSAGE_THREAD
        xs, trip = start
        status = "completed"
        k = 0
        lat = c_send = 0.0
        v_send = 0
        t_start = perf()
        # paced: on the start ramp's grid when it ran, else a moment from now (first_deadline)
        t0 = pacer.start(t_first) if paced else t_start
        # wall-clock time of deadline 0: row k was sent at wall_t0 + k·Δt + lateness[k]
        rec.event("clock", 0.0, 0, wall_t0=time.time() + (t0 - perf()))
        live = _Console(self, bufs[1], t_start, console)
        try:
            while k < step.n and trip is None:
                if stop.signal is not None:  # (the attribute: no property call per step)
                    status, trip = "operator_stop", self._operator_stop(rec, k)
                    break
                tk = k * dt
                # ---- wait for the deadline, then send every command at once ----------------
                if paced:
                    now, lat, trip = wait(k, tk)
                    if trip is not None:
                        break  # step k is not sent: every channel is e-stopped
                    c_send = cpu()  # the step's work starts: the thread's CPU clock, its
                    v_send = usage(THREAD).ru_nvcsw  # voluntary context switches so far
                for ch in chans:
                    ch.send(k, ch.command, True)
                if paced:
                    lat_list[k] = lat = sent(now)
                else:
                    now = perf()
                skew = replies(k, now, tk)  # ---- every channel's reply -------------------
                t_work = perf()
                trip = check_feedback(tk, k)
                if k >= step.hb_next:  # (the test here: no call on the other steps)
                    heartbeat(k)
                x_next, trip = advance(k, tk, xs, trip)  # ---- structure, command safety --
                trip = evaluate(k, tk, lat, trip)  # ---- evaluators, their rules -----------
                record(tk, k, lat, skew, xs)  # ---- row k ----------------------------------
                xs = x_next
                account(k, t_work, c_send, v_send)
                k += 1
                if console:
                    live.tick(tk, k, step.n, pacer.overruns)
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
        self.next_deadline = pacer.deadline(k) if paced else None
        return self._loop_result(rec, step, k, wall, trip, status)

    def _operator_stop(self, rec: Recorder, k: int) -> Trip:
        """The operator stopped the run before step ``k``: its event and trip."""
        dt = self.plan.dt
        rec.event("operator_stop", k * dt, k, signal=self.stop_signal)
        return Trip("operator", f"operator stop ({self.stop_signal})").at(k * dt, k)

    def _loop_result(
        self, rec: Recorder, step: Step, k: int, wall: float, trip: Trip | None, status: str
    ) -> RunResult:
        """The loop's :class:`RunResult` after ``k`` steps (open reply gaps and the trip
        recorded)."""
        plan = self.plan
        paced = step.paced
        chans = self.channels
        for ch in chans:  # a gap still open at the end (the trip it caused, or the last steps)
            if ch.gap_steps:
                step.gap_ended(ch, time.perf_counter(), ended=False)
        if trip is not None and status != "operator_stop":
            status = "trip"
            rec.event("trip", **{k2: v2 for k2, v2 in trip.as_event().items() if k2 != "kind"})
        _lat_list, lat_view, work_list, ready_list, stalled_list = step.bufs
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
            overruns=step.pacer.overruns,
            missed_replies=step.missed,
            estop_confirmed=None,
            final_alpha=chans[0].compensator.alpha,
            ready=ready,
            overrun_threshold=plan.overrun_threshold if paced else math.nan,
            work=np.frombuffer(work_list, dtype=float)[:k],
            stalled=np.frombuffer(stalled_list, dtype=float)[:k] if paced else np.zeros(0),
            channels=[ch.name for ch in chans],
            stalls=step.stalls,
        )

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


class _Console:
    """The console's status line every ``loop.console`` seconds (:meth:`Runner._status`)."""

    __slots__ = ("interval", "last_k", "last_t", "lat_view", "next_t", "runner")

    def __init__(self, runner: Runner, lat_view: np.ndarray, t_start: float, interval: float):
        self.runner = runner
        self.lat_view = lat_view
        self.interval = interval
        self.next_t = t_start + interval if interval > 0 else math.inf
        self.last_k, self.last_t = 0, t_start

    def tick(self, tk: float, k: int, n: int, overruns: int) -> None:
        """After step ``k − 1`` (loop time ``tk``): the status line when it is due."""
        now = time.perf_counter()
        if now >= self.next_t:
            r = self.runner
            rate = (k - self.last_k) / (now - self.last_t)
            recent = self.lat_view[self.last_k : k]
            paced = r.plan.mode == "paced"
            assert r.live is not None
            r.live(r._status(tk, k, n, rate, recent, overruns, paced))
            self.last_k, self.last_t = k, now
            self.next_t = now + self.interval

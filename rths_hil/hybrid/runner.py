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

Safety is called once per phase (:class:`Safety`); a fired rule comes back as a
:class:`~rths_hil.safety.Trip` naming the channel, the rule and the values, and the runner then
e-stops **every** channel through its driver (each twin or controller latches and holds),
confirms each latch with one status poll, records the events and returns; the CLI exits with 3.

Modes, pacing and the overrun policy are those of ``docs/loop.md`` (:mod:`.timing`).
"""

from __future__ import annotations

import array
import contextlib
import gc
import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from operator import attrgetter
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..recorder import Recorder, RecordWriteError
from ..safety import OverrunRule, StallRule, Trip
from .channel import Channel
from .phases import Phases, preflight
from .plan import CHANNEL_COLUMNS_A, CHANNEL_COLUMNS_B, CHANNEL_COLUMNS_C, TestPlan
from .timing import CAUSES, LEAD_IN, MIN_SLEEP, attribute_overruns, count_causes, p99

log = logging.getLogger(__name__)

__all__ = ["STOP_SIGNALS", "RunResult", "Runner", "Safety"]

#: Signals that end a run through the operator-stop path (the same as Ctrl-C): every signal
#: whose default action terminates the process and that a terminal, a session manager or an
#: operator sends — a closed terminal or ssh session (SIGHUP) included.
STOP_SIGNALS = tuple(
    getattr(signal, name)
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2")
    if hasattr(signal, name)
)


# ----------------------------------------------------------------------------------------------
# results


@dataclass
class RunResult:
    """What a run did.

    Attributes
    ----------
    status : {"completed", "trip", "operator_stop"}
    steps : int
        Steps executed (rows recorded).
    planned_steps : int
        Steps the configuration asked for.
    trip : Trip or None
        The safety trip (``status == "trip"``) or the operator stop; ``trip.channel`` names
        the channel whose rule fired.
    run_dir : Path
        Where the record is.
    mode : str
        ``paced`` or ``lockstep``.
    fs : float
        Loop rate (Hz).
    wall_time : float
        Wall-clock duration of the stepping (s).
    lateness : ndarray
        Per-step lateness (s); zeros in lockstep.
    overruns : int
        Paced steps later than the overrun threshold.
    missed_replies : int
        Steps without a matching reply (summed over the channels).
    estop_confirmed : bool or None
        Whether every controller reported the e-stop latched (None when no e-stop was sent).
    driver_stats, twin_stats : dict
        Counters of the driver and (if any) the twin; with several channels, one dict per
        channel name.
    final_alpha : float
        α at the end (first channel; differs from the configured one with adaptive
        compensation).
    ready : ndarray
        Paced: per-step time at which the loop was ready to wait for the deadline (previous
        step's work done) minus the deadline (s; < 0: it waited); empty in lockstep.
    overrun_threshold : float
        Lateness above which a paced step is an overrun (s); NaN in lockstep.
    work : ndarray
        Per-step time of the loop's own work (s): from the last reply to the end of the step's
        record (structure, compensation, evaluators, safety, recorder).
    channels : list of str
        Channel names.
    stalls : list of tuple
        Paced: each stall of the bridge itself as ``(step, length in s)``
        (:class:`~rths_hil.safety.StallRule`).
    handback : bool or None
        After a completed run or an operator stop: whether every controller confirmed it was
        disabled and not latched (:mod:`.phases`); None when the run ended in an e-stop.
    start_steps : int
        Steps of the start ramp before step 0 (0: the actuators were already at the first
        command, or offset mode).
    """

    status: str
    steps: int
    planned_steps: int
    trip: Trip | None
    run_dir: Path
    mode: str
    fs: float
    wall_time: float
    lateness: np.ndarray
    overruns: int
    missed_replies: int
    estop_confirmed: bool | None
    driver_stats: dict = field(default_factory=dict)
    twin_stats: dict = field(default_factory=dict)
    final_alpha: float = math.nan
    ready: np.ndarray = field(default_factory=lambda: np.zeros(0))
    overrun_threshold: float = math.nan
    work: np.ndarray = field(default_factory=lambda: np.zeros(0))
    channels: list = field(default_factory=list)
    stalls: list = field(default_factory=list)
    handback: bool | None = None
    start_steps: int = 0

    @property
    def exit_code(self) -> int:
        """0 completed, 3 safety trip, 130 operator stop."""
        return {"completed": 0, "trip": 3, "operator_stop": 130}[self.status]

    @property
    def steps_per_second(self) -> float:
        """Steps per wall-clock second."""
        return self.steps / self.wall_time if self.wall_time > 0 else math.nan

    def overrun_causes(self) -> dict[str, int]:
        """Overruns per cause (:func:`~rths_hil.hybrid.timing.attribute_overruns`).

        Keys ``machine``, ``machine_backlog``, ``work``, ``work_backlog``; they add up to
        :attr:`overruns`. All zero in lockstep.
        """
        if self.mode != "paced" or self.ready.size != self.steps:
            return {name: 0 for name in CAUSES[1:]}
        cause = attribute_overruns(self.lateness[: self.steps], self.ready, self.overrun_threshold)
        return count_causes(cause)

    def lateness_stats(self) -> dict[str, float]:
        """p50, p99, p99.9 and max lateness (s) and the overrun count."""
        lat = self.lateness[: self.steps]
        if lat.size == 0:
            return {
                "p50": math.nan,
                "p99": math.nan,
                "p99.9": math.nan,
                "max": math.nan,
                "overruns": 0,
            }
        p50, p99_, p999 = np.percentile(lat, [50, 99, 99.9])
        return {
            "p50": float(p50),
            "p99": float(p99_),
            "p99.9": float(p999),
            "max": float(lat.max()),
            "overruns": int(self.overruns),
        }


# ----------------------------------------------------------------------------------------------
# safety, one call per phase


class Safety:
    """The safety rules of every channel, asked once per phase of a step.

    Each channel has its own :class:`~rths_hil.safety.SafetyMonitor` (its limits, watchdog,
    sequence, stuck sensor, FEI and Kalman rules); the overrun rule belongs to the loop. Every
    method returns the first fired :class:`~rths_hil.safety.Trip` (stamped with time, step and
    channel) or ``None``.
    """

    def __init__(self, channels: list[Channel], overrun: OverrunRule | None) -> None:
        self.channels = channels
        self.overrun = overrun
        self.tripped: Trip | None = None
        if len(channels) == 1:  # the same checks without the loop over channels (≈ 0.5 µs)
            self._ch = channels[0]
            self._check_feedback = channels[0].monitor.check_feedback
            self._check_command = channels[0].monitor.check_command
            self.feedback = self._feedback_one
            self.command = self._command_one

    def _feedback_one(self, t: float, k: int) -> Trip | None:
        ch = self._ch
        trip = self._check_feedback(t, k, ch.ok, k, ch.seq_rx, ch.status, ch.c, ch.meas, ch.force)
        return None if trip is None else self._fire(trip, ch, t, k)

    def _command_one(self, t: float, k: int) -> Trip | None:
        ch = self._ch
        trip = self._check_command(t, k, ch.x_next, ch.v, ch.c_next)
        return None if trip is None else self._fire(trip, ch, t, k)

    def _fire(self, trip: Trip, ch: Channel | None, t: float, k: int) -> Trip:
        trip = trip.at(t, k) if trip.step < 0 else trip
        why = getattr(ch.driver, "fault_text", None) if ch is not None else None
        if trip.rule == "controller" and why is not None and why():  # e.g. a CANopen EMCY code
            trip = Trip(trip.rule, f"{trip.reason}; {why()}", trip.time, trip.step, trip.values)
        self.tripped = trip.on(ch.name) if ch is not None else trip
        return self.tripped

    @property
    def rules(self) -> dict[str, list[str]] | list[str]:
        """Active rules (per channel when there are several)."""
        extra = ["overrun"] if self.overrun is not None else []
        if len(self.channels) == 1:
            return self.channels[0].monitor.rules + extra
        out = {ch.name: ch.monitor.rules for ch in self.channels}
        if extra:
            out[""] = extra
        return out

    def command(self, t: float, k: int) -> Trip | None:
        """Before sending: each channel's next target, its velocity and its command."""
        for ch in self.channels:
            trip = ch.monitor.check_command(t, k, ch.x_next, ch.v, ch.c_next)
            if trip is not None:
                return self._fire(trip, ch, t, k)
        return None

    def feedback(self, t: float, k: int) -> Trip | None:
        """After the replies: watchdog, sequence, controller status, NaN, limits, stuck."""
        for ch in self.channels:
            trip = ch.monitor.check_feedback(
                t, k, ch.ok, k, ch.seq_rx, ch.status, ch.c, ch.meas, ch.force
            )
            if trip is not None:
                return self._fire(trip, ch, t, k)
        return None

    def evaluators(self, t: float, k: int) -> Trip | None:
        """New FEI windows and Kalman estimates of each channel."""
        for ch in self.channels:
            if ch.fei_new:
                trip = ch.monitor.check_fei(t, k, ch.a_fei, ch.d_fei, ch.v_fei)
                if trip is not None:
                    return self._fire(trip, ch, t, k)
            if ch.kal_new:
                trip = ch.monitor.check_kalman(t, k, ch.kf_g, ch.kf_d)
                if trip is not None:
                    return self._fire(trip, ch, t, k)
        return None

    def timing(self, t: float, k: int, over: bool, lateness: float) -> Trip | None:
        """A paced step's overrun flag and lateness (the loop's rule, no channel)."""
        rule = self.overrun
        if rule is None:
            return None
        trip = rule.check(over, lateness)
        return None if trip is None else self._fire(trip, None, t, k)

    def margin(self) -> tuple[str, str, float]:
        """The channel nearest to a limit: ``(channel, quantity, unused fraction)``."""
        best = ("", "none", math.inf)
        for ch in self.channels:
            q, m = ch.monitor.margin(ch.pk_disp, ch.pk_vel, ch.pk_force)
            if m < best[2]:
                best = (ch.name, q, m)
        return best


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
        self.stop_signal: str | None = None

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

    def _install_signals(self, stack: contextlib.ExitStack) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def handler(signum, frame):
            if self.stop_signal is not None:  # second Ctrl-C: give up at once
                raise KeyboardInterrupt
            self.stop_signal = signal.Signals(signum).name

        for sig in STOP_SIGNALS:
            old = signal.signal(sig, handler)
            stack.callback(signal.signal, sig, old)

    def run(self) -> RunResult:
        """Run the test; return a :class:`RunResult` (never raises on a safety trip)."""
        plan = self.plan
        cfg = plan.cfg
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
            rec = Recorder(
                plan.run_dir,
                plan.fs,
                config=cfg.as_dict(),
                flush_interval=cfg["output"]["flush_interval"],
                columns=plan.columns,
                extra_meta={
                    "config_source": cfg.source,
                    "mode": plan.mode,
                    "planned_steps": plan.n_steps,
                    "ground_motion": {
                        "name": plan.ground_motion.name,
                        "source": plan.ground_motion.source,
                        "pga": plan.ground_motion.pga,
                    },
                    "driver": first.plan.driver_name,
                    "twin": first.twin.connection if first.twin is not None else None,
                    "window_s": first.plan.window_s,
                    "fei_pair": first.plan.fei_pair,
                    "n_dof": plan.n_dof,
                    "channels": [
                        {
                            "name": ch.name,
                            "suffix": ch.suffix,
                            "transform": ch.row,
                            "driver": ch.plan.driver_name,
                            "twin": ch.twin.connection if ch.twin is not None else None,
                            "window_s": ch.plan.window_s,
                            "fei_pair": ch.plan.fei_pair,
                        }
                        for ch in self.channels
                    ],
                },
            )
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
            # a new run on each controller: restart its sequence count, acknowledge a latch
            replies = []
            for ch in self.channels:
                armed = ch.driver.arm(max(plan.timeout, 0.5), ch.receive)
                replies.append(armed)
                rec.event(
                    "arm", 0.0, 0, channel=ch.name, replied=armed is not None,
                    status=None if armed is None else int(armed.status),
                )  # fmt: skip
            # from where each actuator is to step 0 (a ramp, or an offset), see .phases
            phases = Phases(self, rec)
            try:
                trip0 = phases.start(replies)
            except InputError as exc:
                rec.event("refused", 0.0, 0, reason=str(exc))
                raise
            except BaseException:
                self._estop_on_error(rec, 0)
                raise
            if trip0 is None:
                result = self._loop(rec)
            else:
                result = self._not_started(trip0)
                rec.event("trip", **{k: v for k, v in trip0.as_event().items() if k != "kind"})
            result.start_steps = phases.shift
            if result.status in ("completed", "operator_stop"):
                # back to rest (or hold) and hand the controllers back disabled
                try:
                    trip1 = phases.end(result)
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
                stalls=_stall_summary(result.stalls),
                estop_confirmed=result.estop_confirmed,
                driver_stats=result.driver_stats,
                twin_stats=result.twin_stats,
                final_alpha=result.final_alpha,
                handback=result.handback,
                start_steps=result.start_steps,
                exact_windows=first.exact.windows if first.exact is not None else 0,
            )
        self.result = result
        return result

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
            final_alpha=self.channels[0].comp.alpha,
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
                status=ch._estop_status,
            )
        return confirmed

    # ------------------------------------------------------------------------------------------
    def _loop(self, rec: Recorder) -> RunResult:
        plan = self.plan
        n = plan.n_steps
        dt = plan.dt
        paced = plan.mode == "paced"
        # a memoryview of the plan's float64 array: Python floats on indexing, no copy (an
        # hour at 4096 Hz is 118 MB; a list would be 32 B per sample)
        ag = memoryview(np.ascontiguousarray(plan.ag, dtype=float))
        chans = self.channels
        n_ch = len(chans)
        multi = n_ch > 1
        safety = self.safety
        st = plan.structure
        n_dof = st.n_dof
        st_step = st.step
        st_v, st_r = st, st  # read .v / .r after each commit
        unit = all(ch.dof >= 0 for ch in chans)
        dofs = [ch.dof for ch in chans]

        write_row = _row_writer(rec, chans, multi, n_dof, st)
        if rec.dtype.names != tuple(c[0] for c in plan.columns):  # pragma: no cover
            raise AssertionError("record columns differ from the plan's")

        check_feedback = safety.feedback
        check_command = safety.command
        check_evaluators = safety.evaluators
        check_timing = safety.timing
        warm_min = min(ch.warm for ch in chans)
        timeout = plan.timeout
        spin = plan.spin
        min_sleep = MIN_SLEEP * dt
        thr = plan.overrun_threshold
        hb_steps = plan.heartbeat_steps
        stall_rule = self.stall
        min_stall = stall_rule.min_stall if stall_rule is not None else math.inf
        slip = plan.after_stall == "slip"
        stalls: list[tuple[int, float]] = []
        perf = time.perf_counter
        sleep = time.sleep
        nan = math.nan
        del warm_min

        # lateness in a C double array: the console's p99 reads it as an ndarray without a copy
        # paced: lateness in a C double array (the console's p99 reads it as an ndarray without
        # a copy); lockstep: none (zero by definition, see the result below)
        lat_list = array.array("d", [0.0]) * n if paced else None  # no n-byte temporary
        lat_view = np.frombuffer(lat_list, dtype=float) if paced else np.zeros(0)
        work_list = array.array("d", [0.0]) * n
        ready_list = [0.0] * n if paced else None
        console = plan.console_interval if self.live is not None else 0.0
        next_console = math.inf

        # state of step 0 (an external structure, e.g. an OpenSees site, first gets the runner)
        if hasattr(st, "attach"):
            st.attach(self)
        xs = st.reset()
        for ch in chans:
            ch.x_t = xs[ch.dof] if ch.dof >= 0 else _dot(ch.row, xs)
            ch.comp.reset(ch.x_t)
            ch.alpha = ch.comp.alpha
            ch.c = ch.comp_step(ch.x_t)
            ch.x_next, ch.c_next = ch.x_t, ch.c
            ch.v = st.v[ch.dof] if ch.dof >= 0 else _dot(ch.row, st.v)
        trip = check_command(0.0, 0)
        for ch in chans:
            ch.last_command = ch.c
        overruns = 0
        missed = 0
        status = "completed"
        k = 0
        lat = 0.0
        skew = nan
        was_over = False
        old_switch = sys.getswitchinterval()
        gc_was = gc.isenabled()
        if paced:
            sys.setswitchinterval(1e-4)
        gc.collect()
        gc.disable()
        t_start = perf()
        t0 = t_start + (LEAD_IN if paced else 0.0)
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
                            if slip:  # shift the time base: step k is on time from here
                                t0 += lat
                                rec.event("clock", tk, k, wall_t0=time.time() - tk, slip=lat)
                        elif not slip:
                            now = self._catch_up_spacing(now, prev_send)
                            lat = now - deadline
                    for ch in chans:
                        ch.send(k, ch.c, True)
                    prev_send = now
                    lat_list[k] = lat
                else:
                    for ch in chans:
                        ch.send(k, ch.c, True)
                    now = perf()
                # ---- every channel's reply --------------------------------------------------
                t_lim = now + timeout
                t_first = t_last = 0.0
                for ch in chans:
                    rem = t_lim - perf() if multi else timeout
                    fb = ch.receive(rem if rem > 0.0 else 0.0)
                    t = ch.t_rx = perf()
                    t -= now
                    if fb is not None:
                        ch.ok = True
                        ch.meas = fb.displacement
                        ch.force = fb.force
                        ch.seq_rx = fb.seq
                        ch.status = fb.status
                        ch.fb_time = t
                        if t > t_last:
                            t_last = t
                        if t_first == 0.0 or t < t_first:
                            t_first = t
                    else:
                        ch.ok = False
                        ch.seq_rx = -1
                        ch.status = 0
                        ch.fb_time = nan
                        ch.missed += 1
                        missed += 1
                t_work = perf()
                if multi:
                    skew = t_last - t_first if t_first > 0.0 else nan
                trip = check_feedback(tk, k)
                if hb_steps and k % hb_steps == 0:
                    for ch in chans:
                        ch.heartbeat()
                # ---- structure: commit step k with the measured forces, next targets ---------
                if trip is None:
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
                    v_d, r_d = st_v.v, st_r.r
                    for ch in chans:
                        d = ch.dof
                        if d >= 0:
                            ch.x_next = x_next[d]
                            ch.v = v_d[d]
                            ch.r = r_d[d]
                        else:
                            ch.x_next = _dot(ch.row, x_next)
                            ch.v = _dot(ch.row, v_d)
                            ch.r = _dot(ch.row, r_d)
                        ch.alpha = ch.comp.alpha
                        ch.c_next = ch.comp_step(ch.x_next)
                    trip = check_command(tk, k)
                    if st.finished and trip is None:
                        trip = getattr(st, "trip", None)  # an external structure's fault
                        if trip is None:
                            n = k + 1  # the structure ends the test after this step
                else:
                    x_next = xs
                    for ch in chans:
                        ch.x_next, ch.c_next = ch.x_t, ch.c
                # ---- evaluators -------------------------------------------------------------
                for ch in chans:
                    ch.evaluate(k)
                if trip is None:
                    trip = check_evaluators(tk, k)
                if paced:
                    over = lat > thr
                    if over:
                        overruns += 1
                    # the rule counts consecutive overruns: nothing to tell it while none
                    if (over or was_over) and trip is None:
                        trip = check_timing(tk, k, over, lat)
                    was_over = over
                # ---- record row k (columns by name, see plan.record_columns) ----------------
                write_row(tk, k, ag[k], lat, skew, xs)
                for ch in chans:
                    if console:  # peaks, for the console's safety margin only
                        a = ch.x_t
                        if a < 0:
                            a = -a
                        if a > ch.pk_disp:
                            ch.pk_disp = a
                        a = ch.v
                        if a < 0:
                            a = -a
                        if a > ch.pk_vel:
                            ch.pk_vel = a
                        a = ch.force
                        if a < 0:
                            a = -a
                        if a > ch.pk_force:
                            ch.pk_force = a
                    ch.last_command = ch.c
                    ch.x_t = ch.x_next
                    ch.c = ch.c_next
                xs = x_next
                work_list[k] = perf() - t_work
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
                ch.last_command = ch.c
            k += 1  # step k was sent and answered; only its row is lost
        except BaseException:
            for ch in chans:
                ch.estop()
            rec.event("error", k * dt, k, error=repr(sys.exc_info()[1]))
            raise
        finally:
            sys.setswitchinterval(old_switch)
            if gc_was:
                gc.enable()
        del unit, dofs
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
            final_alpha=chans[0].comp.alpha,
            ready=ready,
            overrun_threshold=thr if paced else math.nan,
            work=np.frombuffer(work_list, dtype=float)[:k],
            channels=[ch.name for ch in chans],
            stalls=stalls,
        )

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
        log.warning("the bridge stalled for %.1f ms before step %d (%s)", length * 1e3, k, action)
        return None if trip is None else self.safety._fire(trip, None, tk, k)

    def _catch_up_spacing(self, now: float, prev_send: float) -> float:
        """Catch-up after a stall: wait until no channel's command moves faster (in wall-clock
        time, from the previous send) than its velocity limit allows; return the send time."""
        need = 0.0
        for ch in self.channels:
            lim = ch.monitor.vel_limit
            if lim != math.inf:
                need = max(need, abs(ch.c - ch.last_command) / lim)
        perf = time.perf_counter
        while now < prev_send + need:
            now = perf()
        return now

    def _status(self, tk, k, n, rate, recent, overruns, paced) -> dict:
        """The console's status dict: the worst channel (nearest a limit) and its FEI."""
        name, quantity, margin = self.safety.margin()
        ch = next((c for c in self.channels if c.name == name), self.channels[0])
        if len(self.channels) > 1 and margin == math.inf:  # no limits: the largest |FEI delay|
            ch = max(self.channels, key=lambda c: abs(c.d_fei) if c.d_fei == c.d_fei else -1.0)
        return {
            "t": tk,
            "k": k,
            "n": n,
            "rate": rate,
            "p99_lateness": p99(recent) if paced and recent.size else 0.0,
            "overruns": overruns,
            "channel": ch.name,
            "amplitude": ch.a_fei,
            "delay": ch.d_fei,
            "valid": ch.v_fei,
            "peak_displacement": ch.pk_disp,
            "margin": (quantity, margin),
            "alpha": ch.comp.alpha,
            "mode": self.plan.mode,
        }


def _row_writer(rec: Recorder, chans: list[Channel], multi: bool, n_dof: int, st=None):
    """``write(t, k, ag, lateness, skew, dofs)``: one record row, each column read by name.

    The plan's column list (:func:`rths_hil.hybrid.plan.record_columns`) names each channel
    column after a :class:`Channel` attribute (:data:`~rths_hil.hybrid.plan.CHANNEL_COLUMNS_A`
    …); an :func:`operator.attrgetter` per group reads them in column order. One channel on
    one DOF gets a writer without an intermediate list (≈ 1 µs less per step). A structure
    stage's own ``record_columns`` (the plan appends them last) are read from ``st`` into the
    same row; a stage without them costs nothing.
    """
    append = rec.append
    extra = [c[1] for c in getattr(st, "record_columns", ())]
    if extra:
        get_x = attrgetter(*extra, *extra[:1])  # ≥ 2 names: a tuple; one too many if one
        nx = len(extra)
        rec_append = rec.append

        def append(*row):
            rec_append(*row, *get_x(st)[:nx])

    get_a = attrgetter(*(a for _, a in CHANNEL_COLUMNS_A))
    get_b = attrgetter(*(a for _, a in CHANNEL_COLUMNS_B), "ok")  # ≥ 2 names: a tuple
    nb = len(CHANNEL_COLUMNS_B)
    get_c = attrgetter(*(c[1] for c in CHANNEL_COLUMNS_C))
    if not multi and n_dof == 1:
        (ch,) = chans

        def write(t, k, ag, lat, skew, dofs):
            append(t, k, ag, *get_a(ch), lat, *get_b(ch)[:nb], k, *get_c(ch))

        return write

    def write_many(t, k, ag, lat, skew, dofs):
        row = [t, k, ag]
        for ch in chans:
            row += get_a(ch)
        row.append(lat)
        for ch in chans:
            row += get_b(ch)[:nb]
        row.append(k)
        for ch in chans:
            row += get_c(ch)
        if multi:
            row.append(skew)
        if n_dof > 1:
            row += dofs
        append(*row)

    return write_many


def _stall_summary(stalls: list) -> dict:
    """Count, longest and total of a run's stalls (s), for the end event and the summary."""
    lengths = [s for _, s in stalls]
    return {
        "count": len(lengths),
        "longest": max(lengths, default=0.0),
        "total": sum(lengths),
    }


def _dot(row: list[float], x) -> float:
    """T-row · vector for short rows (plain floats)."""
    s = 0.0
    for r, v in zip(row, x, strict=False):
        if r:
            s += r * v
    return s


def check_input(plan: TestPlan) -> None:  # pragma: no cover - kept for symmetry
    """Nothing to check at run time that the plan has not checked."""
    if not plan.channels:
        raise InputError("a test needs at least one channel")

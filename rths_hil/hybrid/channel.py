"""One actuator channel at run time: its driver (and twin), compensator, evaluators and rules.

A :class:`Channel` is built from a :class:`~rths_hil.hybrid.plan.ChannelPlan` and opened by the
runner. It holds the channel's state of the current step as plain attributes named after the
record's columns (:func:`rths_hil.records.columns.channel_columns`: ``target``, ``command``,
``measured``, ``force`` … are read by name into each row), and does the per-channel work that
needs no other channel: sending, receiving (serving an inline twin first), the evaluators and
the e-stop with its confirmation poll.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from rths_hil.drivers.base import Driver, Status

from ..compensators.base import Compensator
from ..errors import InputError
from ..fei import OnlineFEI
from ..stability import StabilityIndicator
from .evaluators import ExactFEI, StreamingFEI
from .plan import ChannelPlan

log = logging.getLogger(__name__)

__all__ = ["Channel", "step_mixed"]

_ESTOP = int(Status.ESTOP_ACTIVE)


def _unbound(*_: Any) -> Any:
    """A channel's driver call before :meth:`Channel.bind`."""
    raise RuntimeError("the channel has no driver yet (bind() first)")


def _no_heartbeat() -> None:
    """No heartbeat before :meth:`Channel.bind` (nothing to keep alive)."""


class Channel:
    """An actuator channel of a running test (see the module docstring).

    The step's state has the names of the record's channel columns (the trial values the
    structure asks for, the values the controller measured, the evaluators' estimates).

    Attributes
    ----------
    name, suffix : str
        Channel name and record-column suffix.
    dof : int
        0-based DOF for a unit transform row, else -1 (then :attr:`row` is used).
    row : list of float
        Row of T.
    driver : Driver
        Open driver (after :meth:`open`).
    twin : TwinEndpoint or None
        The running twin endpoint, kept after the run for inspection.
    control : str
        ``control.mode``: ``displacement``, ``force`` or ``load``; :attr:`force_mode` is true
        for the latter two (the wire mode is force).
    target, command : float
        This step's trial displacement from the structure (T·u, m) and the command sent for
        it after compensation (m). A force channel's are its target force and force set-point
        (N, :meth:`force_target`), a load channel's its load (N).
    trial, trial_next : float
        A force channel's trial displacement from the structure along it (m), this step's
        and the next (:func:`step_mixed`; recorded as ``trial``).
    k_force : float
        A force channel's assumed specimen stiffness (N/m, ``structure.k_specimen``).
    target_next, command_next : float
        The same for the next step, computed before its deadline.
    measured, force : float
        The controller's reply: measured displacement (m, held without a reply) and force (N).
    velocity, restoring_force : float
        Velocity (m/s) and numerical restoring force (N) of the structure along the actuator.
    alpha : float
        Compensation α of this step's command.
    fei_amplitude, fei_delay, fei_f_eq, fei_valid : float, float, float, bool
        Latest streaming FEI window (the FEI paper's A, d and f_eq).
    fei_exact_amplitude, fei_exact_delay, fei_exact_valid, fei_exact_step
        Latest exact FEI window and the step it ended at (-1: none yet).
    kf_gain, kf_delay : float
        Kalman estimates of the actuator's gain and delay (s).
    feedback_ok : bool
        A reply with the right sequence number arrived in time this step.
    feedback_time : float
        Time from the step's first send to this channel's reply (s; NaN without a reply).
    reply_seq, reply_status : int
        Sequence number and controller status word of this step's reply (-1, 0 without one).
    missed_replies : int
        Steps without a reply so far (each one a held measurement).
    link_down : str or None
        Set at a missed reply: why the driver's transport is gone (its
        :attr:`~rths_hil.drivers.base.Driver.link_down`), or ``None`` (a missed reply only).
    gap_steps, gap_start : int
        The reply gap under way: missed replies so far and the step of the first (0, -1: none).
    ok_clock : float
        When the last good reply came (perf_counter s).
    gaps, longest_gap, longest_gap_steps : int, float, int
        Reply gaps that ended so far; the longest one's silence (s, from the good reply before
        it to the one that ended it) and its missed replies.
    fei_held : float
        Share of held samples (missed replies) in the streaming FEI window ending at this step.
    stability : float
        The energy stability indicator S of the window ending at this step (NaN: not valid;
        :mod:`rths_hil.stability`).
    stability_ind : StabilityIndicator or None
        Its online evaluator (None: ``safety.stability = "off"``).
    estop_confirmed : bool or None
        After :meth:`confirm_estop`: whether the controller reported the e-stop latched.
    """

    # slots: the runner reads and writes these attributes every step; slot access is
    # measurably faster than an instance dict of this size
    __slots__ = (
        "_estop_status",
        "adaptive",
        "alpha",
        "command",
        "command_next",
        "compensate",
        "compensator",
        "compensator_observe",
        "control",
        "dof",
        "driver",
        "dt",
        "estop_confirmed",
        "exact_fei",
        "feedback_ok",
        "feedback_time",
        "fei_amplitude",
        "fei_delay",
        "fei_exact_amplitude",
        "fei_exact_delay",
        "fei_exact_step",
        "fei_exact_valid",
        "fei_f_eq",
        "fei_held",
        "fei_new",
        "fei_on_target",
        "fei_valid",
        "force",
        "force_mode",
        "fs",
        "gap_start",
        "gap_steps",
        "gaps",
        "heartbeat",
        "k_force",
        "kalman",
        "kalman_every",
        "kalman_new",
        "kalman_on_target",
        "kf_delay",
        "kf_gain",
        "last_command",
        "link_down",
        "load",
        "longest_gap",
        "longest_gap_steps",
        "measured",
        "missed_replies",
        "monitor",
        "name",
        "ok_clock",
        "peak_displacement",
        "peak_force",
        "peak_velocity",
        "plan",
        "receive",
        "reply_clock",
        "reply_seq",
        "reply_status",
        "restoring_force",
        "row",
        "send",
        "stability",
        "stability_ind",
        "stream_fei",
        "suffix",
        "target",
        "target_next",
        "trial",
        "trial_next",
        "twin",
        "velocity",
        "warmup_steps",
    )

    def __init__(self, plan: ChannelPlan, fs: float) -> None:
        self.plan = plan
        self.name = plan.name
        self.suffix = plan.suffix
        self.row = plan.row.tolist()
        self.dof = plan.dof
        self.fs = fs
        self.compensator = plan.compensator
        self.compensate = plan.compensator.step
        # a compensator that learns from the replies (ats, model feedback) observes each one
        observe = type(plan.compensator).observe
        self.compensator_observe = (
            None if observe is Compensator.observe else plan.compensator.observe
        )
        self.adaptive = plan.adaptive
        self.control = plan.control
        self.force_mode = plan.control != "displacement"
        self.k_force = plan.k_force
        self.load = plan.load
        self.dt = 1.0 / fs
        self.trial = self.trial_next = 0.0
        self.kalman = plan.kalman
        self.monitor = plan.monitor
        self.stream_fei = StreamingFEI(fs, plan.window_s) if plan.fei_enabled else None
        self.exact_fei: ExactFEI | None = None
        self.twin: Any = None
        self.driver: Driver | None = None
        self.fei_on_target = plan.fei_pair == "target"
        self.kalman_on_target = plan.kalman_pair == "target"
        self.kalman_every = plan.kalman_every
        self.warmup_steps = plan.warmup_steps
        nan = math.nan
        # state of the current step
        self.target = self.command = self.target_next = self.command_next = 0.0
        self.measured = self.force = self.velocity = self.restoring_force = 0.0
        self.alpha = self.compensator.alpha
        self.feedback_ok = False
        self.feedback_time = nan
        self.reply_seq = -1
        self.reply_status = 0
        self.fei_amplitude = self.fei_delay = self.fei_f_eq = nan
        self.fei_valid = False
        self.fei_exact_amplitude = self.fei_exact_delay = nan
        self.fei_exact_valid = False
        self.fei_exact_step = -1
        self.kf_gain = self.kf_delay = nan
        self.fei_new = False
        self.kalman_new = False
        self.missed_replies = 0
        self.link_down: str | None = None
        self.gap_steps = 0
        self.gap_start = -1
        self.ok_clock = nan
        self.gaps = 0
        self.longest_gap = 0.0
        self.longest_gap_steps = 0
        self.fei_held = 0.0
        self.stability = nan
        self.stability_ind = (
            StabilityIndicator(
                fs, plan.stability_window, plan.stability_damping, plan.stability_min_velocity
            )
            if plan.stability_damping > 0 and plan.monitor.stability is not None
            else None
        )
        self.peak_displacement = self.peak_velocity = self.peak_force = 0.0
        self.last_command = 0.0
        self.estop_confirmed: bool | None = None
        self._estop_status: int | None = None
        # the driver's hot-path calls, bound by bind()
        self.send: Callable[[int, float, bool], None] = _unbound
        self.receive: Callable[[float], Any] = _unbound
        self.heartbeat: Callable[[], None] = _no_heartbeat
        # the time this channel's receive returned (perf_counter): its watchdog measures the
        # time between its own replies, not the time other channels' waits took
        self.reply_clock = 0.0
        wd = plan.monitor.watchdog
        if wd is not None and getattr(wd, "timeout", None) is not None:
            wd.clock = self._rx_clock

    def _rx_clock(self) -> float:
        return self.reply_clock

    # ------------------------------------------------------------------------------------------
    # opening

    def open(self, stack: contextlib.ExitStack, background_exact: bool) -> None:
        """Start the twin (if any), open the driver and the exact-FEI evaluator."""
        plan = self.plan
        cfg = plan.cfg
        where = cfg.source + (f": actuators.{self.name}" if self.name else "")
        name = plan.driver_name
        conn = dict(plan.connection)
        if plan.twin_enabled:
            from rths_hil.sim_backends.twin import start_twin

            # Over the in-process virtual CAN bus, serve the twin from the loop thread (same
            # frames, codecs and controller; no thread hand-off and GIL contention per step).
            try:
                self.twin = start_twin(
                    name,
                    plan.plant,
                    faults=plan.faults,
                    threaded=not plan.twin_inline,
                    heartbeat_timeout=plan.twin_watchdog,
                    initial_position=cfg["twin"]["initial_position"],
                    **conn,
                )
            except InputError as exc:
                raise InputError(f"{where}: driver.connection: {exc}") from None
            stack.callback(self.twin.stop)
            conn = dict(self.twin.connection)
        from rths_hil.drivers.registry import create_driver

        try:
            driver = create_driver(name, **conn)
        except InputError as exc:
            raise InputError(f"{where}: driver: {exc}") from None
        except TypeError as exc:
            raise InputError(f"{where}: driver.connection: {exc}") from None
        set_control = getattr(driver, "set_control", None)
        if set_control is not None:  # the wire mode, once, before open (a load is a force)
            try:
                set_control(plan.wire_control)
            except InputError as exc:
                raise InputError(f"{where}: control.mode = {self.control!r}: {exc}") from None
        driver.open()
        stack.callback(driver.close)
        stack.callback(driver.stop_reader)  # before close: a reader thread stops first
        self.bind(driver)
        if self.stream_fei is not None and plan.exact_hop > 0:
            self.exact_fei = ExactFEI(self.fs, plan.window_s, plan.exact_hop, background_exact)
            stack.callback(self.exact_fei.close)

    def bind(self, driver: Driver) -> None:
        """Use ``driver`` (open) for this channel; bind its hot-path methods."""
        self.driver = driver
        self.send = driver.send
        self.heartbeat = driver.heartbeat
        self.receive = self._receiver(driver)

    def _receiver(self, driver: Driver):
        """``driver.receive``, preceded by serving an inline twin (lockstep over virtual CAN)."""
        twin = self.twin
        if twin is None or not getattr(twin, "inline", False):
            return driver.receive
        pump, recv = twin.pump, driver.receive
        perf = time.perf_counter

        def receive(timeout: float):
            pump()
            if twin._held is None:
                return recv(timeout)
            # the twin holds a delayed reply (a stalled controller): wait for it in slices,
            # serving the twin between them, so the reply comes when it would from a thread
            end = perf() + timeout
            while True:
                fb = recv(min(0.001, max(0.0, end - perf())))
                if fb is not None or perf() >= end:
                    return fb
                pump()

        return receive

    def warm_up(self) -> None:
        """Compile and touch the evaluators on throwaway instances before the clock starts.

        The streaming FEI kernel is numba-compiled on its first call (hundreds of ms) and the
        exact FEI's FFT plans are built on first use; neither may happen at a deadline.
        """
        if self.stream_fei is None:
            return
        tmp = StreamingFEI(self.fs, self.plan.window_s)
        for i in range(4):
            tmp.push(math.sin(i), math.cos(i))
        hop = self.plan.exact_hop
        if hop > 0:
            ex = OnlineFEI(self.fs, self.plan.window_s, hop=hop, method="exact")
            t = np.arange(self.stream_fei.N + hop) / self.fs
            ex.update(np.sin(6.0 * t), np.sin(6.0 * t - 0.1))

    # ------------------------------------------------------------------------------------------
    # per step

    def evaluate(self, k: int) -> None:
        """Streaming FEI (every sample), exact FEI (every hop), Kalman, stability; adaptive α.

        A held measurement (no reply this step, :attr:`feedback_ok` false) is counted in the
        streaming window's share of held samples (:attr:`fei_held`) and is no measurement
        update of the Kalman filter. Sets :attr:`fei_new` / :attr:`kalman_new` when a new
        estimate is there for the rules.
        """
        # the tracked quantity: the measured force of a force-controlled channel
        meas = self.force if self.force_mode else self.measured
        ok = self.feedback_ok
        if self.compensator_observe is not None and ok:
            self.compensator_observe(self.target, self.command, meas)
        stream = self.stream_fei
        self.fei_new = False
        if stream is not None:
            x = self.target if self.fei_on_target else self.command
            done = stream.push(x, meas, not ok)
            self.fei_held = stream.held / stream.N
            if done:
                latest = stream.latest
                self.fei_amplitude, self.fei_delay, self.fei_f_eq, self.fei_valid = latest
                if self.adaptive is not None:
                    self.adaptive.update(latest[1], latest[3])
                self.fei_new = k >= self.warmup_steps
            ex = self.exact_fei
            if ex is not None:
                ex.push(x, meas)
                if ex.end_step != self.fei_exact_step:  # a new exact window came back
                    a, d, _, valid = ex.latest
                    self.fei_exact_amplitude, self.fei_exact_delay, self.fei_exact_valid = (
                        a,
                        d,
                        valid,
                    )
                    self.fei_exact_step = ex.end_step
        kal = self.kalman
        if kal is not None:
            u = self.target if self.kalman_on_target else self.command
            # a held measurement (no reply) is never a measurement update of the filter
            if self.kalman_every == 1:
                self.kf_gain, self.kf_delay = kal.update(u, meas, ok)
                new = True
            else:
                kal.push(u, meas, ok)
                kal.predict()
                new = k % self.kalman_every == 0
                if new:
                    kal.correct()
                    self.kf_gain, self.kf_delay = kal.gain, kal.delay
            self.kalman_new = new and k >= self.warmup_steps
        ind = self.stability_ind
        if ind is not None:  # the interface's energy balance of this step (O(1))
            if self.force_mode:  # the interface's displacements: trial and measured
                self.stability = ind.push(self.trial, self.measured, self.force, self.velocity)
            else:
                self.stability = ind.push(self.target, meas, self.force, self.velocity)

    def interface_force(self) -> float:
        """The force this channel returns to the structure for the step just measured (N).

        Displacement: the measured force. Force: the measured force carried to the trial
        displacement along the specimen stiffness the integrator assumes,
        ``F_m + k_s·(d − x_m)`` (``docs/channels.md``). Load: nothing (it acts on no DOF).
        """
        c = self.control
        if c == "force":
            return self.force + self.k_force * (self.trial - self.measured)
        if c == "load":
            return 0.0
        return self.force

    def force_target(self, trial: float, k: int) -> float:
        """The target of step ``k`` for the structure's trial displacement ``trial`` along it.

        Displacement: ``trial`` (m). Force: the force the assumed specimen stiffness needs
        for it, ``k_s·trial`` (N; built from the structure's state alone, so the compensator
        leads a smooth signal and no measurement is fed back through the actuator). Load: the
        schedule's force at step ``k`` (N).
        """
        c = self.control
        if c == "force":
            return self.k_force * trial
        if c == "load":
            load = self.load
            assert load is not None  # a load-controlled channel has its schedule (plan)
            return load.at(k * self.dt)
        return trial

    def keepalive(self) -> None:
        """Heartbeat while no command is due (the controller's watchdog); serve an inline twin.

        For a structure that makes the loop wait (an external analysis): the actuator holds.
        """
        self.heartbeat()
        twin = self.twin
        if twin is not None and getattr(twin, "inline", False):
            twin.pump()

    def restart_watchdog(self) -> None:
        """Restart the feedback watchdog's clock after a wait in which no reply was due."""
        wd = self.monitor.watchdog
        if wd is not None and hasattr(wd, "reset"):
            wd.reset()

    # ------------------------------------------------------------------------------------------
    # stopping

    def estop(self) -> None:
        """Send the e-stop through the driver (never raises)."""
        driver = self.driver
        if driver is not None:
            with contextlib.suppress(Exception):
                driver.estop()
        if self.twin is not None and getattr(self.twin, "inline", False):
            with contextlib.suppress(Exception):
                self.twin.pump()

    @property
    def estop_status(self) -> int | None:
        """Status word of the reply to :meth:`confirm_estop`'s poll (None: no reply or no poll)."""
        return self._estop_status

    def confirm_estop(self, seq: int) -> bool:
        """One status poll: does the controller report the e-stop latched?

        A new command with ``enable=True`` is ignored by a latched controller (it holds
        position) and answered with ESTOP_ACTIVE. ``enable=False`` would acknowledge (clear)
        the latch, so it is not used here. ``seq`` continues the sequence in the loop's
        numbering (sent through :attr:`send`: after a start ramp its :class:`Link` shifts it
        past the ramp's sequence numbers and adds the start offset).
        """
        try:
            self.send(seq, self.last_command, True)
            fb = self.receive(0.2)
        except InputError:
            fb = None
        self.estop_confirmed = fb is not None and bool(fb.status & _ESTOP)
        self._estop_status = None if fb is None else int(fb.status)
        if not self.estop_confirmed:
            log.warning(
                "e-stop sent but not confirmed by the controller of %s", self.name or "the actuator"
            )
        return self.estop_confirmed


def step_mixed(st: Any, k: int, ag: float, chans: list[Channel], n_dof: int) -> list[float]:
    """Commit step ``k`` of a test with force or load channels; set every channel's next target.

    The runner's structure phase when some channel is not displacement-controlled: each channel
    returns its :meth:`Channel.interface_force` along its row of T, the stage commits step ``k``
    and returns the DOF displacements of step ``k + 1``; each channel's trial displacement
    along it becomes its next target (:meth:`Channel.force_target`), compensated. The trial
    displacement of step ``k`` (:attr:`Channel.trial`) is the one this function set as
    ``trial_next`` at step ``k − 1``.

    Force-based substructuring, what the integrator assumes: the CR integration is explicit in
    displacement, so the trial displacement ``d[k+1]`` along a force channel is known before
    its force is measured; the channel asks the specimen for ``k_s·d[k+1]`` and returns
    ``F_m + k_s·(d − x_m)``, with ``k_s`` the specimen stiffness the integrator already assumes
    for its parameter (``structure.k_specimen``). The specimen is taken as close to
    linear-elastic with that stiffness along the actuator over a step, its force a function of
    its displacement (not of the path between steps), its damping and inertia forces small
    beside ``k_s·d`` (measured and returned, not predicted). For a linear specimen of
    stiffness ``k`` the returned force is exactly ``k·d`` when ``k_s = k``, and wrong by
    ``(k − k_s)²·d/k`` otherwise (a force loop of unit gain); docs/channels.md.
    """
    f = [0.0] * n_dof
    for ch in chans:
        ch.trial = ch.trial_next
        fc = ch.interface_force()
        if ch.dof >= 0:
            f[ch.dof] += fc
        else:
            for i, r in enumerate(ch.row):
                f[i] += r * fc
    x_next = st.step(k, ag, f)
    v_d, r_d = st.v, st.r
    for ch in chans:
        d = ch.dof
        if d >= 0:
            x = x_next[d]
            ch.velocity = v_d[d]
            ch.restoring_force = r_d[d]
        else:
            x = _dot(ch.row, x_next)
            ch.velocity = _dot(ch.row, v_d)
            ch.restoring_force = _dot(ch.row, r_d)
        ch.trial_next = x
        ch.target_next = ch.force_target(x, k + 1)
        ch.alpha = ch.compensator.alpha
        ch.command_next = ch.compensate(ch.target_next)
    return x_next


def _dot(row: list[float], x: Any) -> float:
    """T-row · vector for short rows (plain floats; the runner's sum)."""
    s = 0.0
    for r, v in zip(row, x, strict=False):
        if r:
            s += r * v
    return s

"""One actuator channel at run time: its driver (and twin), compensator, evaluators and rules.

A :class:`Channel` is built from a :class:`~rths_hil.hybrid.plan.ChannelPlan` and opened by the
runner. It holds the channel's state of the current step as plain float attributes (the runner
reads and writes them; the record's per-channel columns name them, see
:data:`rths_hil.hybrid.plan.CHANNEL_COLUMNS_A`), and does the per-channel work that needs no
other channel: sending, receiving (serving an inline twin first), the evaluators and the
e-stop with its confirmation poll.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from typing import Any

import numpy as np

from rths_hil.drivers.base import Driver, Status

from ..compensation import Compensator
from ..errors import InputError
from ..fei import OnlineFEI
from .evaluators import ExactFEI, StreamingFEI
from .plan import ChannelPlan

log = logging.getLogger(__name__)

__all__ = ["Channel"]

_ESTOP = int(Status.ESTOP_ACTIVE)


class Channel:
    """An actuator channel of a running test (see the module docstring).

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
    x_t, c, meas, force, v, r, alpha : float
        This step's target, command, measured displacement, measured force, velocity and
        numerical restoring force along the actuator, and compensation α.
    ok : bool
        A reply with the right sequence number arrived in time this step.
    fb_time : float
        Time from the step's first send to this channel's reply (s; NaN without a reply).
    """

    # slots: the runner reads and writes these attributes every step; slot access is
    # measurably faster than an instance dict of this size
    __slots__ = (
        "_estop_status",
        "a_ex",
        "a_fei",
        "adaptive",
        "alpha",
        "c",
        "c_next",
        "comp",
        "comp_observe",
        "comp_step",
        "d_ex",
        "d_fei",
        "dof",
        "driver",
        "estop_confirmed",
        "ex_step",
        "exact",
        "f_fei",
        "fb_time",
        "fei_new",
        "fei_target",
        "force",
        "fs",
        "heartbeat",
        "kal_every",
        "kal_new",
        "kal_target",
        "kalman",
        "kf_d",
        "kf_g",
        "last_command",
        "meas",
        "missed",
        "monitor",
        "name",
        "ok",
        "pk_disp",
        "pk_force",
        "pk_vel",
        "plan",
        "r",
        "receive",
        "row",
        "send",
        "seq_rx",
        "status",
        "stream",
        "suffix",
        "t_rx",
        "twin",
        "v",
        "v_ex",
        "v_fei",
        "warm",
        "x_next",
        "x_t",
    )

    def __init__(self, plan: ChannelPlan, fs: float) -> None:
        self.plan = plan
        self.name = plan.name
        self.suffix = plan.suffix
        self.row = plan.row.tolist()
        self.dof = plan.dof
        self.fs = fs
        self.comp = plan.compensator
        self.comp_step = plan.compensator.step
        # a compensator that learns from the replies (ats, model feedback) observes each one
        observe = type(plan.compensator).observe
        self.comp_observe = None if observe is Compensator.observe else plan.compensator.observe
        self.adaptive = plan.adaptive
        self.kalman = plan.kalman
        self.monitor = plan.monitor
        self.stream = StreamingFEI(fs, plan.window_s) if plan.fei_enabled else None
        self.exact: ExactFEI | None = None
        self.twin: Any = None
        self.driver: Driver | None = None
        self.fei_target = plan.fei_pair == "target"
        self.kal_target = plan.kalman_pair == "target"
        self.kal_every = plan.kalman_every
        self.warm = plan.warmup_steps
        nan = math.nan
        # state of the current step
        self.x_t = self.c = self.x_next = self.c_next = 0.0
        self.meas = self.force = self.v = self.r = 0.0
        self.alpha = self.comp.alpha
        self.ok = False
        self.fb_time = nan
        self.seq_rx = -1
        self.status = 0
        self.a_fei = self.d_fei = self.f_fei = nan
        self.v_fei = False
        self.a_ex = self.d_ex = nan
        self.v_ex = False
        self.ex_step = -1
        self.kf_g = self.kf_d = nan
        self.fei_new = False
        self.kal_new = False
        self.missed = 0
        self.pk_disp = self.pk_vel = self.pk_force = 0.0
        self.last_command = 0.0
        self.estop_confirmed: bool | None = None
        self.send = self.receive = self.heartbeat = None
        # the time this channel's receive returned (perf_counter): its watchdog measures the
        # time between its own replies, not the time other channels' waits took
        self.t_rx = 0.0
        wd = plan.monitor.watchdog
        if wd is not None and getattr(wd, "timeout", None) is not None:
            wd.clock = self._rx_clock

    def _rx_clock(self) -> float:
        return self.t_rx

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
        driver.open()
        stack.callback(driver.close)
        stack.callback(driver.stop_reader)  # before close: a reader thread stops first
        self.bind(driver)
        if self.stream is not None and plan.exact_hop > 0:
            self.exact = ExactFEI(self.fs, plan.window_s, plan.exact_hop, background_exact)
            stack.callback(self.exact.close)

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
        if self.stream is None:
            return
        tmp = StreamingFEI(self.fs, self.plan.window_s)
        for i in range(4):
            tmp.push(math.sin(i), math.cos(i))
        hop = self.plan.exact_hop
        if hop > 0:
            ex = OnlineFEI(self.fs, self.plan.window_s, hop=hop, method="exact")
            t = np.arange(self.stream.N + hop) / self.fs
            ex.update(np.sin(6.0 * t), np.sin(6.0 * t - 0.1))

    # ------------------------------------------------------------------------------------------
    # per step

    def evaluate(self, k: int) -> None:
        """Streaming FEI (every sample), exact FEI (every hop), Kalman; adaptive α.

        Sets :attr:`fei_new` / :attr:`kal_new` when a new estimate is there for the rules.
        """
        meas = self.meas
        if self.comp_observe is not None and self.ok:
            self.comp_observe(self.x_t, self.c, meas)
        stream = self.stream
        self.fei_new = False
        if stream is not None:
            x = self.x_t if self.fei_target else self.c
            if stream.push(x, meas):
                latest = stream.latest
                self.a_fei, self.d_fei, self.f_fei, self.v_fei = latest
                if self.adaptive is not None:
                    self.adaptive.update(latest[1], latest[3])
                self.fei_new = k >= self.warm
            ex = self.exact
            if ex is not None:
                ex.push(x, meas)
                if ex.end_step != self.ex_step:  # a new exact window came back
                    self.a_ex, self.d_ex, _, self.v_ex = ex.latest
                    self.ex_step = ex.end_step
        kal = self.kalman
        if kal is not None:
            u = self.x_t if self.kal_target else self.c
            if self.kal_every == 1:
                self.kf_g, self.kf_d = kal.update(u, meas)
                new = True
            else:
                kal.push(u, meas)
                kal.predict()
                new = k % self.kal_every == 0
                if new:
                    kal.correct()
                    self.kf_g, self.kf_d = kal.gain, kal.delay
            self.kal_new = new and k >= self.warm

    # ------------------------------------------------------------------------------------------
    # stopping

    def estop(self) -> None:
        """Send the e-stop through the driver (never raises)."""
        with contextlib.suppress(Exception):
            self.driver.estop()
        if self.twin is not None and getattr(self.twin, "inline", False):
            with contextlib.suppress(Exception):
                self.twin.pump()

    def confirm_estop(self, seq: int) -> bool:
        """One status poll: does the controller report the e-stop latched?

        A new command with ``enable=True`` is ignored by a latched controller (it holds
        position) and answered with ESTOP_ACTIVE. ``enable=False`` would acknowledge (clear)
        the latch, so it is not used here. ``seq`` continues the sequence (no gap).
        """
        try:
            self.driver.send(seq, self.last_command, True)
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

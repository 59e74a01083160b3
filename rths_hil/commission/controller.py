"""Paced command/reply exchanges with one channel's controller while it is commissioned."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from rths_hil.drivers.base import Feedback, Status

from ..hybrid.pacer import Pacer, ReplyBudget
from ..hybrid.stepio import ENABLED, ESTOP, FAULT, LATCHED, WATCHDOG, StepIO
from ..stopping import OperatorStop

__all__ = [
    "ENABLED",
    "ESTOP",
    "FAULT",
    "LATCHED",
    "WATCHDOG",
    "Controller",
    "last_reply",
    "status_names",
]


class Controller:
    """Paced command/reply exchanges with one channel's controller (sequence after arming).

    Each exchange is the loop's (:class:`~rths_hil.hybrid.stepio.StepIO`: the command, its
    reply within :attr:`timeout`). Every paced motion checks the operator stop once per period
    (:class:`Stopped`); the hand-back's own exchanges do not (``check=False``).
    """

    def __init__(
        self, ch: Any, fs: float, timeout: float, heartbeat_steps: int, stop: OperatorStop
    ) -> None:
        self.ch = ch
        self.drv = ch.driver
        self.recv = ch.receive
        self.dt = 1.0 / fs
        #: one command per period: sleep until 0.3 ms before each deadline, then spin (no
        #: real-time scheduling here, so no forced sleep)
        self.pacer = Pacer(self.dt, 3e-4)
        #: the command and its reply within the timeout
        self.io = StepIO([(self.drv.send, self.recv)], ReplyBudget(self.dt, timeout, False))
        self.hb = heartbeat_steps
        self.stop = stop
        self.seq = 0
        self.last: Feedback | None = None
        #: how late each command of the last :meth:`run` left (s)
        self.lateness = np.zeros(0)
        #: the last command sent: position and enable flag (what the controller is doing)
        self.x = math.nan
        self.enabled = False

    @property
    def timeout(self) -> float:
        """How long a reply is waited for (s)."""
        return self.io.budget.timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self.io.budget.timeout = value

    def arm(self) -> Feedback | None:
        """The driver's arming command: a new run; acknowledges a latch (e-stop, watchdog)."""
        self.seq = 0
        self.enabled = False
        return self.drv.arm(max(self.timeout, 0.5), self.recv)

    def exchange(self, x: float, enable: bool) -> tuple[Feedback | None, float]:
        """One command and its reply: (feedback or None, round trip in s)."""
        self.seq += 1
        io = self.io
        t = time.perf_counter()
        self.x, self.enabled = float(x), bool(enable)
        io.send(self.seq, (self.x,), enable)
        fb = io.collect(t)[0]
        if fb is not None:
            self.last = fb
        return fb, io.clocks[0] - t

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
        self,
        path: np.ndarray,
        enable: bool,
        each: Callable[[int, Feedback | None, float], None],
        check: bool = True,
    ) -> None:
        """One command of ``path`` per period (sleep, then spin to the deadline)."""
        pacer = self.pacer
        pacer.start(lead=0.0)  # the first command a period from now
        self.lateness = late = np.zeros(len(path))
        for i, x in enumerate(path):
            if check:
                self.stop.check()
            late[i] = pacer.wait(i) - pacer.due
            fb, rtt = self.exchange(float(x), enable)
            if self.hb and i % self.hb == 0:
                self.drv.heartbeat()
            each(i, fb, rtt)

    def hold(
        self, x: float, seconds: float, enable: bool, check: bool = True
    ) -> list[Feedback | None]:
        out: list[Feedback | None] = []
        path = np.full(max(1, round(seconds / self.dt)), x)
        self.run(path, enable, lambda i, f, r: out.append(f), check)
        return out

    def idle_while(self, work: Callable[[], Any]) -> Any:
        """``work()`` in a thread while this one keeps commanding ``x`` disabled, the heartbeat
        going (a drive's heartbeat consumer watches even while disabled); its result."""
        import concurrent.futures

        x = self.x
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            fut = pool.submit(work)
            while not fut.done():
                self.hold(x, 0.05, False, check=False)
            return fut.result()

    def silent(self, seconds: float) -> float:
        """Send nothing for ``seconds`` (the operator stop still ends it); the time spent."""
        t0 = time.perf_counter()
        end = t0 + seconds
        while (now := time.perf_counter()) < end:
            self.stop.check()
            time.sleep(min(0.01, end - now))
        return time.perf_counter() - t0


def status_names(status: int | None) -> str:
    if status is None:
        return "no reply"
    names = [b.name for b in Status if b & status and b.name]
    return "|".join(names) if names else "0"


def last_reply(fbs: list[Feedback | None]) -> Feedback | None:
    return next((f for f in reversed(fbs) if f is not None), None)

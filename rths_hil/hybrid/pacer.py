"""The paced wait: one grid of deadlines for the loop, the start and end phases and commissioning.

A :class:`Pacer` keeps an absolute grid of deadlines ``t0 + k·Δt`` (no drift), waits for each
one (sleep until ``spin`` before it, then busy-wait), accounts for how late each send left
(lateness, overruns past a threshold) and tells a stall of our own process (the loop did not
run for longer than ``min_stall`` past a period) from a late step. What the caller does with a
stall (tell the feedback watchdogs that the silence was ours, an event, the stall rule) is the
caller's: the pacer only measures. See ``docs/loop.md`` ("Modes").

The clock and the sleep are parameters, so the arithmetic is tested against a fake clock
(``tests/hybrid/test_pacer.py``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

__all__ = ["MIN_SLEEP", "PHASE_LEAD", "SPIN_CAP", "Pacer", "ReplyBudget", "first_deadline"]

#: Paced: from the end of a phase's set-up to its first deadline, at least (s). A phase that
#: follows another one without set-up (the loop after the start ramp, the end after the loop)
#: continues the previous one's grid instead: the controllers get a command every period from
#: arming to the hand-back (``docs/loop.md``, "No silent gap").
PHASE_LEAD = 0.002

#: Paced: when the work leaves less than ``spin`` before the deadline, still sleep this fraction
#: of a period if there is room for it (and as much again to spin). A SCHED_FIFO thread that
#: never sleeps exhausts the kernel's RT bandwidth (sched_rt_runtime_us = 95 %; on Linux ≥ 6.12
#: the fair server) and is stopped for ≈ 50 ms every second: at 4096 Hz with ≈ 170 µs of work
#: per 244 µs period that alone made 18 % of the steps late.
MIN_SLEEP = 0.1

#: The loop never spins longer than this fraction of a period (``loop.spin`` is capped to it).
SPIN_CAP = 0.4


def first_deadline(
    dt: float,
    after: float | None = None,
    lead: float = PHASE_LEAD,
    clock: Callable[[], float] = time.perf_counter,
) -> float:
    """The first deadline (``clock`` s) of a paced phase of period ``dt``.

    Parameters
    ----------
    dt : float
        Period (s).
    after : float, optional
        The next deadline of the phase before this one (its grid continues), used when it is
        not already more than a period past.
    lead : float
        Otherwise the first deadline is ``max(dt, lead)`` from now.
    clock : callable
        The clock (``time.perf_counter``).

    Returns
    -------
    float
        The deadline of step 0.
    """
    now = clock()
    if after is not None and after > now - dt:
        return max(after, now)
    return now + max(dt, lead)


class Pacer:
    """Deadlines ``t0 + k·Δt``: wait for each, account for lateness, detect our own stalls.

    Parameters
    ----------
    dt : float
        Period Δt (s).
    spin : float
        Busy-wait before each deadline (s); the wait sleeps until then.
    min_sleep : float
        When the time left before the deadline is less than ``spin``, still sleep this long
        if at least twice as much is left (s; 0: never force a sleep). The loop's is
        :data:`MIN_SLEEP` · Δt (the kernel's RT bandwidth limit, see there).
    threshold : float
        A send that leaves more than this after its deadline is an overrun (s).
    min_stall : float
        A late send is a stall of our own process when it is more than this late and more
        than this past one period after the previous send (s; ``inf``: no stall detection).
    clock, sleep : callable
        The monotonic clock (s) and the sleep (``time.perf_counter``, ``time.sleep``).

    Attributes
    ----------
    t0 : float
        Deadline of step 0 (moves on a :meth:`slip`).
    due : float
        Deadline of the step last waited for.
    ready : float
        Time at which the last :meth:`wait` was called minus its deadline (s; < 0 when the
        caller was early and waited).
    prev_send : float
        Time of the last :meth:`sent` (``t0 − Δt`` before the first).
    overruns : int
        Sends later than ``threshold``.
    over : bool
        Whether the last send was an overrun.
    """

    __slots__ = (
        "clock",
        "dt",
        "due",
        "min_sleep",
        "min_stall",
        "over",
        "overruns",
        "prev_send",
        "ready",
        "sleep",
        "spin",
        "t0",
        "threshold",
    )

    def __init__(
        self,
        dt: float,
        spin: float,
        *,
        min_sleep: float = 0.0,
        threshold: float = math.inf,
        min_stall: float = math.inf,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not dt > 0:
            raise ValueError(f"Pacer: dt must be > 0, got {dt}")
        self.dt = float(dt)
        self.spin = float(spin)
        self.min_sleep = float(min_sleep)
        self.threshold = float(threshold)
        self.min_stall = float(min_stall)
        self.clock = clock
        self.sleep = sleep
        self.t0 = 0.0
        self.due = 0.0
        self.ready = 0.0
        self.prev_send = -self.dt
        self.overruns = 0
        self.over = False

    @classmethod
    def for_loop(
        cls,
        dt: float,
        spin: float,
        threshold: float = math.inf,
        min_stall: float = math.inf,
        **kwargs,
    ) -> Pacer:
        """The paced loop's settings: ``spin`` capped at :data:`SPIN_CAP` · Δt and the forced
        sleep of :data:`MIN_SLEEP` · Δt (the loop, its start and end phases, the floor)."""
        return cls(
            dt,
            min(spin, SPIN_CAP * dt),
            min_sleep=MIN_SLEEP * dt,
            threshold=threshold,
            min_stall=min_stall,
            **kwargs,
        )

    def start(self, after: float | None = None, lead: float = PHASE_LEAD) -> float:
        """Set the grid: step 0 at :func:`first_deadline` (``after``, ``lead``); returns ``t0``."""
        self.t0 = t0 = first_deadline(self.dt, after, lead, self.clock)
        self.prev_send = t0 - self.dt
        self.overruns = 0
        self.over = False
        return t0

    def deadline(self, k: int) -> float:
        """Deadline of step ``k``: ``t0 + k·Δt``."""
        return self.t0 + k * self.dt

    def wait(self, k: int) -> float:
        """Wait for the deadline of step ``k``; return the time the wait ended (≥ the deadline).

        Sleeps until ``spin`` before the deadline (at least ``min_sleep`` when twice that is
        left), then busy-waits to it. Sets :attr:`due` and :attr:`ready`.
        """
        clock = self.clock
        self.due = deadline = self.t0 + k * self.dt
        now = clock()
        gap = deadline - now
        self.ready = -gap  # > 0: the caller's previous step ran past this deadline
        rem = gap - self.spin
        min_sleep = self.min_sleep
        if rem < min_sleep and gap > 2.0 * min_sleep:
            rem = min_sleep  # give the CPU away every period (RT bandwidth limit)
        if rem > 0:
            self.sleep(rem)
            now = clock()
        while now < deadline:
            now = clock()
        return now

    def stall(self, now: float) -> float | None:
        """Where a stall of our own process began, or ``None`` when the step is only late.

        ``now``: the time :meth:`wait` returned. A stall: more than ``min_stall`` late, and
        more than ``min_stall`` past one period after the previous send — the process did not
        run (the machine, a page fault, a stop), which is no controller's silence. Returns
        the stall's start (one period after the previous send); it ends at ``now``.
        """
        ms = self.min_stall
        if now - self.due > ms and now - self.prev_send - self.dt > ms:
            return self.prev_send + self.dt
        return None

    def slip(self, lateness: float) -> None:
        """Shift the grid by ``lateness`` (s): the step waited for is on time from here."""
        self.t0 += lateness

    def spin_until(self, t: float, now: float) -> float:
        """Busy-wait from ``now`` until ``t`` (a short catch-up spacing); the time it ended."""
        clock = self.clock
        while now < t:
            now = clock()
        return now

    def sent(self, now: float) -> float:
        """The step waited for was sent at ``now``: its lateness (s), counted as an overrun
        when over the threshold; the next stall is measured from this send."""
        lat = now - self.due
        self.prev_send = now
        self.over = over = lat > self.threshold
        if over:
            self.overruns += 1
        return lat


class ReplyBudget:
    """How long a paced step waits for its replies (``docs/loop.md``, "Modes").

    With ``loop.feedback_timeout`` set the replies are waited for at most that long after the
    send. With the automatic wait (``auto``: ``loop.feedback_timeout = 0``, paced) they are
    waited for at most until the step's own work after them still ends before the next
    deadline: until deadline + Δt − reserve, where the reserve is the recent peak of that
    work (+50 %, decaying by 0.2 % a step, kept between 5 % and 25 % of Δt; a step whose work
    took longer than Δt is a stall, not work to reserve for). A reply later than that is a
    missed reply (the measurement is held), not an overrun that the following steps inherit.

    Parameters
    ----------
    dt : float
        Period (s).
    timeout : float
        The reply timeout from the send (s).
    auto : bool
        The automatic wait (paced, ``loop.feedback_timeout = 0``).
    """

    __slots__ = ("auto", "dt", "reserve", "reserve_max", "reserve_min", "timeout")

    def __init__(self, dt: float, timeout: float, auto: bool) -> None:
        self.dt = dt
        self.timeout = timeout
        self.auto = bool(auto)
        self.reserve_min, self.reserve_max = 0.05 * dt, 0.25 * dt
        self.reserve = 0.2 * dt

    def limit(self, now: float, deadline: float) -> float:
        """The time (s) by which the replies of the step sent at ``now`` for ``deadline``
        must have come."""
        t_lim = now + self.timeout
        if self.auto:
            t_cut = deadline + self.dt - self.reserve
            if t_cut < t_lim:
                t_lim = t_cut
        return t_lim

    def note(self, work: float) -> None:
        """A step's work after its replies took ``work`` s: update the reserve."""
        if self.auto and work < self.dt:
            work *= 1.5
            reserve = work if work > self.reserve else self.reserve * 0.998
            if reserve < self.reserve_min:
                reserve = self.reserve_min
            elif reserve > self.reserve_max:
                reserve = self.reserve_max
            self.reserve = reserve

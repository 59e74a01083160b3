"""The Pacer against a scripted clock: deadlines, sleeps, lateness, overruns, stalls.

Every expected number is worked out here from the period and the scripted times, not read
from the pacer: the grid ``t0 + k·Δt``, the sleep until ``spin`` before a deadline (or the
forced minimum sleep), the lateness of a send and whether a late step is our own stall.
"""

from __future__ import annotations

import math

import pytest

from rths_hil.hybrid.pacer import MIN_SLEEP, SPIN_CAP, Pacer, ReplyBudget, first_deadline


class FakeClock:
    """A clock that advances ``tick`` per reading; ``sleep`` advances by the request plus
    ``oversleep`` (what a loaded kernel adds) and is logged."""

    def __init__(self, t: float = 10.0, tick: float = 1e-6) -> None:
        self.t = t
        self.tick = tick
        self.oversleep = 0.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        self.t += self.tick
        return self.t

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.t += s + self.oversleep

    def work(self, s: float) -> None:
        """The caller's own work between two waits."""
        self.t += s


def make(clock: FakeClock, dt: float = 1e-3, **kw) -> Pacer:
    return Pacer(dt, kw.pop("spin", 3e-4), clock=clock, sleep=clock.sleep, **kw)


def test_first_deadline_continues_a_grid_or_leads() -> None:
    c = FakeClock(t=5.0, tick=0.0)
    dt = 1e-3
    assert first_deadline(dt, None, clock=c) == pytest.approx(5.002)  # PHASE_LEAD > dt
    assert first_deadline(0.01, None, clock=c) == pytest.approx(5.01)  # a period
    assert first_deadline(dt, 5.0007, clock=c) == 5.0007  # the previous grid continues
    assert first_deadline(dt, 4.9995, clock=c) == 5.0  # just past: at once
    assert first_deadline(dt, 4.998, clock=c) == pytest.approx(5.002)  # > a period past
    assert first_deadline(dt, None, lead=0.0, clock=c) == pytest.approx(5.001)


def test_deadlines_sleep_then_spin() -> None:
    c = FakeClock(t=10.0, tick=1e-6)
    dt, spin = 1e-3, 3e-4
    p = make(c, dt, spin=spin)
    t0 = p.start(lead=0.0)
    assert t0 == pytest.approx(10.0 + 1e-6 + dt)  # one reading, then a period
    for k in range(5):
        c.work(1e-4)  # 0.1 ms of work after each send
        before = c.t
        now = p.wait(k)
        deadline = t0 + k * dt
        assert p.due == deadline
        assert now >= deadline
        assert now - deadline <= 1e-6 + 1e-9  # one tick of spin past it at most
        # slept until spin before the deadline, from the first clock reading
        assert c.sleeps[-1] == pytest.approx(deadline - (before + 1e-6) - spin, abs=1e-12)
        assert p.ready == pytest.approx(before + 1e-6 - deadline, abs=1e-12)
        lat = p.sent(now)
        assert lat == now - deadline
    assert p.overruns == 0
    assert len(c.sleeps) == 5


def test_forced_min_sleep_when_the_work_leaves_less_than_the_spin() -> None:
    dt = 1 / 4096
    c = FakeClock(t=0.0, tick=1e-7)
    p = Pacer.for_loop(dt, 3e-4, clock=c, sleep=c.sleep)
    assert p.spin == pytest.approx(SPIN_CAP * dt)  # 0.3 ms > 0.4·244 µs: capped
    t0 = p.start()
    # 50 µs left before the deadline: less than the spin, more than 2 × 0.1 Δt (48.8 µs)
    c.t = t0 - 50e-6
    p.wait(0)
    assert c.sleeps == [pytest.approx(MIN_SLEEP * dt)]
    # 40 µs left: less than twice the minimum sleep, so no sleep at all (spin only)
    c.t = t0 + dt - 40e-6
    now = p.wait(1)
    assert c.sleeps == [pytest.approx(MIN_SLEEP * dt)]
    assert t0 + dt <= now <= t0 + dt + 1.01e-7  # the spin ends within a tick of it


def test_overruns_are_counted_over_the_threshold() -> None:
    dt = 1e-3
    c = FakeClock(t=0.0, tick=1e-7)
    p = make(c, dt, threshold=0.5 * dt)
    t0 = p.start(lead=0.0)
    late_by = [0.0, 0.2e-3, 0.6e-3, 0.49e-3, 1.5e-3, 0.0]
    expected = [d > 0.5e-3 for d in late_by]
    for k, d in enumerate(late_by):
        c.t = t0 + k * dt + d  # the previous step's work ended d past this deadline
        now = p.wait(k)
        lat = p.sent(now)
        assert lat == pytest.approx(d, abs=2e-7)  # late by d (and a clock tick)
        assert p.over == expected[k]
        assert p.ready == pytest.approx(d, abs=2e-7)
    assert p.overruns == sum(expected) == 2


def test_a_stall_is_told_from_a_late_step() -> None:
    dt = 1e-3
    min_stall = max(2e-3, 2 * dt)
    c = FakeClock(t=0.0, tick=1e-7)
    p = make(c, dt, threshold=0.5 * dt, min_stall=min_stall)
    t0 = p.start(lead=0.0)
    now = p.wait(0)
    p.sent(now)
    # step 1: the process did not run for 40 ms after step 0's send
    c.t = t0 + 0.040
    now = p.wait(1)
    assert p.stall(now) == pytest.approx(t0 + dt, abs=1e-6)  # a period after the send ...
    assert now - p.stall(now) == pytest.approx(0.039, abs=1e-6)  # ... to now: 39 ms silent
    p.slip(now - p.due)  # shift the grid: step 1 on time from here
    p.sent(now)
    assert p.deadline(2) == pytest.approx(t0 + 0.040 + dt, abs=1e-6)
    # step 2 1.5 ms late: an overrun, not a stall (1.5 ms < 2 ms)
    c.t = p.deadline(2) + 1.5e-3
    now = p.wait(2)
    assert p.stall(now) is None
    p.sent(now)
    # step 3: 2.5 ms late (more than min_stall), but the previous send was 1.5 ms late: only
    # 1 ms past a period after it — the catch-up of a late step, not a new stall
    c.t = p.deadline(3) + 2.5e-3
    now = p.wait(3)
    assert now - p.due == pytest.approx(2.5e-3, abs=1e-6)
    assert now - p.prev_send - dt == pytest.approx(1.0e-3, abs=1e-6)
    assert p.stall(now) is None
    p.sent(now)
    # without stall detection nothing is a stall
    q = make(c, dt)
    q.start(lead=0.0)
    c.t += 1.0
    assert q.stall(q.wait(0)) is None
    assert math.isinf(q.min_stall)


def test_spin_until_and_bad_period() -> None:
    c = FakeClock(t=0.0, tick=1e-5)
    p = make(c)
    end = p.spin_until(1e-3, c())
    assert 1e-3 <= end < 1e-3 + 1.01e-5
    with pytest.raises(ValueError, match="dt must be > 0"):
        Pacer(0.0, 3e-4)


def test_reply_budget_reserve_follows_the_work_peak() -> None:
    dt = 1e-3
    b = ReplyBudget(dt, timeout=0.05, auto=True)
    # before any work: deadline + Δt − 20 % Δt, earlier than send + timeout
    assert b.limit(now=1.0001, deadline=1.0) == pytest.approx(1.0 + 0.8e-3)
    b.note(0.1e-3)  # 0.15 ms < the 0.2 ms reserve: it decays by 0.2 %
    assert b.reserve == pytest.approx(0.2e-3 * 0.998)
    b.note(0.14e-3)  # 0.21 ms > the reserve: the new peak
    assert b.reserve == pytest.approx(0.21e-3)
    b.note(0.9e-3)  # 1.35 ms: capped at 25 % of Δt
    assert b.reserve == pytest.approx(0.25e-3)
    b.note(2e-3)  # longer than Δt: a stall, not work to reserve for
    assert b.reserve == pytest.approx(0.25e-3)
    r = 0.25e-3
    for _ in range(1000):  # no work: decays to the 5 % floor
        b.note(0.0)
        r = max(r * 0.998, 0.05e-3)
    assert b.reserve == pytest.approx(r) == pytest.approx(0.05e-3)
    assert b.limit(now=2.0, deadline=2.0) == pytest.approx(2.0 + 1e-3 - 0.05e-3)
    # a fixed timeout (loop.feedback_timeout) or lockstep: the send + timeout, no reserve
    fixed = ReplyBudget(dt, timeout=2e-3, auto=False)
    fixed.note(0.1e-3)
    assert fixed.limit(now=3.0, deadline=2.9995) == 3.002
    assert fixed.reserve == pytest.approx(0.2e-3)

"""The step's exchange (StepIO): every command sent, the replies within the budget, the
missing ones told apart — with fake controllers whose replies and delays the test sets."""

from __future__ import annotations

import time

import pytest
from rths_hil.drivers.base import Feedback

from rths_hil.hybrid.pacer import ReplyBudget
from rths_hil.hybrid.stepio import StepIO

timing = pytest.mark.timing


class FakeController:
    """Answers each command after ``delay`` s if that is within the wait, else not at all."""

    def __init__(self, delay: float = 0.0, answers: bool = True) -> None:
        self.delay = delay
        self.answers = answers
        self.sent: list[tuple[int, float, bool]] = []
        self.waits: list[float] = []

    def send(self, seq: int, x: float, enable: bool) -> None:
        self.sent.append((seq, x, enable))

    def receive(self, timeout: float) -> Feedback | None:
        self.waits.append(timeout)
        t_end = time.perf_counter() + min(self.delay, timeout)
        while time.perf_counter() < t_end:
            pass
        if not self.answers or self.delay > timeout:
            return None
        seq, x, _ = self.sent[-1]
        return Feedback(seq, x, 2.0 * x, 0)


def _io(ctls, timeout, auto=False, shared=None, dt=1e-3):
    return StepIO([(c.send, c.receive) for c in ctls], ReplyBudget(dt, timeout, auto), shared)


def test_every_command_sent_and_every_reply_in_its_place():
    a, b = FakeController(), FakeController(answers=False)
    io = _io([a, b], 0.01, shared=False)
    io.send(7, [0.5, -0.25], True)
    assert a.sent == [(7, 0.5, True)] and b.sent == [(7, -0.25, True)]
    replies = io.collect(time.perf_counter())
    assert replies is io.replies
    assert replies[0] is not None and (replies[0].seq, replies[0].force) == (7, 1.0)
    assert replies[1] is None  # missed: the caller holds what it had
    assert io.clocks[0] <= io.clocks[1]
    assert a.waits == [0.01] and b.waits == [0.01]  # not shared: each waits the timeout
    with pytest.raises(ValueError):  # one command per controller
        io.send(8, [0.5], True)


@timing
def test_shared_replies_wait_only_what_is_left_of_the_limit():
    slow, late = FakeController(delay=0.004), FakeController(delay=1.0)
    io = _io([slow, late], 0.01)  # several controllers: shared by default
    assert io.shared
    io.send(1, [0.0, 0.0])
    now = time.perf_counter()
    replies = io.collect(now)
    assert replies[0] is not None and replies[1] is None
    assert slow.waits[0] <= 0.01
    # the second controller waited only what the first left of the limit, not the timeout
    assert late.waits[0] <= 0.01 - 0.004 + 1e-4
    assert io.clocks[1] - now < 0.01 + 2e-3  # the step was not held past the limit (+ slack)


@timing
def test_automatic_wait_ends_before_the_next_deadline():
    dt = 2e-3
    ctl = FakeController(delay=1.0)
    io = _io([ctl], 0.5, auto=True, dt=dt)
    assert io.shared  # the automatic wait shares its limit even with one controller
    now = time.perf_counter()
    io.send(1, [0.0])
    io.collect(now, deadline=now)
    # deadline + Δt − reserve (0.2 Δt at first): far inside the 0.5 s timeout
    assert ctl.waits[0] <= dt * 0.8 + 1e-6
    assert io.replies[0] is None

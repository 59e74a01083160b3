"""Paced-overrun attribution (machine vs the loop's own work) and the empty-loop floor."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from rths_hil.config import load_config
from rths_hil.hybrid import (
    CAUSES,
    MACHINE,
    MACHINE_BACKLOG,
    MACHINE_IN_WORK,
    ON_TIME,
    WORK,
    WORK_BACKLOG,
    RTHSLoop,
    attribute_overruns,
    count_causes,
    paced_floor,
)
from rths_hil.records.recorder import read_run

# The attribution against the event model and the console's percentile are arithmetic: they run
# with the parallel tests; the paced runs and the paced floor run apart from them, one at a time
# (the "timing" marker, pyproject.toml; make test).

DT = 1.0 / 4096.0
THR = 0.5 * DT


def _simulate(work, wait_stall, spin_late=0.0, work_stall=None):
    """An independent event model of the paced loop: deadlines k·Δt, never skipped.

    Step k becomes ready when the previous step's work is done (``send[k-1] + work[k-1]``,
    plus ``work_stall[k-1]`` when the machine preempted the loop inside that work); the wait
    ends at ``max(ready, deadline) + wait_stall[k]`` (a stall of the machine during the wait)
    and the command leaves then. Returns (lateness, ready) as the loop records them.
    """
    n = len(work)
    work_stall = np.zeros(n) if work_stall is None else work_stall
    send = np.empty(n)
    ready = np.empty(n)
    t_ready = -1.0  # the first step is ready long before its deadline
    for k in range(n):
        deadline = k * DT
        ready[k] = t_ready - deadline
        send[k] = max(t_ready, deadline) + wait_stall[k] + spin_late
        t_ready = send[k] + work[k] + work_stall[k]
    lateness = send - np.arange(n) * DT
    return lateness, ready


def _truth(lateness, work, wait_stall, work_stall=None):
    """Causes from what the model was told: a chain starts at a step whose predecessor's work
    ran past this step's threshold (work), or did so only with the preemption inside it
    (machine in the work), otherwise at a stall in its wait (machine); the rest of the chain
    is backlog."""
    work_stall = np.zeros(len(work)) if work_stall is None else work_stall
    over = lateness > THR
    machine = (MACHINE, MACHINE_BACKLOG, MACHINE_IN_WORK)
    out = np.zeros(len(over), dtype=np.int8)
    for k in np.flatnonzero(over):
        if k > 0 and over[k - 1]:
            out[k] = MACHINE_BACKLOG if out[k - 1] in machine else WORK_BACKLOG
        elif k > 0 and lateness[k - 1] + work[k - 1] > DT + THR:
            out[k] = WORK
        elif k > 0 and lateness[k - 1] + work[k - 1] + work_stall[k - 1] > DT + THR:
            out[k] = MACHINE_IN_WORK
        else:
            assert wait_stall[k] > 0
            out[k] = MACHINE
    return out


def test_a_stall_in_the_wait_is_the_machine_and_its_catch_up_is_backlog():
    n = 60
    work = np.full(n, 0.6 * DT)  # catch-up gains 0.4 Δt per step
    stall = np.zeros(n)
    stall[10] = 3.0 * DT
    lat, ready = _simulate(work, stall)
    cause = attribute_overruns(lat, ready, THR)
    assert cause[10] == MACHINE
    # behind by 3 Δt, gaining 0.4 Δt a step: late by more than ½ Δt while 3 - 0.4 j > 0.5
    backlog = [j for j in range(1, 20) if 3.0 - 0.4 * j > 0.5]
    assert cause[11 : 11 + len(backlog)].tolist() == [MACHINE_BACKLOG] * len(backlog)
    assert (cause[:10] == ON_TIME).all() and (cause[11 + len(backlog) :] == ON_TIME).all()
    assert count_causes(cause) == {
        "machine": 1,
        "machine_backlog": len(backlog),
        "work": 0,
        "work_backlog": 0,
        "machine_in_work": 0,
    }


def test_a_preemption_inside_the_work_is_the_machine_only_when_the_work_alone_was_in_time():
    n = 40
    work = np.full(n, 0.3 * DT)
    preempt = np.zeros(n)
    preempt[5] = 2.0 * DT  # step 5's work is 0.3 Δt of CPU and 2 Δt off the CPU
    work[20] = 2.0 * DT  # step 20's work is 2 Δt of CPU, and also preempted a little
    preempt[20] = 0.2 * DT
    lat, ready = _simulate(work, np.zeros(n), work_stall=preempt)
    cause = attribute_overruns(lat, ready, THR, preempt)
    assert cause[6] == MACHINE_IN_WORK and cause[21] == WORK
    # the same run without the thread's clock: both are the work's
    blind = attribute_overruns(lat, ready, THR)
    assert blind[6] == WORK and blind[21] == WORK
    assert (cause != blind).sum() == 1 + (cause == MACHINE_BACKLOG).sum()
    with pytest.raises(ValueError, match="stalled"):
        attribute_overruns(lat, ready, THR, preempt[:-1])


def test_long_work_is_the_loops_own_overrun():
    n = 40
    work = np.full(n, 0.3 * DT)
    work[5] = 2.0 * DT  # step 6 is ready 1.0 Δt (+ step 5's lateness 0) after its deadline
    lat, ready = _simulate(work, np.zeros(n))
    cause = attribute_overruns(lat, ready, THR)
    assert cause[5] == ON_TIME and cause[6] == WORK
    # behind by 1 Δt at step 6, gaining 0.7 Δt a step: step 7 is 0.3 Δt late (not an overrun)
    assert cause[7] == ON_TIME
    assert count_causes(cause)["work"] == 1 and (cause > 0).sum() == 1


def test_boundary_lateness_equal_to_the_threshold_is_not_an_overrun():
    lat = np.array([0.0, THR, np.nextafter(THR, 1.0)])
    ready = np.array([-DT, -DT, -DT])
    assert attribute_overruns(lat, ready, THR).tolist() == [ON_TIME, ON_TIME, MACHINE]


def test_random_runs_match_the_event_model():
    rng = np.random.default_rng(7)
    n = 20_000
    work = rng.uniform(0.3, 0.7, n) * DT
    long = rng.random(n) < 0.002
    work[long] = rng.uniform(1.0, 8.0, long.sum()) * DT
    stall = np.where(rng.random(n) < 0.002, rng.uniform(0.6, 20.0, n) * DT, 0.0)
    preempt = np.where(rng.random(n) < 0.004, rng.uniform(0.1, 10.0, n) * DT, 0.0)
    lat, ready = _simulate(work, stall, work_stall=preempt)
    cause = attribute_overruns(lat, ready, THR, preempt)
    truth = _truth(lat, work, stall, preempt)
    np.testing.assert_array_equal(cause, truth)
    counts = count_causes(cause)
    assert sum(counts.values()) == int((lat > THR).sum())
    assert counts["machine"] > 10 and counts["work"] > 10  # every kind happened
    assert counts["machine_in_work"] > 10
    assert counts["machine_backlog"] > 0 and counts["work_backlog"] > 0
    assert set(counts) == set(CAUSES[1:])


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="same length"):
        attribute_overruns(np.zeros(3), np.zeros(2), THR)


@pytest.mark.timing
def test_the_empty_loop_floor_keeps_the_grid():
    fs = 1024.0
    lat, ready = paced_floor(fs, 0.3, spin=2e-4)
    assert lat.shape == ready.shape == (round(0.3 * fs),)
    assert (lat >= 0).all()  # never early
    assert (lat >= ready - 1e-9).all()  # the send is never before the loop was ready
    # nothing to do between steps: the steps not caught up after a stall wait for their deadline
    assert (ready < 0).mean() > 0.25
    cause = attribute_overruns(lat, ready, 0.5 / fs)
    assert sum(count_causes(cause).values()) == int((lat > 0.5 / fs).sum())


class _SlowPlant:
    """The default twin plant, taking ``slow`` seconds per step from step ``after`` on."""

    def __init__(self, after: int, slow: float) -> None:
        from rths_hil.sim_backends.twin import default_plant

        self.inner = default_plant()
        self.dt = self.inner.dt
        self.after, self.slow, self.k = after, slow, 0

    def reset(self) -> None:
        self.inner.reset()
        self.k = 0

    def step(self, command: float):
        self.k += 1
        if self.k > self.after:
            t = time.perf_counter() + self.slow
            while time.perf_counter() < t:
                pass
        return self.inner.step(command)


@pytest.mark.timing
def test_consecutive_overruns_trip_where_the_record_says(tmp_path):
    fs = 1024.0
    cfg = load_config(
        None,
        [
            "loop.duration=2",
            "loop.console=0",
            "output.plot=false",
            "safety.max_overruns=20",
            "safety.watchdog_missed=1000000",
            "kalman.enabled=false",
        ],
    )
    res = RTHSLoop(cfg, tmp_path / "r", plant=_SlowPlant(200, 2.0 / fs), mode="paced").run()
    assert res.status == "trip" and res.trip.rule == "overrun"
    over = read_run(tmp_path / "r").record["lateness"] > 0.5 / fs
    # the first step that closes a run of 20 consecutive overruns in the record
    first = next(k for k in range(19, over.size) if over[k - 19 : k + 1].all())
    assert res.steps == first + 1 and res.trip.step == first
    causes = res.overrun_causes()
    assert sum(causes.values()) == res.overruns == int(over.sum())
    # step 200's work took 2 periods: step 201 is late because of the work (unless a stall of
    # the machine had already made step 200 late), and the rest of the run is its backlog
    cause = attribute_overruns(res.lateness, res.ready, res.overrun_threshold)
    if first > 201 and not over[200]:  # (a long stall of the machine may trip it earlier)
        assert cause[201] == WORK
        assert (cause[202 : first + 1] == WORK_BACKLOG).all()


@pytest.mark.parametrize("n", [1, 2, 3, 100, 511, 2048])
def test_console_p99_is_numpys_percentile(n):
    from rths_hil.hybrid.timing import p99 as _p99

    x = np.random.default_rng(n).exponential(1e-5, n)
    assert _p99(x) == pytest.approx(np.percentile(x, 99), rel=1e-12, abs=0)
    assert (x == np.random.default_rng(n).exponential(1e-5, n)).all()  # not sorted in place


_HOG = """
import os, sys, time
os.sched_setaffinity(0, {int(sys.argv[1])})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))  # above the loop's (10)
print("ready", flush=True)
while os.read(0, 1):  # each byte: take the CPU for float(sys.argv[2]) s, then sleep again
    end = time.perf_counter() + float(sys.argv[2])
    while time.perf_counter() < end:
        pass
"""


@pytest.fixture
def same_cpu_hog():
    """A real-time process on the loop thread's CPU that preempts it on demand: each byte
    written to ``hog.stdin`` makes it spin 4 ms at SCHED_FIFO priority 50 (a task the
    machine runs instead of the loop, as another process or the hypervisor would)."""
    cpu = min(os.sched_getaffinity(0))
    old = os.sched_getaffinity(0)
    hog = subprocess.Popen([sys.executable, "-c", _HOG, str(cpu), "0.004"],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE)  # fmt: skip
    try:
        assert hog.stdout.readline() == b"ready\n"
        os.sched_setaffinity(0, {cpu})  # this thread (the loop's) on the hog's CPU
        yield hog
    finally:
        os.sched_setaffinity(0, old)
        hog.kill()
        hog.wait()


@pytest.mark.timing
def test_the_threads_clock_tells_a_preemption_inside_the_work_from_the_work(
    tmp_path, monkeypatch, same_cpu_hog
):
    """Nine steps' work is disturbed for 4 ms after the replies, three by each of: the hog
    preempting the loop (the machine), the work itself spinning (CPU work) and sleeping (a
    voluntary wait). Each time the next step is ready ≈ 3 ms late; only the preemption is the
    machine's. (Three of each, interleaved: a noisy host once took 3 of the 4 ms of both
    spinning steps of an earlier two-of-each layout, leaving none of them to tell apart.)"""
    from rths_hil.hybrid.channel import Channel

    kinds = ("preempted", "cpu", "sleep")
    at = {150 + 100 * i: kinds[i % 3] for i in range(9)}  # steps 150 … 950
    evaluate = Channel.evaluate

    def disturbed(self, k):
        evaluate(self, k)
        what = at.get(k)
        if what == "preempted":
            os.write(same_cpu_hog.stdin.fileno(), b"x")  # returns after the hog's 4 ms
        elif what == "cpu":
            end = time.perf_counter() + 0.004
            while time.perf_counter() < end:
                pass
        elif what == "sleep":
            time.sleep(0.004)

    monkeypatch.setattr(Channel, "evaluate", disturbed)
    cfg = load_config(None, ["loop.duration=1.1", "loop.console=0", "output.plot=false",
                             "safety.max_overruns=1000", "kalman.enabled=false"])  # fmt: skip
    res = RTHSLoop(cfg, tmp_path / "r", mode="paced").run()
    assert res.status == "completed", res.trip
    thr = res.overrun_threshold
    cause = attribute_overruns(res.lateness, res.ready, thr, res.stalled)
    # judged: the steps not already late by a stall of the machine (one of each kind at least)
    judged = [k for k in at if res.lateness[k] <= thr]
    assert {at[k] for k in judged} == {"preempted", "cpu", "sleep"}, res.lateness[list(at)]
    told_apart = set()
    for k in judged:
        assert res.ready[k + 1] > 0.002  # the disturbance made the next step late
        if at[k] == "preempted":
            assert res.stalled[k] > 0.0035, res.stalled[k]
            assert cause[k + 1] == MACHINE_IN_WORK
            told_apart.add(at[k])
        elif res.ready[k + 1] - res.stalled[k] <= thr:
            # the machine preempted this step's own work as well, long enough to explain the
            # lateness (a noisy host does, now and then): then it is the machine's, as for
            # the hog
            assert cause[k + 1] == MACHINE_IN_WORK, (k, res.stalled[k])
        else:
            assert cause[k + 1] == WORK
            if res.stalled[k] < 0.002 if at[k] == "cpu" else res.stalled[k] == 0.0:
                told_apart.add(at[k])  # and the thread's clock saw no machine in it
    # at least one step of each kind was told apart from the others
    assert told_apart == {"preempted", "cpu", "sleep"}, res.stalled[list(at)]
    counts = res.overrun_causes()
    assert sum(counts.values()) == res.overruns

"""E-stop paths of the loop: each fault trips the right rule within 2 steps of the first
detectable sample, the twin receives (and confirms) the e-stop, the record holds every step up
to the trip and the trip event."""

from __future__ import annotations

import numpy as np
import pytest

from rths_hil.config import load_config
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import read_run

FS = 1024.0
DRIVERS = ["can", "modbus", "serial"]


def run_lockstep(tmp_path, *overrides, plant=None, name="run"):
    cfg = load_config(
        None,
        ["loop.mode=lockstep", "loop.console=0", "output.plot=false", "twin.sensor={}", *overrides],
    )
    loop = RTHSLoop(cfg, tmp_path / name, plant=plant)
    result = loop.run()
    return loop, result, read_run(tmp_path / name)


class JumpDelayPlant:
    """Pure delay of ``d1`` samples growing to ``d2`` samples from step ``at``; a linear spring.

    The delay grows by one sample every second step (the actuator moves at half speed for a
    moment) rather than in one go: an instantaneous jump would make the measured displacement
    jump too, which the velocity rule catches before any estimator could.
    """

    def __init__(self, d1: int, d2: int, at: int, stiffness: float = 1.19e6) -> None:
        self.dt = 1 / FS
        self.d1, self.d2, self.at, self.stiffness = d1, d2, at, stiffness
        self.reset()

    def reset(self) -> None:
        self.hist: list[float] = []

    def step(self, command: float) -> tuple[float, float]:
        self.hist.append(command)
        k = len(self.hist) - 1
        d = self.d1 if k < self.at else min(self.d2, self.d1 + (k - self.at) // 2)
        i = k - d
        x = self.hist[i] if i >= 0 else 0.0
        return x, self.stiffness * x


def _check_trip_bookkeeping(loop, res, run, rule, estop_confirmed=True):
    assert res.status == "trip" and res.exit_code == 3
    trip = res.trip
    assert trip.rule == rule, trip
    # the record holds every step up to and including the one that tripped, nothing after
    assert len(run.record) == trip.step + 1 == res.steps
    np.testing.assert_array_equal(run.record["step"], np.arange(res.steps))
    events = [e for e in run.events if e["kind"] == "trip"]
    assert len(events) == 1
    assert events[0]["rule"] == rule and events[0]["step"] == trip.step
    assert events[0]["time"] == pytest.approx(trip.step / FS)
    assert events[0]["reason"] == trip.reason
    assert run.events[-1]["kind"] == "end" and run.events[-1]["status"] == "trip"
    assert loop.driver.stats.estops == 1
    if estop_confirmed:
        assert loop.twin.stats.estops == 1  # the twin received it ...
        assert res.estop_confirmed is True  # ... and reported the latch
        assert loop.twin.stats.seq_gaps == 0  # the status poll continued the sequence
    return trip


def _first_run(flags: np.ndarray, length: int) -> int:
    """First index at which ``length`` consecutive True values end (brute force)."""
    for i in range(length - 1, len(flags)):
        if flags[i - length + 1 : i + 1].all():
            return i
    raise AssertionError("condition never held")


def test_delay_jump_trips_the_fei_rule(tmp_path):
    at = 5 * 1024  # after the first full window (3/fn = 3.9 s)
    plant = JumpDelayPlant(20, 61, at)  # 19.5 ms -> 59.6 ms
    loop, res, run = run_lockstep(
        tmp_path,
        "compensation.alpha=21",
        "loop.duration=14",
        "kalman.enabled=false",
        "safety.fei_delay_tol=0.010",
        "safety.fei_consecutive=32",
        plant=plant,
    )
    trip = _check_trip_bookkeeping(loop, res, run, "fei")
    rec = run.record
    # before the jump the compensated test tracks well
    before = rec["fei_valid"][:at]
    assert before.sum() > 1000
    assert np.abs(rec["fei_delay"][:at][before]).max() < 0.002
    out = rec["fei_valid"] & (np.abs(rec["fei_delay"]) > 0.010)
    # invalid windows neither count nor reset; here all windows after the first are valid
    expected = _first_run(out[rec["fei_valid"]], 32)
    expected = np.flatnonzero(rec["fei_valid"])[expected]
    assert 0 <= trip.step - expected <= 2
    assert trip.step > at
    assert "delay" in trip.reason and "10.000 ms" in trip.reason


def test_delay_jump_trips_the_kalman_rule(tmp_path):
    at = 2 * 1024
    plant = JumpDelayPlant(20, 61, at)
    loop, res, run = run_lockstep(
        tmp_path,
        "compensation.alpha=21",
        "loop.duration=8",
        "safety.fei_delay_tol=0",
        "safety.fei_amplitude_tol=0",
        "safety.kf_delay_max=0.040",
        plant=plant,
    )
    trip = _check_trip_bookkeeping(loop, res, run, "kalman")
    rec = run.record
    bad = (np.abs(rec["kf_delay"]) > 0.040) | (rec["kf_gain"] < 0.5) | (rec["kf_gain"] > 1.5)
    expected = int(np.flatnonzero(bad)[0])
    assert 0 <= trip.step - expected <= 2
    assert trip.step > at
    assert rec["kf_delay"][at - 1] == pytest.approx(20 / FS, abs=0.002)


def test_stuck_sensor_trips_the_stuck_rule(tmp_path):
    at = 2 * 1024
    loop, res, run = run_lockstep(
        tmp_path,
        f"twin.faults=stuck_from={at}",
        "loop.duration=5",
        "safety.stuck_steps=50",
    )
    trip = _check_trip_bookkeeping(loop, res, run, "stuck")
    m, c = run.record["measured"], run.record["command"]
    same = np.r_[False, m[1:] == m[:-1]]
    # 50 identical values = 49 repeats, and the command travelled > 0.1 mm meanwhile
    moved = np.array([np.abs(np.diff(c[max(i - 49, 0) : i + 1])).sum() for i in range(len(c))])
    runs = np.array([same[max(i - 48, 0) : i + 1].all() and i >= 49 for i in range(len(m))])
    expected = int(np.flatnonzero(runs & (moved > 1e-4))[0])
    assert 0 <= trip.step - expected <= 2
    assert at <= expected <= at + 50


@pytest.mark.parametrize("driver", DRIVERS)
def test_disconnect_trips_at_once(tmp_path, driver):
    at = 1536
    loop, res, run = run_lockstep(
        tmp_path,
        f"driver.name={driver}",
        f"twin.faults=disconnect_from={at}",
        "loop.duration=4",
        "loop.lockstep_timeout=0.5",
        "safety.watchdog_missed=3",
    )
    # the twin is gone: it cannot confirm, but the driver sent the e-stop. A closed socket or
    # line (Modbus TCP, serial) is a dead link: the `link` rule trips at the first reply it
    # costs, not after safety.watchdog_missed of them; a CAN twin that falls silent on the bus
    # is only silence: lockstep waits for the reply up to its wall-clock bound, which trips
    rule = "watchdog" if driver == "can" else "link"
    trip = _check_trip_bookkeeping(loop, res, run, rule, estop_confirmed=False)
    ok = run.record["feedback_ok"]
    assert ok[:at].all() and not ok[at:].any()
    assert trip.step == at
    if rule == "watchdog":
        assert trip.values["elapsed"] >= 0.5
    else:
        assert "connection" in trip.reason or "line" in trip.reason, trip.reason
    assert res.estop_confirmed is False


@pytest.mark.parametrize("driver", DRIVERS)
def test_nan_feedback_trips_the_nan_rule_at_once(tmp_path, driver):
    at = 1500
    loop, res, run = run_lockstep(
        tmp_path,
        f"driver.name={driver}",
        f"twin.faults=nan={at}",
        "loop.duration=3",
    )
    trip = _check_trip_bookkeeping(loop, res, run, "nan")
    assert trip.step == at
    assert np.isnan(run.record["measured"][at]) and np.isfinite(run.record["measured"][:at]).all()
    assert "measured" in trip.reason


def test_displacement_limit_stops_the_command_before_it_is_sent(tmp_path):
    lim = 0.008
    _, free, free_run = run_lockstep(tmp_path, "loop.duration=8", name="free")
    assert free.status == "completed"
    rec = free_run.record
    over = (np.abs(rec["target"]) > lim) | (np.abs(rec["command"]) > lim)
    first = int(np.flatnonzero(over)[0])  # the first step whose command would exceed
    loop, res, run = run_lockstep(
        tmp_path, "loop.duration=8", f"safety.displacement_limit={lim}", name="limited"
    )
    trip = _check_trip_bookkeeping(loop, res, run, "displacement")
    assert trip.step == first - 1  # caught at the end of the step before, never sent
    assert np.abs(run.record["command"]).max() <= lim
    assert np.abs(run.record["measured"]).max() <= lim
    assert "exceeds the limit ±8 mm" in trip.reason  # displayed in mm; values stay SI
    assert trip.values["limit"] == lim


def test_runaway_trips_the_controller_rule_or_the_measured_limit(tmp_path):
    at = 1024
    loop, res, run = run_lockstep(
        tmp_path,
        f"twin.faults=runaway_from={at}; runaway_rate=0.5",
        "loop.duration=3",
        name="status",
    )
    trip = _check_trip_bookkeeping(loop, res, run, "controller")
    assert trip.step == at and "FAULT" in trip.reason
    # without the status rule, the measured displacement limit catches the runaway
    loop, res, run = run_lockstep(
        tmp_path,
        f"twin.faults=runaway_from={at}; runaway_rate=0.5",
        "loop.duration=3",
        "safety.controller_status=false",
        "safety.velocity_limit=0",
        "kalman.enabled=false",
        name="limit",
    )
    trip = _check_trip_bookkeeping(loop, res, run, "displacement")
    m = np.abs(run.record["measured"])
    assert m[trip.step] > 0.05 and (m[: trip.step] <= 0.05).all()
    assert "measured displacement" in trip.reason

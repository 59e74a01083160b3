"""Safety rules: FEIRule, limits, watchdog, sequence, overrun, stuck, NaN, monitor."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.drivers.base import Status

from rths_hil.errors import InputError
from rths_hil.safety import (
    ControllerRule,
    FEIRule,
    KalmanRule,
    OverrunRule,
    SafetyMonitor,
    SequenceRule,
    StuckRule,
    WatchdogRule,
)


def _brute_first_trip(a, d, valid, a_tol, d_tol, consecutive):
    """Index of the window at which the FEI rule must trip (independent formulation).

    Keep only the valid windows, mark each as out of tolerance or not, and find the first
    position where the last `consecutive` kept windows are all out; map it back.
    """
    kept = [i for i in range(len(a)) if valid[i] and not (np.isnan(a[i]) or np.isnan(d[i]))]
    out = [abs(a[i] - 1) > a_tol or abs(d[i]) > d_tol for i in kept]
    for j in range(consecutive - 1, len(kept)):
        if all(out[j - consecutive + 1 : j + 1]):
            return kept[j]
    return None


def test_fei_rule_matches_brute_force_on_random_sequences():
    rng = np.random.default_rng(7)
    for trial in range(300):
        n = int(rng.integers(1, 60))
        a = 1 + rng.normal(0, 0.1, n)
        d = rng.normal(0, 0.01, n)
        valid = rng.random(n) > 0.25
        if trial % 5 == 0:
            a[rng.random(n) < 0.2] = np.nan
        consecutive = int(rng.integers(1, 6))
        rule = FEIRule(0.1, 0.01, consecutive)
        got = None
        for i in range(n):
            if rule.check(float(a[i]), float(d[i]), bool(valid[i])) is not None:
                got = i
                break
        assert got == _brute_first_trip(a, d, valid, 0.1, 0.01, consecutive), trial


def test_fei_rule_invalid_windows_neither_trip_nor_reset():
    rule = FEIRule(amplitude_tol=0.05, delay_tol=0.005, consecutive=3)
    assert rule.check(1.0, 0.02, True) is None  # out (delay) 1
    assert rule.check(1.0, 0.02, True) is None  # out 2
    for _ in range(10):  # invalid windows, even wildly out of tolerance
        assert rule.check(5.0, 1.0, False) is None
    trip = rule.check(1.0, 0.02, True)  # out 3 -> trips
    assert trip is not None and rule.count == 3


def test_fei_rule_valid_in_tolerance_resets_and_boundary_is_inside():
    rule = FEIRule(0.25, 0.005, 2)
    assert rule.check(1.0, 0.006, True) is None
    assert rule.check(1.25, 0.005, True) is None  # exactly at the tolerances: inside
    assert rule.count == 0
    assert rule.check(1.0, -0.006, True) is None
    assert rule.check(0.7, 0.0, True) is not None


def test_fei_rule_reason_names_quantity_value_and_limit():
    rule = FEIRule(0.05, 0.005, 1)
    trip = rule.check(1.0, 0.0123, True)
    assert trip.rule == "fei"
    assert "delay" in trip.reason and "12.300 ms" in trip.reason and "±5.000 ms" in trip.reason
    assert trip.values["delay"] == pytest.approx(0.0123)
    rule = FEIRule(0.05, 0.005, 1)
    trip = rule.check(0.8, 0.0, True)
    assert "amplitude" in trip.reason and "0.8000" in trip.reason and "0.05" in trip.reason
    assert "delay" not in trip.reason


def test_fei_rule_update_with_arrays_equals_scalar_feed():
    rng = np.random.default_rng(3)
    a = 1 + rng.normal(0, 0.05, 200)
    d = rng.normal(0, 0.004, 200)
    v = rng.random(200) > 0.1
    r1, r2 = FEIRule(0.06, 0.005, 4), FEIRule(0.06, 0.005, 4)
    t_blocks = None
    for start in range(0, 200, 17):
        t_blocks = r1.update(a[start : start + 17], d[start : start + 17], v[start : start + 17])
        if t_blocks is not None:
            break
    t_scalar = None
    for i in range(200):
        t_scalar = r2.check(a[i], d[i], v[i])
        if t_scalar is not None:
            break
    assert (t_blocks is None) == (t_scalar is None)
    if t_scalar is not None:
        assert t_blocks.values == t_scalar.values


# (a tolerance of 0 is the configuration's documented "off", not bad input)
@pytest.mark.parametrize(
    "args", [(-0.1, 0.01, 1), (0.1, -1, 1), (0.1, 0.01, 0), (0.1, 0.01, 1.5), ("x", 0.01, 1)]
)
def test_fei_rule_rejects_bad_arguments(args):
    with pytest.raises(InputError):
        FEIRule(*args)


def _monitor(**kw):
    base = dict(displacement_limit=0.05, velocity_limit=0.5, force_limit=1e5)
    base.update(kw)
    return SafetyMonitor(1 / 1024, **base)


def test_command_checked_before_send_and_monitor_latches_first_trip():
    m = _monitor()
    assert m.check_command(0.0, 0, 0.01, 0.1, 0.012) is None
    trip = m.check_command(0.5, 512, 0.049, 0.1, 0.0501)
    assert trip.rule == "displacement" and trip.step == 512 and trip.time == 0.5
    assert trip.reason == "command 50.1 mm exceeds the limit ±50 mm"  # shown in mm
    assert trip.values == {"command": 0.0501, "limit": 0.05}  # kept in SI
    # later problems do not replace the first trip
    again = m.check_feedback(0.6, 600, True, 600, 600, 1, 0.0, math.nan, 0.0)
    assert again is trip


def test_measured_velocity_spans_missed_replies():
    m = _monitor()
    dt = 1 / 1024
    assert m.check_feedback(0, 10, True, 10, 10, 1, 0.0, 0.0, 0.0) is None
    for k in (11, 12, 13):  # three missed replies: the measurement is held
        assert m.check_feedback(k * dt, k, False, k, -1, 0, 0.0, 0.0, 0.0) is None
    # 1.6 mm in 4 steps is 0.41 m/s (not 1.6 m/s over one step)
    assert m.check_feedback(14 * dt, 14, True, 14, 14, 1, 0.0, 0.0016, 0.0) is None
    trip = m.check_feedback(15 * dt, 15, True, 15, 15, 1, 0.0, 0.0016 + 0.6 * dt, 0.0)
    assert trip.rule == "velocity" and trip.values["measured velocity"] == pytest.approx(0.6)


def test_velocity_limit_on_structure_and_on_measured_backward_difference():
    m = _monitor()
    assert m.check_command(0, 0, 0.0, -0.49, 0.0) is None
    assert m.check_command(0, 1, 0.0, -0.51, 0.0).rule == "velocity"
    m = _monitor()
    dt = 1 / 1024
    assert m.check_feedback(0, 0, True, 0, 0, 1, 0.0, 0.0, 0.0) is None
    assert m.check_feedback(dt, 1, True, 1, 1, 1, 0.0, 0.45 * dt, 0.0) is None
    trip = m.check_feedback(2 * dt, 2, True, 2, 2, 1, 0.0, 0.45 * dt + 0.55 * dt, 0.0)
    assert trip.rule == "velocity" and trip.values["measured velocity"] == pytest.approx(0.55)


@pytest.mark.parametrize(
    ("measured", "force", "rule", "word"),
    [
        (0.06, 0.0, "displacement", "measured displacement"),
        (0.0, -2e5, "force", "force"),
        (math.nan, 0.0, "nan", "measured"),
        (0.0, math.inf, "nan", "force"),
    ],
)
def test_feedback_limits_and_nan(measured, force, rule, word):
    m = _monitor()
    trip = m.check_feedback(1.0, 1024, True, 1024, 1024, 1, 0.0, measured, force)
    assert trip.rule == rule and word in trip.reason and trip.step == 1024


def test_nan_in_command_names_the_quantity():
    trip = _monitor().check_command(0, 3, 0.0, 0.0, math.nan)
    assert trip.rule == "nan" and "command" in trip.reason and "target" not in trip.reason


def test_watchdog_trips_on_kth_consecutive_miss_only():
    m = _monitor(watchdog=WatchdogRule(3))
    feed = [True, False, False, True, False, False]
    for k, ok in enumerate(feed):
        assert m.check_feedback(k, k, ok, k, k if ok else -1, 1, 0.0, 0.0, 0.0) is None
    trip = m.check_feedback(6, 6, False, 6, -1, 0, 0.0, 0.0, 0.0)
    assert trip.rule == "watchdog" and trip.values["missed"] == 3


def test_sequence_rule_counts_gaps():
    r = SequenceRule(max_gaps=1)
    assert r.check(5, 5) is None
    assert r.check(6, 4) is None  # first gap tolerated
    trip = r.check(7, 9)
    assert trip.rule == "sequence" and "9" in trip.reason and "7" in trip.reason


def test_sequence_rule_counts_the_controller_gap_flag():
    m = _monitor(sequence=SequenceRule(0))
    assert m.check_feedback(0, 5, True, 5, 5, int(Status.ENABLED), 0.0, 0.0, 0.0) is None
    status = int(Status.ENABLED | Status.SEQ_GAP)
    trip = m.check_feedback(0, 6, True, 6, 6, status, 0.0, 0.0, 0.0)
    assert trip.rule == "sequence" and "missing command" in trip.reason


@pytest.mark.parametrize("bit", [Status.ESTOP_ACTIVE, Status.FAULT, Status.WATCHDOG])
def test_controller_alarm_bits_trip(bit):
    m = _monitor(controller=ControllerRule())
    assert m.check_feedback(0, 1, True, 1, 1, int(Status.ENABLED), 0.0, 0.0, 0.0) is None
    assert m.check_feedback(0, 2, True, 2, 2, int(Status.SENSOR_INVALID), 0.0, 0.0, 0.0) is None
    trip = m.check_feedback(0, 3, True, 3, 3, int(Status.ENABLED | bit), 0.0, 0.0, 0.0)
    assert trip.rule == "controller" and bit.name in trip.reason


def test_overrun_rule_consecutive():
    r = OverrunRule(3)
    seq = [True, True, False, True, True]
    assert all(r.check(o, 0.001) is None for o in seq)
    trip = r.check(True, 0.0012)
    assert trip.rule == "overrun" and "1.200 ms" in trip.reason


def test_stuck_rule_needs_identical_values_and_command_motion():
    r = StuckRule(steps=5, motion=1e-3)
    # command static, measurement constant: not stuck (nothing to follow)
    for _ in range(20):
        assert r.check(0.01, 0.01) is None
    # command moves 0.4 mm per step, measurement frozen -> trips on the 5th identical value
    r = StuckRule(steps=5, motion=1e-3)
    trips = []
    for i in range(10):
        trips.append(r.check(0.0004 * i, 0.002))
    first = next(i for i, t in enumerate(trips) if t is not None)
    assert first == 4  # values 0..4 identical: 5 identical samples, command moved 1.6 mm
    # a sensor with noise never trips
    r = StuckRule(steps=5, motion=1e-3)
    rng = np.random.default_rng(1)
    assert all(r.check(0.0004 * i, rng.normal()) is None for i in range(50))


def test_kalman_rule_and_nan_estimates():
    m = _monitor(kalman=KalmanRule(0.8, 1.2, 0.05))
    assert m.check_kalman(1, 1, 1.0, 0.02) is None
    assert m.check_kalman(1, 2, 1.25, 0.0).rule == "kalman"
    m = _monitor(kalman=KalmanRule(0.8, 1.2, 0.05))
    trip = m.check_kalman(1, 2, 1.0, -0.06)
    assert trip.rule == "kalman" and "delay" in trip.reason
    m = _monitor()
    assert m.check_kalman(1, 2, math.nan, 0.0).rule == "nan"


def test_monitor_fei_ignores_invalid_and_trips_on_valid():
    m = _monitor(fei=FEIRule(0.1, 0.01, 2))
    assert m.check_fei(0, 0, math.nan, math.nan, False) is None
    assert m.check_fei(0, 1, 1.0, 0.02, True) is None
    trip = m.check_fei(0.1, 2, 1.0, 0.02, True)
    assert trip.rule == "fei" and trip.step == 2
    event = trip.as_event()
    assert event["rule"] == "fei" and event["values"]["delay"] == pytest.approx(0.02)


def test_margin_reports_nearest_limit():
    m = _monitor()
    name, frac = m.margin(0.04, 0.1, 1e4)
    assert name == "displacement" and frac == pytest.approx(0.2)

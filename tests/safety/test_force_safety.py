"""Safety per control mode: a force channel's target and command against the force limit, its
trial and measured displacement against the displacement limit; no stuck rule on it."""

from __future__ import annotations

import math

import pytest

from rths_hil.safety import SafetyMonitor, StuckRule

DT = 1.0 / 1024.0


def _monitor(control: str) -> SafetyMonitor:
    return SafetyMonitor(
        DT,
        displacement_limit=0.05,
        velocity_limit=0.5,
        force_limit=1e5,
        stuck=StuckRule(10, 1e-4),
        control=control,
    )


@pytest.mark.parametrize("control", ["force", "load"])
def test_force_channel_command_phase(control):
    m = _monitor(control)
    # 80 kN at a 20 mm trial displacement: inside both limits (a displacement channel would
    # trip on 80 000 "m")
    assert m.check_command(0.0, 0, 8e4, 0.1, 8e4, 0.02) is None
    assert _monitor("displacement").check_command(0.0, 0, 8e4, 0.1, 8e4).rule == "displacement"
    trip = _monitor(control).check_command(0.0, 1, 8e4, 0.1, 1.2e5, 0.02)
    assert trip.rule == "force" and "commanded force" in trip.reason
    trip = _monitor(control).check_command(0.0, 1, -1.01e5, 0.1, 0.0, 0.02)
    assert trip.rule == "force" and "target force" in trip.reason
    trip = _monitor(control).check_command(0.0, 1, 8e4, 0.1, 8e4, -0.051)
    assert trip.rule == "displacement" and "trial displacement" in trip.reason
    trip = _monitor(control).check_command(0.0, 1, 8e4, 0.6, 8e4, 0.0)
    assert trip.rule == "velocity"
    trip = _monitor(control).check_command(0.0, 1, 8e4, 0.0, 8e4, math.nan)
    assert trip.rule == "nan"


def test_force_channel_feedback_phase_watches_displacement_and_force():
    m = _monitor("force")
    assert m.check_feedback(0.0, 0, True, 0, 0, 0, 5e4, 0.01, 5e4) is None
    trip = _monitor("force").check_feedback(0.0, 0, True, 0, 0, 0, 5e4, 0.06, 5e4)
    assert trip.rule == "displacement" and "measured displacement" in trip.reason
    trip = _monitor("force").check_feedback(0.0, 0, True, 0, 0, 0, 5e4, 0.01, 1.5e5)
    assert trip.rule == "force" and "measured force" in trip.reason


def test_no_stuck_rule_on_a_held_load():
    """A constant load: the set-point does not move and neither does the actuator. The stuck
    rule compares command motion with measured motion in m; on a force channel it is off."""
    m = _monitor("load")
    assert "stuck" not in m.rules and "stuck" in _monitor("displacement").rules
    for k in range(50):  # the force set-point moves (a ramp), the displacement does not
        assert m.check_feedback(k * DT, k, True, k, k, 0, 1e3 * k, 1e-4, 1e3 * k) is None
    d = _monitor("displacement")
    trips = [d.check_feedback(k * DT, k, True, k, k, 0, 1e-3 * k, 0.0, 0.0) for k in range(50)]
    assert any(t is not None and t.rule == "stuck" for t in trips)

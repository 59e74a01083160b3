"""The first-order section shared by the first-order servo model and the ``force_feedback``
effect: against scipy's own discretisation and filter, and step against whole-history."""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.effects import ForceFeedback
from rths_hil.sim_backends.first_order import FirstOrderServo
from scipy.signal import cont2discrete, lfilter

DT = 1 / 1024


def _command() -> np.ndarray:
    t = np.arange(600) * DT
    rng = np.random.default_rng(7)
    return 0.01 * np.sin(2 * np.pi * 3.0 * t) + 1e-3 * rng.standard_normal(t.size)


def _reference(gain: float, time_constant: float, x: np.ndarray) -> np.ndarray:
    """``gain / (T s + 1)`` discretised by scipy with a first-order hold, run by lfilter."""
    b, a, _ = cont2discrete(([gain], [time_constant, 1.0]), DT, method="foh")
    return lfilter(np.ravel(b), a, x)


def _stepped(model, x: np.ndarray) -> np.ndarray:
    model.reset()
    return np.array([model.step(v) for v in x])


@pytest.mark.parametrize("time_constant", [2e-3, 15e-3])
def test_servo_matches_scipy_and_steps_as_it_simulates(time_constant) -> None:
    x = _command()
    servo = FirstOrderServo(time_constant, DT)
    whole = servo.simulate(x)
    np.testing.assert_allclose(whole, _reference(1.0, time_constant, x), rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(_stepped(servo, x), whole)


def test_force_feedback_lag_and_gain_match_scipy() -> None:
    """k_h = 5e7, k_s = 2e6, c_s = 1e5: static gain k_h/(k_h+k_s), lag c_s/(k_h+k_s)."""
    k_h, k_s, c_s = 5e7, 2e6, 1e5
    eff = ForceFeedback(DT, actuator_stiffness=k_h, specimen_stiffness=k_s, specimen_damping=c_s)
    x = _command()
    whole = eff.simulate(x)
    want = _reference(k_h / (k_h + k_s), c_s / (k_h + k_s), x)
    np.testing.assert_allclose(whole, want, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(_stepped(eff, x), whole)


def test_force_feedback_without_damping_is_a_pure_gain() -> None:
    k_h, k_s = 5e7, 2e6
    eff = ForceFeedback(DT, actuator_stiffness=k_h, specimen_stiffness=k_s, specimen_damping=0.0)
    x = _command()
    np.testing.assert_allclose(eff.simulate(x), x * k_h / (k_h + k_s), rtol=1e-15)
    np.testing.assert_array_equal(_stepped(eff, x), eff.simulate(x))


def test_reset_returns_to_rest() -> None:
    servo = FirstOrderServo(5e-3, DT)
    first = [servo.step(1.0) for _ in range(5)]
    servo.reset()
    assert [servo.step(1.0) for _ in range(5)] == first

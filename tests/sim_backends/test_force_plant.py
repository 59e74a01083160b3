"""The force-controlled twin against the continuous force loop integrated independently."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.base import Plant
from rths_hil.sim_backends.first_order import FirstOrderServo
from rths_hil.sim_backends.force import ForcePlant, force_plant
from rths_hil.sim_backends.plant import Sensor
from rths_hil.sim_backends.specimen import KelvinVoigt
from rths_hil.sim_backends.twin import default_force_plant
from scipy.integrate import solve_ivp

from rths_hil.errors import InputError

DT = 1.0 / 1024.0


def _loop_reference(t, f_ref, loop_gain, k, c):
    """x(t), F(t) of ẋ = K_f (F_r − k x − c ẋ) from rest, F_r(t) given: the physics, not T."""

    def rhs(tt, y):
        return [loop_gain * (f_ref(tt) - k * y[0]) / (1.0 + loop_gain * c)]

    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0], t_eval=t, rtol=1e-10, atol=1e-14, max_step=DT / 4)
    x = sol.y[0]
    v = np.array([rhs(tt, [xx])[0] for tt, xx in zip(t, x, strict=True)])
    return x, k * x + c * v


def test_is_a_plant_in_force_mode():
    p = ForcePlant(KelvinVoigt(1.0e6, 0.0, DT))
    assert isinstance(p, Plant) and p.control == "force"
    # T = 1/(K_f k) with the default gain on a 1 MN/m spring
    assert p.time_constant == pytest.approx(1.0 / (2.0e-4 * 1.0e6))
    d = default_force_plant()
    assert d.control == "force" and d.time_constant == pytest.approx(1.0 / (2.0e-4 * 1.19e6))
    x, f = np.array([d.step(1e4) for _ in range(1024)]).T
    assert f[-1] == pytest.approx(1e4) and x[-1] == pytest.approx(1e4 / 1.19e6)
    assert np.all(f[:4] == 0.0)  # the 5 ms delay (5.12 samples, Lagrange from the 5th)


def test_steady_state_force_is_gain_times_command_and_displacement_force_over_stiffness():
    k, gain, f0 = 2.5e6, 0.97, 40e3
    p = ForcePlant(KelvinVoigt(k, 300.0, DT), loop_gain=1e-4, delay=0.012, gain=gain)
    for _ in range(2048):  # 2 s: hundreds of time constants (T = 4 ms)
        x, f = p.step(f0)
    assert f == pytest.approx(gain * f0, rel=1e-9)
    assert x == pytest.approx(gain * f0 / k, rel=1e-9)


def test_step_response_is_the_delayed_first_order_lag():
    """Steps through an integer delay: F = g F0 (1 − exp(−(t − τ)/T)) past the hold's ramp."""
    k, lg, gain, f0 = 1.0e6, 1.0e-4, 1.0, 10e3
    delay = 8 * DT
    p = ForcePlant(KelvinVoigt(k, 0.0, DT), loop_gain=lg, delay=delay, gain=gain)
    n = 200
    out = np.array([p.step(f0)[1] for _ in range(n)])
    t = np.arange(n) * DT
    T = 1.0 / (lg * k)
    # the first-order hold sees the step as a ramp over the step before it: it reaches F0 at
    # sample 0, so the response is the lag's ramp response up to then and its step response on
    assert np.all(out[:8] == 0.0)
    late = t >= delay + 2 * DT
    tau = t[late] - delay
    # ramp over [−dt, 0] then hold: y = F0 (1 − (T/dt)(1 − e^{−dt/T}) e^{−τ/T})
    ref = gain * f0 * (1.0 - (T / DT) * -math.expm1(-DT / T) * np.exp(-tau / T))
    np.testing.assert_allclose(out[late], ref, rtol=1e-9, atol=1e-9 * f0)


def test_sine_response_agrees_with_the_integrated_force_loop():
    """A 2 Hz force sine through delay, valve lag and a damped specimen vs solve_ivp."""
    k, c, lg, gain, delay, tv = 1.19e6, 114.6, 2.0e-4, 0.95, 0.0073, 0.006
    amp, w = 30e3, 2 * math.pi * 2.0
    n = 2048
    t = np.arange(n) * DT
    cmd = amp * np.sin(w * t) * np.minimum(t / 0.25, 1.0)  # ramped in: starts at rest
    p = ForcePlant(
        KelvinVoigt(k, c, DT),
        loop_gain=lg,
        delay=delay,
        gain=gain,
        dynamics=FirstOrderServo(tv, DT),
    )
    x, f = p.simulate(cmd)
    # the reference: the valve lag and the delay on the command (linear between samples, as
    # the first-order hold sees it), then the force loop's own equation
    lagged, _ = _loop_reference(t, lambda tt: np.interp(tt, t, cmd), 1.0 / tv, 1.0, 0.0)
    x_ref, f_ref = _loop_reference(
        t, lambda tt: gain * np.interp(tt - delay, t, lagged, left=0.0), lg, k, c
    )
    assert np.max(np.abs(f - f_ref)) < 2e-3 * amp
    assert np.max(np.abs(x - x_ref)) < 2e-3 * amp / k
    # the step path is the simulate path
    p.reset()
    stepped = np.array([p.step(v) for v in cmd])
    np.testing.assert_allclose(stepped[:, 1], f, rtol=1e-12, atol=1e-9)


def test_sensor_noise_is_the_displacement_twins():
    sensor = Sensor(force_noise=5.0, force_resolution=0.5, seed=3)
    p = ForcePlant(KelvinVoigt(1e6, 0.0, DT), sensor=sensor)
    _, f = p.simulate(np.full(4096, 1e4))
    tail = f[2048:]
    assert np.std(tail) == pytest.approx(5.0, rel=0.1)
    assert np.all(np.abs(tail / 0.5 - np.round(tail / 0.5)) < 1e-9)
    assert np.mean(tail) == pytest.approx(1e4, abs=0.5)


def test_force_plant_from_tables_and_refusals():
    p = force_plant(
        {
            "actuator": {"model": "servo_lag", "time_constant": 0.01, "delay": 0.005},
            "specimen": {"stiffness": 5e6, "damping": 0.0},
        },
        DT,
        1e-4,
    )
    assert p.time_constant == pytest.approx(1.0 / (1e-4 * 5e6))
    with pytest.raises(InputError, match="effects"):
        force_plant(
            {"actuator": {"delay": 0.0, "effects": [{"kind": "backlash", "width": 1e-3}]}}, DT, 1e-4
        )
    with pytest.raises(InputError, match="benchmark"):
        force_plant({"actuator": {"model": "benchmark"}}, DT, 1e-4)
    with pytest.raises(InputError, match="stiffness"):
        force_plant({"actuator": {"delay": 0.0}, "specimen": {"stiffness": 0.0}}, DT, 1e-4)
    with pytest.raises(InputError, match="loop_gain"):
        ForcePlant(KelvinVoigt(1e6, 0.0, DT), loop_gain=0.0)

"""The force-controlled twin's catalogue effects against closed forms and brute-force loops.

The references are the physics of the force loop, ``ẋ = K_f (F_r − k x)`` with the limits
acting on the piston, integrated independently (fine explicit steps or scipy), not the
twin's discrete lag.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.force import ForcePlant, force_plant
from rths_hil.sim_backends.specimen import KelvinVoigt
from scipy import signal

from rths_hil.errors import InputError

DT = 1.0 / 1024.0
K = 1.19e6
LG = 2.0e-4  # T = 4.2 ms on K


def _tables(*effects, delay=0.0):
    return {
        "actuator": {"delay": delay, "effects": [dict(e) for e in effects]},
        "specimen": {"stiffness": K, "damping": 0.0},
    }


def _brute_loop(t, f_ref, lo=-math.inf, hi=math.inf, vmax=math.inf, sub=200):
    """ẋ = clip(K_f (F_r − k x), ±vmax), x kept in [lo, hi], by explicit Euler at dt/sub.

    ``f_ref`` is sampled and taken linear between samples (the first-order hold's view).
    """
    h = DT / sub
    x = 0.0
    out = np.empty(len(t))
    out[0] = 0.0
    for i in range(1, len(t)):
        for j in range(sub):
            fr = f_ref[i - 1] + (f_ref[i] - f_ref[i - 1]) * (j / sub)
            v = min(max(LG * (fr - K * x), -vmax), vmax)
            x = min(max(x + h * v, lo), hi)
        out[i] = x
    return out


def test_offset_is_a_constant_force_error_at_steady_state():
    off = -750.0  # N
    p = force_plant(_tables({"kind": "offset", "offset": off}, delay=0.005), DT, LG)
    x, f = p.simulate(np.full(1024, 20e3))
    assert f[-1] - 20e3 == pytest.approx(off, rel=1e-9)
    assert x[-1] == pytest.approx((20e3 + off) / K, rel=1e-9)


def test_offset_and_drift_read_in_newtons_in_a_force_twin():
    p = force_plant(_tables({"kind": "offset", "offset": "2kN"}), DT, LG)
    assert p.simulate(np.zeros(512))[1][-1] == pytest.approx(2000.0, rel=1e-9)


def test_drift_is_a_ramp_error_lagged_by_delay_and_loop():
    rate, delay = 400.0, 8 * DT  # N/s, an integer delay
    p = force_plant(_tables({"kind": "drift", "rate": rate}, delay=delay), DT, LG)
    n = 2048
    _, f = p.simulate(np.full(n, 10e3))
    t = np.arange(n) * DT
    T = 1.0 / (LG * K)
    # past the transient, a first-order lag follows a ramp T behind; the drift's clock starts
    # at reset, ahead of the delay line, so the ramp arrives ``delay`` late and ``delay·rate`` up
    late = t > 0.5
    ref = 10e3 + rate * (t[late] - T)
    np.testing.assert_allclose(f[late], ref, rtol=0, atol=1e-6 * rate)


def test_servo_lag_effect_is_a_second_lag_on_the_force():
    tv = 0.01
    p = force_plant(_tables({"kind": "servo_lag", "time_constant": tv}), DT, LG)
    n = 1024
    t = np.arange(n) * DT
    cmd = 30e3 * np.sin(2 * math.pi * 3.0 * t) * np.minimum(t / 0.2, 1.0)
    _, f = p.simulate(cmd)
    T = 1.0 / (LG * K)
    sys = signal.lti([1.0], np.polymul([tv, 1.0], [T, 1.0]))
    _, ref, _ = signal.lsim(sys, cmd, t, interp=True)
    assert np.max(np.abs(f - ref)) < 2e-4 * 30e3  # measured 2.8e-5


def test_time_varying_delay_delays_the_force_reference():
    d0, amp, period = 0.010, 0.004, 0.25
    eff = {"kind": "time_varying_delay", "delay": d0, "amplitude": amp, "period": period}
    p = force_plant(_tables(eff), DT, LG)
    n = 2048
    t = np.arange(n) * DT
    w = 2 * math.pi * 1.5

    def command(tt):
        return 20e3 * np.sin(w * tt) * np.minimum(tt / 0.2, 1.0) * (tt >= 0)

    _, f = p.simulate(command(t))
    tau = d0 + amp * np.sin(2 * math.pi * t / period)
    delayed = command(t - tau)  # the exact delayed reference, then the loop's lag
    T = 1.0 / (LG * K)
    _, ref, _ = signal.lsim(signal.lti([1.0], [T, 1.0]), delayed, t, interp=True)
    assert np.max(np.abs(f - ref)) < 2e-4 * 20e3  # measured 3.3e-5
    # and it is a delay: the same loop without it is further from the reference
    _, f0 = ForcePlant(KelvinVoigt(K, 0.0, DT), LG).simulate(command(t))
    assert np.max(np.abs(f0 - ref)) > 0.05 * 20e3  # measured 0.13


def test_stroke_limit_clips_the_piston_and_the_force_follows_the_specimen():
    lim = 0.02  # m: k·lim = 23.8 kN
    p = force_plant(_tables({"kind": "stroke_limit", "limit": lim}), DT, LG)
    n = 1024
    t = np.arange(n) * DT
    cmd = 40e3 * np.sin(2 * math.pi * 2.0 * t)  # asks for ±33.6 mm
    x, f = p.simulate(cmd)
    assert np.max(np.abs(x)) == pytest.approx(lim, rel=1e-12)
    np.testing.assert_allclose(f, K * x, rtol=1e-12)  # the force is the spring's at x
    assert np.sum(np.abs(x) == lim) > 100  # held at the stops for a while
    # no wind-up: leaving the stop follows the brute-force loop with the piston at the stop
    ref = _brute_loop(t, cmd, lo=-lim, hi=lim)
    assert np.max(np.abs(x - ref)) < 2e-4 * lim  # measured 1.9e-5
    # step and simulate agree
    p.reset()
    stepped = np.array([p.step(c)[0] for c in cmd])
    np.testing.assert_array_equal(stepped, x)


def test_velocity_limit_bounds_the_displacement_rate():
    vmax = 0.05  # m/s
    p = force_plant(_tables({"kind": "velocity_limit", "limit": vmax}), DT, LG)
    n = 1024
    t = np.arange(n) * DT
    cmd = np.where(t >= 0.05, 30e3, 0.0)  # 25 mm: 0.5 s at the limit (the lag asks for 6 m/s)
    x, f = p.simulate(cmd)
    rate = np.abs(np.diff(x)) / DT
    assert np.max(rate) <= vmax * (1 + 1e-9)
    assert np.max(rate) == pytest.approx(vmax, rel=1e-9)  # it binds
    ref = _brute_loop(t, cmd, vmax=vmax)
    assert np.max(np.abs(x - ref)) < 2e-4 * 30e3 / K  # measured 1.4e-5
    assert f[-1] == pytest.approx(30e3, rel=1e-6)  # and the loop still settles on the force


@pytest.mark.parametrize("kind", ["backlash", "force_feedback"])
def test_effects_that_do_not_apply_are_refused_in_one_line(kind):
    params = {"backlash": {"width": 1e-3}, "force_feedback": {"actuator_stiffness": 1e8}}[kind]
    with pytest.raises(InputError) as info:
        force_plant(_tables({"kind": kind, **params}), DT, LG)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith("actuator.effects[0].kind: a force-controlled twin does not take")
    assert kind in msg


def test_a_model_file_path_takes_the_effects(tmp_path):
    path = tmp_path / "force.toml"
    path.write_text(
        "[actuator]\ndelay = '5ms'\n\n[[actuator.effects]]\nkind = 'offset'\noffset = 500.0\n\n"
        "[[actuator.effects]]\nkind = 'stroke_limit'\nlimit = '10mm'\n\n"
        f"[specimen]\nstiffness = {K}\ndamping = 0.0\n",
        encoding="utf-8",
    )
    p = force_plant(path, DT, LG)
    x, f = p.simulate(np.full(1024, 5e3))
    assert f[-1] == pytest.approx(5.5e3, rel=1e-9)
    x, f = p.simulate(np.full(1024, 50e3))
    assert x[-1] == pytest.approx(0.010) and f[-1] == pytest.approx(K * 0.010)


def test_every_catalogue_effect_is_taken_or_refused_by_the_force_twin():
    from rths_hil.sim_backends.effects import EFFECTS, FORCE_EFFECTS, FORCE_REFUSED

    assert set(FORCE_EFFECTS) | set(FORCE_REFUSED) == set(EFFECTS)
    assert not set(FORCE_EFFECTS) & set(FORCE_REFUSED)

"""Kalman delay/gain estimator on twins driven by SDOF responses to recorded ground motions."""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay
from rths_hil.sim_backends.modelfile import load_plant
from rths_hil.sim_backends.models import benchmark_transfer_function
from scipy import signal

from rths_hil.errors import InputError
from rths_hil.estimation import DelayGainEstimator, LinearDelayGainKF
from tests.helpers.twin_signals import FS, sdof_response

SENSOR = {"displacement_noise": 2e-5, "displacement_resolution": 1e-6}  # 20 µm rms, 1 µm steps


def _measured(u: np.ndarray, delay: float, gain: float, effects=(), seed: int = 0) -> np.ndarray:
    model = {
        "actuator": {"delay": delay, "gain": gain, "effects": list(effects)},
        "sensor": {**SENSOR, "seed": seed},
    }
    return load_plant(model, 1 / FS).simulate(u)[0]


def _onset(t: np.ndarray, u: np.ndarray) -> float:
    return float(t[np.argmax(np.abs(u) > 0.05 * np.max(np.abs(u)))])


@pytest.mark.parametrize(
    "record,fn,peak",
    [("el_centro_1940_NS_chopra_0p02", 1.0, 0.02), ("kobe_1995_nishi_akashi_NIS000", 2.0, 0.01)],
)
def test_converges_within_seconds_of_excitation(record, fn, peak):
    t, u = sdof_response(record, fn=fn, peak=peak)
    y = _measured(u, delay=0.012, gain=0.97)
    gains, delays = DelayGainEstimator(FS).run(u, y)
    after = t >= _onset(t, u) + 3.0
    assert np.max(np.abs(gains[after] / 0.97 - 1)) < 0.02
    assert np.max(np.abs(delays[after] - 0.012)) < 1e-3
    # and it is not a lucky constant: it started at the initial guess (1, 0 s)
    assert delays[10] == pytest.approx(0.0, abs=1e-3)


def test_follows_a_step_in_delay():
    t, u = sdof_response(fn=1.0, peak=0.02)
    ts = 15.0
    y = np.where(t < ts, _measured(u, 0.010, 1.02), _measured(u, 0.020, 1.02))
    gains, delays = DelayGainEstimator(FS).run(u, y)
    before = (t > 4.0) & (t < ts)
    assert np.max(np.abs(delays[before] - 0.010)) < 1e-3
    after = t >= ts + 3.0
    assert np.max(np.abs(delays[after] - 0.020)) < 1e-3
    assert np.max(np.abs(gains[after] / 1.02 - 1)) < 0.02
    # it moved promptly: half-way within one second
    assert delays[np.searchsorted(t, ts + 1.0)] > 0.015


def test_negative_delay_when_measured_leads():
    t, u = sdof_response(fn=1.0, peak=0.02)
    rng = np.random.default_rng(3)
    y = 0.99 * np.interp(t + 0.006, t, u) + 2e-5 * rng.standard_normal(len(t))
    est = DelayGainEstimator(FS, delay_range=(-0.02, 0.1))
    gains, delays = est.run(u, y)
    after = t > 4.0
    assert np.max(np.abs(delays[after] + 0.006)) < 1e-3
    assert np.max(np.abs(gains[after] / 0.99 - 1)) < 0.02
    assert est.latency == pytest.approx(21 / FS)  # look-ahead ceil(0.02·1024) samples


def test_offset_and_drift_do_not_bias_gain_and_delay():
    t, u = sdof_response(fn=1.0, peak=0.02)
    effects = [{"kind": "offset", "offset": 5e-4}, {"kind": "drift", "rate": 5e-5}]
    y = _measured(u, 0.015, 1.0, effects)
    est = DelayGainEstimator(FS)
    gains, delays = est.run(u, y)
    after = t > 4.0
    assert np.max(np.abs(delays[after] - 0.015)) < 1e-3
    assert np.max(np.abs(gains[after] - 1.0)) < 0.02
    # offset estimate refers to the measurement M samples back
    assert est.offset == pytest.approx(5e-4 + 5e-5 * (t[-1] - est.latency), abs=5e-5)
    # without the offset state the same record ruins the estimates
    _, d2 = DelayGainEstimator(FS, estimate_offset=False).run(u, y)
    assert np.max(np.abs(d2[after] - 0.015)) > 5e-3


def test_fast_path_equals_filterpy_path():
    _, u = sdof_response(fn=1.0, peak=0.02, duration=4.0)
    y = _measured(u, 0.012, 0.97)
    fast = DelayGainEstimator(FS, backend="fast")
    ref = DelayGainEstimator(FS, backend="filterpy")
    gf, df = fast.run(u, y)
    gr, dr = ref.run(u, y)
    np.testing.assert_allclose(gf, gr, rtol=1e-9)
    np.testing.assert_allclose(df, dr, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.P, ref.P, rtol=1e-6, atol=1e-18)


def test_benchmark_plant_estimate_matches_its_phase_delay():
    # the RTHS benchmark plant is not a pure delay; at the structure's frequency the EKF
    # should report the plant's amplitude and phase delay (continuous transfer function)
    t, u = sdof_response(fn=1.0, peak=0.02)
    model = {"actuator": {"model": "benchmark"}, "sensor": {"displacement_noise": 1.6e-5}}
    y = load_plant(model, 1 / FS).simulate(u)[0]
    gains, delays = DelayGainEstimator(FS).run(u, y)
    num, den = benchmark_transfer_function()
    _, h = signal.freqs(num, den, worN=[2 * np.pi * 1.0])
    after = t > 4.0
    assert np.median(delays[after]) == pytest.approx(-np.angle(h[0]) / (2 * np.pi), abs=1e-3)
    assert np.median(gains[after]) == pytest.approx(abs(h[0]), rel=0.02)


@pytest.mark.parametrize("f,tau", [(2.0, 0.040), (1.0, 0.020)])
def test_first_order_regression_bias_versus_ekf(f, tau):
    """Closed form of the linear model's bias: ĝ = cos ωτ, τ̂ = tan(ωτ)/ω; the EKF has none."""
    t = np.arange(int(12 * FS)) / FS
    u = 0.01 * np.sin(2 * np.pi * f * t)
    y = fractional_delay(u, tau, FS) + 1e-5 * np.random.default_rng(0).standard_normal(len(t))
    w = 2 * np.pi * f
    gl, dl = LinearDelayGainKF(FS).run(u, y)
    assert gl[-1] == pytest.approx(np.cos(w * tau), abs=2e-3)
    assert dl[-1] == pytest.approx(np.tan(w * tau) / w, abs=2e-4)
    ge, de = DelayGainEstimator(FS).run(u, y)
    assert ge[-1] == pytest.approx(1.0, abs=2e-3)
    assert de[-1] == pytest.approx(tau, abs=1e-4)


def test_filterpy_style_steps_and_properties():
    est = DelayGainEstimator(FS, gain0=1.1, delay0=0.005)
    assert est.gain == 1.1 and est.delay == 0.005 and est.offset == 0.0
    p0 = est.P.copy()
    est.predict()
    assert np.all(np.diag(est.P) > np.diag(p0))
    est.push(0.0, 0.0)
    assert est.correct() is False  # warming up
    assert est.std.shape == (3,)
    assert DelayGainEstimator(FS, estimate_offset=False).x.shape == (2,)


def test_bad_arguments():
    with pytest.raises(InputError, match="fs"):
        DelayGainEstimator(0.0)
    with pytest.raises(InputError, match="delay0"):
        DelayGainEstimator(FS, delay0=0.5)
    with pytest.raises(InputError, match="delay_range"):
        DelayGainEstimator(FS, delay_range=(0.1, 0.0))
    with pytest.raises(InputError, match="backend"):
        DelayGainEstimator(FS, backend="numba")
    with pytest.raises(InputError, match="equal length"):
        DelayGainEstimator(FS).run(np.zeros(10), np.zeros(11))

"""Inverse compensation and adaptive α against independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay
from scipy.signal import lfilter

from rths_hil.compensators.inverse import AdaptiveAlpha, InverseCompensator, alpha_for_delay
from rths_hil.errors import InputError

FS = 1024.0
DT = 1 / FS


def _run(comp, x):
    return np.array([comp.step(v) for v in x])


def test_step_equals_fir_filter_reference():
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(0, 1e-4, 3000))
    for alpha, amp in [(1.0, 1.0), (13.7, 1.0), (29.0, 0.97)]:
        y = _run(InverseCompensator(alpha, amp), x)
        ref = lfilter([amp * alpha, -amp * (alpha - 1)], [1.0], x)
        np.testing.assert_allclose(y, ref, rtol=0, atol=1e-15)


def test_disabled_and_alpha_one_are_identity():
    x = np.sin(np.linspace(0, 20, 500))
    np.testing.assert_array_equal(_run(InverseCompensator(30.0, 1.2, enabled=False), x), x)
    np.testing.assert_allclose(_run(InverseCompensator(1.0), x), x, atol=1e-16)


def test_steady_state_sine_matches_closed_form_frequency_response():
    f, alpha = 0.77, 26.6
    w = 2 * math.pi * f
    n = np.arange(int(20 * FS))
    x = np.sin(w * n * DT)
    y = _run(InverseCompensator(alpha), x)
    h = alpha - (alpha - 1) * np.exp(-1j * w * DT)  # z-transform at z = e^{iωΔt}
    ref = np.abs(h) * np.sin(w * n * DT + np.angle(h))
    np.testing.assert_allclose(y[1:], ref[1:], atol=1e-12)


@pytest.mark.parametrize("delay", [0.010, 0.025, 0.040])
def test_alpha_for_delay_cancels_a_pure_delay_at_structural_frequencies(delay):
    # command through a pure (fractional) delay: the measured signal vs the target
    alpha = alpha_for_delay(delay, DT)
    assert alpha == pytest.approx(1 + delay * FS)
    f = 0.77
    w = 2 * math.pi * f
    t = np.arange(int(30 * FS)) * DT
    x = np.sin(w * t)
    meas = fractional_delay(_run(InverseCompensator(alpha), x), delay, FS)
    # fit the phase of the measured sinusoid over the settled part (least squares)
    sl = slice(int(5 * FS), None)
    basis = np.column_stack([np.sin(w * t[sl]), np.cos(w * t[sl])])
    (c_s, c_c), *_ = np.linalg.lstsq(basis, meas[sl], rcond=None)
    residual_delay = -math.atan2(c_c, c_s) / w
    # closed form: the compensator's phase lead is arg H(e^{iωΔt}), H = α − (α−1)e^{−iωΔt}
    h = alpha - (alpha - 1) * np.exp(-1j * w * DT)
    assert residual_delay == pytest.approx(delay - np.angle(h) / w, abs=1e-6)
    # linear extrapolation leaves about (ωτ)³/(3ω) of the delay uncompensated (Taylor of atan)
    assert 0 < residual_delay <= w**2 * delay**3 / 3 * 1.1 + 1e-6
    # without compensation the delay is the full τ
    meas0 = fractional_delay(x, delay, FS)
    (c_s, c_c), *_ = np.linalg.lstsq(basis, meas0[sl], rcond=None)
    assert -math.atan2(c_c, c_s) / w == pytest.approx(delay, abs=1e-6)


def test_bad_parameters_are_input_errors():
    for args in [(0.5, 1.0), (math.nan, 1.0), (2.0, 0.0), (2.0, -1.0)]:
        with pytest.raises(InputError):
            InverseCompensator(*args)
    comp = InverseCompensator(5.0)
    with pytest.raises(InputError):
        AdaptiveAlpha(comp, DT, pair="foo")
    with pytest.raises(InputError):
        AdaptiveAlpha(comp, DT, alpha_min=10, alpha_max=5)
    with pytest.raises(InputError):
        AdaptiveAlpha(comp, DT, time_constant=0)


def test_adaptive_target_pair_converges_with_first_order_closed_form():
    tau, T = 0.025, 2.0
    comp = InverseCompensator(1.0)
    ad = AdaptiveAlpha(comp, DT, "target", time_constant=T, rate=1e9, alpha_max=1e3)
    goal = 1 + tau / DT
    n = int(6 * FS)
    hist = np.empty(n)
    for i in range(n):
        residual = tau - (comp.alpha - 1) * DT  # ideal residual delay of measured vs target
        hist[i] = ad.update(residual, True)
    k = np.arange(1, n + 1)
    ref = goal - (goal - 1.0) * (1 - DT / T) ** k
    np.testing.assert_allclose(hist, ref, rtol=1e-9)


def test_adaptive_command_pair_goal_and_rate_limit_and_bounds():
    tau = 0.030
    comp = InverseCompensator(1.0)
    ad = AdaptiveAlpha(comp, DT, "command", time_constant=0.01, rate=4.0, alpha_max=25.0)
    prev = comp.alpha
    steps = []
    for _ in range(int(10 * FS)):
        a = ad.update(tau, True)
        steps.append(a - prev)
        prev = a
    assert max(steps) <= 4.0 * DT + 1e-12  # rate limit 4 per second
    assert steps[0] == pytest.approx(4.0 * DT)  # far from the goal: rate limited
    assert comp.alpha == 25.0  # goal 1 + τ/Δt = 31.7 is above the upper bound
    ad.alpha_max = 100.0
    for _ in range(int(5 * FS)):
        ad.update(tau, True)
    assert comp.alpha == pytest.approx(1 + tau / DT, abs=1e-6)


def test_adaptive_ignores_invalid_and_non_finite_estimates():
    comp = InverseCompensator(10.0)
    ad = AdaptiveAlpha(comp, DT, "target", time_constant=1.0, rate=100.0)
    for d, v in [(0.01, False), (math.nan, True), (math.inf, True), (-math.inf, True)]:
        assert ad.update(d, v) == 10.0
    assert ad.update(0.01, True) == pytest.approx(10.0 + 0.01 / DT * DT / 1.0)

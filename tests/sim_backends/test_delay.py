"""Actuator block model of the FEI paper's Fig. 4.1: fractional delay + gain, exactness checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.delay import DelayGain, FractionalDelay, fractional_delay, lagrange_taps

FS = 1024.0
RNG = np.random.default_rng(11)
FREQS = np.array([0.37, 1.0, 2.9, 5.3, 11.0, 19.5])  # Hz, band-limited to 20 Hz
AMPS = RNG.uniform(0.2, 1.0, FREQS.size)
PHASES = RNG.uniform(0, 2 * np.pi, FREQS.size)


def _tones(t: np.ndarray) -> np.ndarray:
    return np.sum(AMPS[:, None] * np.sin(2 * np.pi * FREQS[:, None] * t + PHASES[:, None]), axis=0)


def _lagrange_bound(delay_samples: float) -> float:
    """Lagrange remainder |f⁗|max/4!·∏|D'−k|·Δt⁴, with |f⁗| ≤ Σ a·(2πf)⁴ (independent of taps)."""
    n0 = max(math.floor(delay_samples) - 1, 0)
    frac = delay_samples - n0
    prod = abs(np.prod([frac - k for k in range(4)]))
    d4 = np.sum(AMPS * (2 * np.pi * FREQS / FS) ** 4)
    return prod / 24 * d4


@pytest.mark.parametrize("delay_s", [0.3e-3, 1e-3, 5e-3, 12.7e-3, 45e-3])
def test_fractional_delay_exact_on_band_limited_tones(delay_s):
    t = np.arange(int(20 * FS)) / FS
    x = _tones(t)
    y = fractional_delay(x, delay_s, FS)
    ref = _tones(t - delay_s)
    settled = t > delay_s + 4 / FS  # after the filter has seen 4 samples of real history
    err = np.max(np.abs(y[settled] - ref[settled]))
    bound = _lagrange_bound(delay_s * FS)
    assert err <= bound * 1.0001 + 1e-14
    # and it is small in absolute terms: far below a whole-sample rounding of the delay
    rounded = np.interp(t - round(delay_s * FS) / FS, t, x)
    assert err < 1e-3 * np.max(np.abs(rounded[settled] - ref[settled])) or err < 1e-7


def test_fractional_delay_exact_on_band_limited_noise():
    """A periodic random signal band-limited to 10 Hz, delayed exactly by an FFT phase shift."""
    n = 8192
    spec = np.zeros(n // 2 + 1, complex)
    kmax = int(10 * n / FS)
    spec[1:kmax] = RNG.normal(size=kmax - 1) + 1j * RNG.normal(size=kmax - 1)
    x = np.fft.irfft(spec, n)
    delay_s = 1e-3
    f = np.fft.rfftfreq(n, 1 / FS)
    x_delayed = np.fft.irfft(spec * np.exp(-2j * np.pi * f * delay_s), n)
    y = fractional_delay(np.tile(x, 2), delay_s, FS)[n:]  # second period: no start-up
    rel = np.sqrt(np.mean((y - x_delayed) ** 2) / np.mean(x**2))
    assert rel < 1e-7
    # the error of simply rounding the delay to one sample is ~ 2π·f·(0.024 ms): 1e-3 scale
    assert np.sqrt(np.mean((np.roll(x, 1) - x_delayed) ** 2) / np.mean(x**2)) > 1e-4


@pytest.mark.parametrize("samples", [0, 1, 2, 3, 7])
def test_integer_delays_are_pure_shifts(samples):
    x = RNG.normal(size=200)
    y = fractional_delay(x, samples / FS, FS)
    ref = np.concatenate([np.zeros(samples), x[: x.size - samples]])
    np.testing.assert_allclose(y, ref, atol=1e-12)


def test_taps_interpolate_polynomials_exactly():
    """Order-3 Lagrange: exact for cubic signals, whatever the fractional delay."""
    k = np.arange(50.0)
    x = 0.5 - 0.2 * k + 0.03 * k**2 - 0.001 * k**3
    for d in (0.25, 1.5, 2.71, 6.02):
        n0, taps = lagrange_taps(d)
        y = sum(taps[j] * x[10 - n0 - j] for j in range(4))
        kk = 10 - d
        assert y == pytest.approx(0.5 - 0.2 * kk + 0.03 * kk**2 - 0.001 * kk**3, rel=1e-12)
    assert np.sum(lagrange_taps(3.3)[1]) == pytest.approx(1.0)


def test_streaming_equals_offline():
    x = RNG.normal(size=3000)
    for d in (0.4e-3, 5e-3):
        line = FractionalDelay(d, FS)
        y = np.array([line.step(v) for v in x])
        np.testing.assert_allclose(y, fractional_delay(x, d, FS), rtol=1e-12, atol=1e-14)


def test_delay_gain_block_is_gain_times_delayed_target():
    t = np.arange(int(10 * FS)) / FS
    x = _tones(t)
    act = DelayGain(delay=5e-3, gain=1.1, dt=1 / FS)
    y = act.simulate(x)
    settled = t > 0.01
    err = np.max(np.abs(y[settled] - 1.1 * _tones(t[settled] - 5e-3)))
    assert err <= 1.1 * _lagrange_bound(5e-3 * FS) * 1.0001
    act.reset()
    stepped = np.array([act.step(v) for v in x])
    np.testing.assert_allclose(stepped, y, rtol=1e-12, atol=1e-14)


def test_negative_delay_rejected():
    with pytest.raises(ValueError):
        fractional_delay(np.ones(10), -1e-3, FS)

"""Tracking metrics J1–J3 and TI against closed forms for sinusoids."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rths_hil import metrics
from rths_hil.errors import InputError
from sim_backends.delay import fractional_delay

FS = 1024.0
T = np.arange(int(20 * FS)) / FS


@pytest.mark.parametrize("delay", [0.0, 0.0042, 0.0137, -0.008])
def test_j1_recovers_fractional_delay_with_sign(delay):
    rng = np.random.default_rng(1)
    x = np.convolve(rng.standard_normal(T.size), np.hanning(64), "same")
    if delay >= 0:
        y = fractional_delay(x, delay, FS)
    else:  # measured leads: the target is the delayed one
        y, x = x, fractional_delay(x, -delay, FS)
    assert metrics.j1_delay(x, y, FS, max_lag_s=0.05) == pytest.approx(delay, abs=1e-4)


def test_j1_respects_lag_range():
    rng = np.random.default_rng(2)
    x = np.convolve(rng.standard_normal(T.size), np.hanning(128), "same")
    y = fractional_delay(x, 0.1, FS)
    assert metrics.j1_delay(x, y, FS, max_lag_s=0.2) == pytest.approx(0.1, abs=1e-3)
    assert abs(metrics.j1_delay(x, y, FS, max_lag_s=0.05)) <= 0.05 + 1e-9


def test_j2_j3_closed_forms():
    a, w, tau, g = 0.02, 2 * np.pi * 1.0, 0.01, 1.05
    x = a * np.sin(w * T)
    y = g * a * np.sin(w * (T - tau))
    # |g e^{-jωτ} − 1| is the ratio of error amplitude to target amplitude for both.
    ratio = abs(g * np.exp(-1j * w * tau) - 1)
    assert metrics.j2_nrms(x, y) == pytest.approx(100 * ratio, rel=1e-3)
    assert metrics.j3_peak(x, y) == pytest.approx(100 * ratio, rel=1e-3)
    assert metrics.j2_nrms(x, x) == 0.0
    assert math.isnan(metrics.j2_nrms(np.zeros(10), np.ones(10)))


@pytest.mark.parametrize("tau", [0.005, -0.005, 0.02])
def test_tracking_indicator_per_cycle(tau):
    a, f = 0.01, 2.0
    w = 2 * np.pi * f
    x = a * np.sin(w * T)
    y = a * np.sin(w * (T - tau))
    cycles = T[-1] * f
    expected = math.pi * a * a * math.sin(w * tau) * cycles
    assert metrics.tracking_indicator(x, y) == pytest.approx(expected, rel=2e-3)
    # A pure gain error encloses no area.
    assert abs(metrics.tracking_indicator(x, 1.2 * x)) < 1e-12
    running = metrics.tracking_indicator(x, y, cumulative=True)
    assert running.shape == x.shape and running[0] == 0.0


def test_bad_pairs():
    with pytest.raises(InputError, match="equal length"):
        metrics.j2_nrms(np.zeros(5), np.zeros(6))
    with pytest.raises(InputError, match="max_lag_s"):
        metrics.j1_delay(np.ones(5), np.ones(5), FS, max_lag_s=0)


@pytest.mark.parametrize("delay", [0.0061, 0.02])
def test_j1_on_a_short_building_up_transient(delay):
    """6 s of a growing SDOF response: the strongest part sits at the end of the record."""
    from rths_hil.groundmotion import default_record
    from rths_hil.structure import simulate_sdof

    ag = default_record().resampled(FS).accel[: int(6 * FS)]
    x = simulate_sdof(ag, FS, 0.77, 0.02)
    y = fractional_delay(x, delay, FS)
    assert metrics.j1_delay(x, y, FS) == pytest.approx(delay, abs=2e-4)

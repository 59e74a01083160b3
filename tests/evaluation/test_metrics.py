"""Tracking metrics J1–J3 and TI against closed forms for sinusoids."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay
from scipy.signal import fftconvolve

from rths_hil import metrics
from rths_hil.errors import InputError

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
    from rths_hil.structures.sdof import simulate_sdof

    ag = default_record().resampled(FS).accel[: int(6 * FS)]
    x = simulate_sdof(ag, FS, 0.77, 0.02)
    y = fractional_delay(x, delay, FS)
    assert metrics.j1_delay(x, y, FS) == pytest.approx(delay, abs=2e-4)


# -- J1–J9: the benchmark's evaluation script and the paper's definitions -----------------------


def _f4_evaluation(x_m, num_resp, ref_resp, dt_rths):
    """numpy transcription of the RTHS benchmark's F4_evaluation.m, lines 11–39, statement by
    statement (MATLAB corr = Pearson correlation, std with N−1, round halves away from zero)."""
    from decimal import ROUND_HALF_UP, Decimal

    def mround(v):
        if not math.isfinite(v):
            return v
        return float(Decimal(v).quantize(Decimal(1), rounding=ROUND_HALF_UP))

    def corr(a, b):
        return np.corrcoef(a, b)[0, 1]

    def std(v):
        return np.std(v, ddof=1)

    n_rows = x_m.shape[0]
    N = np.arange(1, 51)
    r1 = np.zeros(50)
    for jj in N:
        r1[jj - 1] = corr(x_m[jj - 1 :, 0], num_resp[: n_rows - jj + 1, 0])
    I = int(np.argmax(r1))  # noqa: E741 - the script's name
    del1 = (N - 1) * dt_rths
    J = [0.0] * 10
    J[1] = mround(10000 * del1[I]) / 10
    J[2] = mround(10000 * std(x_m[:, 0] - num_resp[:, 0]) / std(num_resp[:, 0])) / 100
    J[3] = mround(10000 * max(abs(x_m[:, 0] - num_resp[:, 0])) / max(abs(num_resp[:, 0]))) / 100
    J[4] = mround(10000 * (std(x_m[:, 0] - ref_resp[:, 0]) / std(ref_resp[:, 0]))) / 100
    J[5] = mround(10000 * max(abs(x_m[:, 0] - ref_resp[:, 0])) / max(abs(ref_resp[:, 0]))) / 100
    J[6] = mround(10000 * (std(num_resp[:, 1] - ref_resp[:, 1]) / std(ref_resp[:, 1]))) / 100
    J[7] = mround(10000 * (std(num_resp[:, 2] - ref_resp[:, 2]) / std(ref_resp[:, 2]))) / 100
    J[8] = (
        mround(10000 * max(abs(num_resp[:, 1] - ref_resp[:, 1])) / max(abs(ref_resp[:, 1]))) / 100
    )
    J[9] = (
        mround(10000 * max(abs(num_resp[:, 2] - ref_resp[:, 2])) / max(abs(ref_resp[:, 2]))) / 100
    )
    return {f"J{i}": J[i] for i in range(1, 10)}


def _three_floors(fs, seconds=12.0, seed=5):
    """A band-limited 3-floor reference response and a slightly different numerical one (m)."""
    rng = np.random.default_rng(seed)
    n = int(seconds * fs)
    t = np.arange(n) / fs
    base = fftconvolve(rng.standard_normal(n), np.hanning(int(0.25 * fs)), "same")
    base *= 0.01 / np.max(np.abs(base)) * np.minimum(t / 1.0, 1.0)
    ref = np.column_stack([base, 1.8 * base, 2.3 * base])
    num = ref * np.array([1.0, 1.04, 0.97]) + 1e-4 * np.sin(2 * np.pi * 1.3 * t)[:, None]
    return num, ref


@pytest.mark.parametrize(
    "fs,delay,offset,j1_ms",
    [
        (4096.0, 0.010, 0.0, 10.0),  # 40.96 samples → lag 41 → 10.009 ms → 10.0
        (4096.0, 0.015, 0.0, 12.0),  # beyond 49 samples: tops out at 11.96 → 12.0
        (4096.0, -0.003, 0.0, 0.0),  # a lead cannot be reported
        (4096.0, 0.004, 2e-4, 3.9),  # 0.2 mm offset: std and RMS differ
        (1024.0, 32 / 1024, 0.0, 31.3),  # 312.5 → MATLAB rounds the half up (numpy: 312)
    ],
)
def test_benchmark_criteria_equal_transcription_of_f4_evaluation(fs, delay, offset, j1_ms):
    num, ref = _three_floors(fs)
    x_m = fractional_delay(num[:, 0], delay, fs) if delay >= 0 else None
    if x_m is None:  # measured leads the target
        x_m = np.concatenate([num[round(-delay * fs) :, 0], np.zeros(round(-delay * fs))])
    x_m = 1.01 * x_m + offset
    expected = _f4_evaluation(x_m[:, None], num, ref, 1.0 / fs)
    got = metrics.benchmark_criteria(num, x_m, fs, ref)
    assert got == expected
    assert got["J1"] == j1_ms


def test_offset_separates_std_from_rms_and_numbering_differs():
    fs = 4096.0
    num, ref = _three_floors(fs)
    x_m = num[:, 0] + 2e-4
    bench = metrics.benchmark_criteria(num, x_m, fs, ref)
    paper = metrics.criteria(num, x_m, fs, ref)
    # std removes the offset entirely; the RMS of Eq. 13 sees it
    assert bench["J2"] == 0.0
    rms = np.sqrt(np.mean(num[:, 0] ** 2))
    assert paper["J2"] == pytest.approx(100 * 2e-4 / rms, rel=1e-9)
    # the script's J5 is the paper's J7 (floor-1 peak), its J6/J7 the paper's J5/J6
    assert bench["J5"] == pytest.approx(paper["J7"], abs=0.005)
    assert bench["J8"] == pytest.approx(paper["J8"], abs=0.005)
    e2 = num[:, 1] - ref[:, 1]
    assert paper["J5"] == pytest.approx(
        100 * np.sqrt(np.mean(e2**2)) / np.sqrt(np.mean(ref[:, 1] ** 2)), rel=1e-12
    )
    # the project's J1 is signed and sub-sample where the script's is neither
    lead = np.concatenate([num[12:, 0], np.zeros(12)])
    assert metrics.criteria(num, lead, fs, ref)["J1"] == pytest.approx(-12 / fs, abs=1e-4)
    assert metrics.benchmark_criteria(num, lead, fs, ref)["J1"] == 0.0


def test_criteria_sdof_has_nan_upper_floors():
    fs = 1024.0
    num, ref = _three_floors(fs)
    got = metrics.criteria(num[:, 0], num[:, 0] * 1.02, fs, ref[:, 0])
    assert got["J4"] == pytest.approx(metrics.nrms_error(num[:, 0] * 1.02, ref[:, 0]))
    assert all(math.isnan(got[k]) for k in ("J5", "J6", "J8", "J9"))
    b = metrics.benchmark_criteria(num[:, 0], num[:, 0] * 1.02, fs, ref[:, 0])
    assert all(math.isnan(b[k]) for k in ("J6", "J7", "J8", "J9"))
    with pytest.raises(InputError, match="floors"):
        metrics.benchmark_criteria(np.zeros((10, 4)), np.zeros(10), fs)

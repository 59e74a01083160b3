"""Sliding-DFT engine of the exact online FEI against per-window FFTs written from Eq. 2.1–2.4."""

from __future__ import annotations

import numpy as np
import pytest

from rths_hil import fei as F
from rths_hil.fei.sliding import SlidingSums
from tests.helpers.fei_refs import brute_lowband, brute_sums, random_walk_pair


@pytest.mark.parametrize("N", [96, 128, 250])
def test_sliding_sums_match_direct_dft_over_many_resyncs(N):
    # 12 windows long: the states are advanced ~N times between resyncs and resynced 11 times
    L = 12 * N + 17
    x, y = random_walk_pair(L, N)
    s = SlidingSums(N, hop=1)
    cuts = np.sort(np.random.default_rng(1).choice(np.arange(1, L), 40, replace=False))
    rows, ends = [], []
    for a, b in zip(np.split(x, cuts), np.split(y, cuts), strict=True):
        r, e = s.process(a, b)
        rows.append(r.copy())
        ends.append(e.copy())
    rows = np.concatenate(rows)
    ends = np.concatenate(ends)
    np.testing.assert_array_equal(ends, np.arange(N - 1, L))
    worst = 0.0
    for j in range(0, ends.size, 5):
        E, Fk, S = brute_sums(x, y, int(ends[j]), N)
        worst = max(
            worst,
            abs(rows[j, 0] - E) / E,
            abs(rows[j, 1] - Fk) / Fk,
            abs(complex(rows[j, 2], rows[j, 3]) - S) / abs(S),
        )
    assert worst < 1e-10


def test_without_resync_the_recursion_drifts_and_resync_bounds_it():
    N = 128
    L = 400 * N
    x, y = random_walk_pair(L, 5)
    x = x * 1e3  # large values make the round-off of the removals visible
    y = y * 1e3
    # hop L − N: windows end at N − 1 and at L − 1 (the one checked)
    drift = SlidingSums(N, hop=L - N, resync=10**12)  # never resynchronised
    synced = SlidingSums(N, hop=L - N)
    (r_drift, e1), (r_sync, e2) = drift.process(x, y), synced.process(x, y)
    E, _, _ = brute_sums(x, y, L - 1, N)
    assert e1[-1] == e2[-1] == L - 1
    err_sync = abs(r_sync[-1, 0] - E) / E
    err_drift = abs(r_drift[-1, 0] - E) / E
    assert err_sync < 1e-11
    assert err_drift > 10 * err_sync


@pytest.mark.parametrize("window_s", [0.8, 1.0])  # N = 205 (M = 256) and N = M = 256
def test_online_exact_hop1_is_sliding_and_equals_batch(window_s):
    fs = 256.0
    t = np.arange(int(20 * fs)) / fs
    rng = np.random.default_rng(2)
    x = 0.01 * np.sin(2 * np.pi * 1.3 * t) * (1 + 0.5 * np.sin(0.4 * t)) + 1e-4 * (
        rng.standard_normal(t.size)
    )
    y = 0.97 * np.interp(t - 0.012, t, x)
    online = F.OnlineFEI(fs, window_s, hop=1, method="exact")
    assert online._slide is not None
    one_by_one = [online.push(a, b) for a, b in zip(x, y, strict=True)]
    batch = F.moving_fei(x, y, fs, window_s)
    got = [r for r in one_by_one if r is not None]
    assert len(got) == batch.amplitude.size
    amp = np.array([g[0] for g in got])
    delay = np.array([g[1] for g in got])
    valid = np.array([g[3] for g in got])
    np.testing.assert_array_equal(valid, batch.valid)
    np.testing.assert_allclose(amp, batch.amplitude, rtol=1e-9)
    np.testing.assert_allclose(delay, batch.delay, rtol=1e-8, atol=1e-12)
    # and the block path gives the same windows (same sums; the scalar finish of push may
    # differ from the vectorised one in the last bit)
    blocks = F.OnlineFEI(fs, window_s, hop=1, method="exact")
    parts = [blocks.update(x[i : i + 777], y[i : i + 777]) for i in range(0, x.size, 777)]
    joined = F.MovingFEIResult.concatenate(parts)
    np.testing.assert_array_equal(joined.valid, valid)
    np.testing.assert_allclose(joined.amplitude[valid], amp[valid], rtol=1e-14)
    np.testing.assert_allclose(joined.delay[valid], delay[valid], rtol=1e-13)


def test_large_hops_keep_the_fft_path():
    assert F.OnlineFEI(256.0, 1.0, hop=F.SLIDING_MAX_HOP + 1)._slide is None
    assert F.OnlineFEI(256.0, 1.0, hop=F.SLIDING_MAX_HOP)._slide is not None
    assert F.OnlineFEI(256.0, 1.0, method="streaming")._slide is None


@pytest.mark.parametrize("N, K0", [(100, 7), (101, 7), (128, 10), (203, 13), (300, 20)])
def test_lowband_sums_match_direct_dft_over_many_resyncs(N, K0):
    from rths_hil.fei.sliding import LB_RESYNC_WINDOWS, LowBandSums

    period = LB_RESYNC_WINDOWS * N
    L = 3 * period + 11  # three resynchronisations
    x, y = random_walk_pair(L, K0)
    lb = LowBandSums(N, K0, hop=3)
    rows = np.concatenate([lb.process(x[i : i + 97], y[i : i + 97]) for i in range(0, L, 97)])
    np.testing.assert_array_equal(rows[:, 4], np.arange(N - 1, L, 3))
    # the same stream in other cuts (one sample, odd blocks, all at once): identical rows
    for cuts in ([1] * 500 + [L], [7, 1000, 333, L], [L]):
        other = LowBandSums(N, K0, hop=3)
        parts, pos = [], 0
        for c in cuts:
            parts.append(other.process(x[pos : pos + c], y[pos : pos + c]))
            pos += c
        np.testing.assert_array_equal(np.concatenate(parts), rows)
    # every 8th window, and the windows around each resynchronisation
    ends = rows[:, 4].astype(int)
    near = np.zeros(len(rows), bool)
    for k in range(1, 4):
        near |= np.abs(ends - k * period) < 12
    worst = 0.0
    for r in rows[(np.arange(len(rows)) % 8 == 0) | near]:
        E, Fk, S = brute_lowband(x, y, int(r[4]), N, K0)
        worst = max(
            worst, abs(r[0] - E) / E, abs(r[1] - Fk) / Fk, abs(complex(r[2], r[3]) - S) / abs(S)
        )
    assert worst < 1e-10

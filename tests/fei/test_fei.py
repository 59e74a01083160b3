"""FEI engine: exactness against a brute-force DFT of the FEI paper's Eq. 2.1–2.5, recovery of known
delay/gain, sign conventions, moving windows, online = batch, streaming vs exact."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay

from rths_hil import fei as F
from rths_hil.errors import InputError
from rths_hil.groundmotion import bundled_path, load
from rths_hil.structures.sdof import simulate_sdof

FS = 1024.0


def brute_fei(target, measured, fs):
    """The FEI paper's Eq. 2.1–2.5 written out with an explicit DFT sum (no FFT, no shortcuts)."""
    x = np.asarray(target, float)
    y = np.asarray(measured, float)
    n = x.size
    M = 1
    while M < n:
        M *= 2
    p = M // 2
    w = np.array([0.5 - 0.5 * math.cos(2 * math.pi * i / (n - 1)) for i in range(n)])
    xw = w * (x - x.mean())
    yw = w * (y - y.mean())
    idx = np.arange(n)
    num = 0j
    den = 0.0
    fnum = 0.0
    for k in range(1, p):
        e = np.exp(-2j * math.pi * k * idx / M)
        X = np.sum(xw * e)
        Y = np.sum(yw * e)
        num += Y * np.conj(X)  # y_o / y_I · |y_I|² without division
        den += abs(X) ** 2
        fnum += abs(X) ** 2 * k * fs / M
    fei = num / den
    amp = abs(fei)
    phase = math.atan2(fei.imag, fei.real)
    f_eq = fnum / den
    return amp, phase, f_eq, -phase / (2 * math.pi * f_eq)


def sdof_pair(record: str, fn: float, delay: float, gain: float, bouc_wen=False, seconds=None):
    gm = load(bundled_path(record)).resampled(FS)
    ag = gm.accel if seconds is None else gm.accel[: int(seconds * FS)]
    x = simulate_sdof(ag, FS, fn, 0.02, bouc_wen=bouc_wen)
    return x, gain * fractional_delay(x, delay, FS)


@pytest.mark.parametrize("n", [8, 37, 64, 200])
def test_fei_matches_brute_force_dft(n):
    rng = np.random.default_rng(n)
    x = rng.standard_normal(n) + 2.0
    y = 0.8 * np.roll(x, 1) + 0.3 * rng.standard_normal(n) - 1.0
    r = F.fei(x, y, 100.0)
    a, ph, feq, d = brute_fei(x, y, 100.0)
    assert r.valid
    assert r.amplitude == pytest.approx(a, rel=1e-10)
    assert r.phase == pytest.approx(ph, rel=1e-9, abs=1e-12)
    assert r.f_eq == pytest.approx(feq, rel=1e-10)
    assert r.delay == pytest.approx(d, rel=1e-9, abs=1e-12)


def test_multisine_delay_and_gain_recovered():
    t = np.arange(int(40 * FS)) / FS
    freqs, amps = [0.7, 1.3, 2.9], [1.0, 0.6, 0.3]
    x = sum(a * np.sin(2 * np.pi * f * t + f) for f, a in zip(freqs, amps, strict=True)) * 1e-2
    for delay, gain in [(0.005, 1.1), (0.02, 0.9), (-0.008, 1.0)]:
        shifted = sum(
            a * np.sin(2 * np.pi * f * (t - delay) + f) for f, a in zip(freqs, amps, strict=True)
        )
        r = F.fei(x, gain * 1e-2 * shifted, FS)
        # Closed form for well-separated tones: power-weighted mean of the per-tone responses.
        p = np.square(amps)
        f = np.asarray(freqs)
        mean = gain * np.sum(p * np.exp(-2j * np.pi * f * delay)) / p.sum()
        f_eq = np.sum(p * f) / p.sum()
        assert r.amplitude == pytest.approx(abs(mean), rel=1e-3)
        assert r.f_eq == pytest.approx(f_eq, rel=5e-3)
        assert r.delay == pytest.approx(-np.angle(mean) / (2 * np.pi * f_eq), rel=5e-3)
        assert r.delay == pytest.approx(delay, rel=0.02)


def test_sdof_delay_and_gain_recovered_whole_record():
    x, y = sdof_pair("el_centro_1940_NS_chopra_0p02.csv", 1.0, 0.005, 1.1)
    r = F.fei(x, y, FS)
    assert r.amplitude == pytest.approx(1.1, rel=1e-3)
    assert r.delay == pytest.approx(0.005, abs=2e-5)
    assert r.f_eq == pytest.approx(1.0, rel=0.1)


def test_sign_convention_and_full_phase_range():
    t = np.arange(4096) / 256.0
    x = np.sin(2 * np.pi * t)
    lag = F.fei(x, np.sin(2 * np.pi * (t - 0.02)), 256.0)
    lead = F.fei(x, np.sin(2 * np.pi * (t + 0.02)), 256.0)
    assert lag.delay > 0 > lead.delay
    # An inverted measurement is a phase of ±π, which atan (as printed in Eq. 2.3) cannot give.
    inv = F.fei(x, -x, 256.0)
    assert abs(inv.phase) == pytest.approx(math.pi, abs=1e-9)
    assert inv.amplitude == pytest.approx(1.0, rel=1e-12)
    # 170° of phase lag: atan would fold it to −10°.
    y = np.sin(2 * np.pi * t - math.radians(170))
    assert F.fei(x, y, 256.0).phase == pytest.approx(-math.radians(170), abs=1e-3)


def test_zero_variance_target_is_invalid_not_an_error():
    x = np.full(500, 0.123)
    r = F.fei(x, np.linspace(0, 1, 500), 100.0)
    assert not r.valid
    assert all(math.isnan(v) for v in (r.amplitude, r.phase, r.f_eq, r.delay))
    tiny = 0.123 + 1e-14 * np.sin(np.arange(500))
    assert not F.fei(tiny, tiny, 100.0).valid


def test_moving_exact_algorithms_agree_with_brute_force_per_window():
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal(400)) * 1e-3 + 0.05
    y = 1.05 * np.roll(x, 2) + 1e-4 * rng.standard_normal(400)
    N, fs = 40, 50.0
    rec = F.moving_fei(x, y, fs, N / fs, algorithm="recursive", abs_floor=0, rel_floor=0)
    dire = F.moving_fei(x, y, fs, N / fs, algorithm="direct", abs_floor=0, rel_floor=0)
    assert len(rec) == x.size - N + 1
    np.testing.assert_allclose(rec.t_end, (np.arange(N - 1, x.size)) / fs)
    for name in ("amplitude", "phase", "f_eq", "delay"):
        np.testing.assert_allclose(getattr(rec, name), getattr(dire, name), rtol=1e-9, atol=1e-12)
    for i in (0, 17, 200, len(rec) - 1):
        s = slice(i, i + N)
        a, _ph, feq, d = brute_fei(x[s], y[s], fs)
        assert rec.amplitude[i] == pytest.approx(a, rel=1e-9)
        assert rec.delay[i] == pytest.approx(d, rel=1e-8, abs=1e-12)
        assert rec.f_eq[i] == pytest.approx(feq, rel=1e-9)


def test_mw_without_overlap_equals_fei_of_each_segment():
    x, y = sdof_pair("kobe_1995_nishi_akashi_NIS000.csv", 2.0, 0.005, 0.95, seconds=20)
    N = 2048
    mw = F.moving_fei(x, y, FS, N / FS, hop=N)
    assert len(mw) == x.size // N
    for i in range(len(mw)):
        r = F.fei(x[i * N : (i + 1) * N], y[i * N : (i + 1) * N], FS)
        if mw.valid[i]:
            assert mw.amplitude[i] == pytest.approx(r.amplitude, rel=1e-9)
            assert mw.delay[i] == pytest.approx(r.delay, rel=1e-8)


def test_mwo_recovers_constant_delay_and_gain_on_sdof():
    x, y = sdof_pair("el_centro_1940_NS_chopra_0p02.csv", 1.0, 0.005, 1.1)
    res = F.moving_fei(x, y, FS, 3.0)
    v = res.valid
    assert v.mean() > 0.7
    # The FEI paper's Table 4.1 (linear, 1 Hz): max errors 0.6 % in A and 0.1 % in d with MWO.
    # Ours: the onset windows (response building up) are the worst; the bulk is far tighter.
    err_a = np.abs(res.amplitude[v] / 1.1 - 1)
    err_d = np.abs(res.delay[v] / 0.005 - 1)
    assert np.max(err_a) < 0.015
    assert np.max(err_d) < 0.07
    assert np.percentile(err_a, 90) < 0.006
    assert np.percentile(err_d, 90) < 0.015
    assert np.all(np.isnan(res.delay[~v]))


def test_validity_floor_marks_quiet_windows():
    t = np.arange(int(30 * FS)) / FS
    env = np.where(t < 15, 1.0, 1e-3)
    x = 0.01 * env * np.sin(2 * np.pi * t)
    y = fractional_delay(x, 0.01, FS)
    res = F.moving_fei(x, y, FS, 3.0, hop=64)
    early = res.t_end < 14.5
    late = res.t_end > 18.5
    assert res.valid[early].all()
    assert not res.valid[late].any()  # 0.1 % of the running peak < 5 %
    loose = F.moving_fei(x, y, FS, 3.0, hop=64, rel_floor=0.0)
    assert loose.valid[late].all()  # 7 µm RMS is still above the 1 µm absolute floor


@pytest.mark.parametrize("method", ["exact", "streaming"])
def test_online_is_block_size_invariant(method):
    x, y = sdof_pair("el_centro_1940_NS_chopra_0p02.csv", 1.0, 0.01, 0.97, seconds=12)
    whole = F.OnlineFEI(FS, 2.0, hop=7, method=method).update(x, y)
    rng = np.random.default_rng(0)
    cuts = np.sort(rng.choice(np.arange(1, x.size), size=300, replace=False))
    online = F.OnlineFEI(FS, 2.0, hop=7, method=method)
    parts = [online.update(a, b) for a, b in zip(np.split(x, cuts), np.split(y, cuts), strict=True)]
    parts.append(online.update(x[:0], y[:0]))
    joined = F.MovingFEIResult.concatenate(parts)
    np.testing.assert_array_equal(joined.t_end, whole.t_end)
    np.testing.assert_array_equal(joined.valid, whole.valid)
    for name in ("amplitude", "delay", "f_eq"):
        np.testing.assert_allclose(getattr(joined, name), getattr(whole, name), rtol=1e-12)


def test_online_one_sample_at_a_time_equals_batch():
    x, y = sdof_pair("el_centro_1940_NS_chopra_0p02.csv", 2.0, 0.005, 1.1, seconds=4)
    online = F.OnlineFEI(FS, 1.0, hop=1)
    parts = [online.update(x[i : i + 1], y[i : i + 1]) for i in range(x.size)]
    joined = F.MovingFEIResult.concatenate(parts)
    batch = F.moving_fei(x, y, FS, 1.0)
    np.testing.assert_array_equal(joined.valid, batch.valid)
    np.testing.assert_allclose(joined.t_end, batch.t_end)
    for name in ("amplitude", "phase", "f_eq", "delay"):
        np.testing.assert_allclose(
            getattr(joined, name), getattr(batch, name), rtol=1e-9, atol=1e-13
        )


def test_streaming_agrees_with_exact_on_sdof_responses():
    """Streaming vs exact on valid windows: SDOF responses to recorded ground motions,
    fn 0.5–2 Hz, delay 5 ms, gain 0.9–1.1, t_w = 3 Tn.

    Validity uses an absolute floor of 10 % of the record's peak window level (an operator's
    expected-amplitude floor). The whole measured envelope (2–3 Tn, 5–30 ms) is in docs/fei.md:
    the two estimators part most in windows where the response builds up or dies out.
    """
    shares_a, shares_d, worst_a, worst_d = [], [], 0.0, 0.0
    for record, fn, gain in [
        ("el_centro_1940_NS_chopra_0p02.csv", 0.5, 1.1),
        ("el_centro_1940_NS_chopra_0p02.csv", 1.0, 0.9),
        ("kobe_1995_nishi_akashi_NIS000.csv", 1.0, 1.1),
        ("kobe_1995_nishi_akashi_NIS000.csv", 2.0, 0.9),
        ("chichi_1999_TCU045_N.csv", 0.5, 0.9),
    ]:
        x, y = sdof_pair(record, fn, 0.005, gain)
        window = 3 / fn
        floor = 0.1 * np.max(F.moving_fei(x, y, FS, window, hop=256).level)
        ex = F.moving_fei(x, y, FS, window, abs_floor=floor, rel_floor=0.1)
        st = F.OnlineFEI(FS, window, method="streaming", abs_floor=floor, rel_floor=0.1)
        sr = st.update(x, y)
        v = ex.valid & sr.valid
        assert v.sum() > 0.1 * len(ex)
        err_a = np.abs(sr.amplitude[v] / ex.amplitude[v] - 1)
        err_d = np.abs(sr.delay[v] - ex.delay[v])
        shares_a.append(np.mean(err_a < 0.01))
        shares_d.append(np.mean(err_d < 0.5e-3))
        worst_a = max(worst_a, err_a.max())
        worst_d = max(worst_d, err_d.max())
    assert worst_a < 0.01  # the 1 % holds on every valid window
    assert min(shares_d) > 0.99  # 0.5 ms holds on ≥ 99 % of them (docs/fei.md)
    assert worst_d < 1e-3


def test_streaming_agrees_with_exact_at_30ms_and_two_periods_thanks_to_the_exact_low_band():
    """The hardest corner of the issue's envelope: 30 ms, window 2 Tn, fn 0.5 Hz (Kobe).

    With the exact low band (default) every valid window agrees within 1 % / 0.5 ms; with the
    whole quadrature part from the analytic signals (exact_band = 0) the same windows are
    several ms apart (the windowed analytic signal is not the analytic signal of the windowed
    signal when the window spectrum reaches DC).
    """
    x, y = sdof_pair("kobe_1995_nishi_akashi_NIS000.csv", 0.5, 0.030, 1.1)
    ex = F.moving_fei(x, y, FS, 4.0)
    worst = {}
    for band in (None, 0.0):
        sr = F.OnlineFEI(FS, 4.0, method="streaming", exact_band=band).update(x, y)
        v = ex.valid & sr.valid
        assert v.sum() > 0.5 * len(ex)
        worst[band] = (
            np.max(np.abs(sr.amplitude[v] / ex.amplitude[v] - 1)),
            np.max(np.abs(sr.delay[v] - ex.delay[v])),
        )
    assert worst[None][0] < 0.01
    assert worst[None][1] < 0.5e-3
    assert worst[0.0][1] > 2e-3


def test_streaming_with_every_bin_in_the_exact_band_is_exact():
    # N = 16 = M: bins 1 … 7 all below 14 cycles per window → no analytic-signal part left
    fs = 100.0
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal(3000)) * 1e-3
    y = 0.9 * np.roll(x, 2) + 1e-4 * rng.standard_normal(3000)
    ex = F.moving_fei(x, y, fs, 0.16)
    st = F.OnlineFEI(fs, 0.16, method="streaming")
    assert st._stream.K0 == 7
    sr = st.update(x, y)
    np.testing.assert_array_equal(sr.valid, ex.valid)
    for name in ("amplitude", "phase", "f_eq", "delay"):
        np.testing.assert_allclose(getattr(sr, name), getattr(ex, name), rtol=1e-9, atol=1e-12)


def test_decimation_keeps_estimates():
    x, y = sdof_pair("el_centro_1940_NS_chopra_0p02.csv", 1.0, 0.005, 1.1)
    full = F.moving_fei(x, y, FS, 3.0, hop=64)
    dec = F.moving_fei(x, y, FS, 3.0, hop=16, decimate=4)
    assert len(dec) == pytest.approx(len(full), abs=2)
    n = min(len(dec), len(full))
    v = full.valid[:n] & dec.valid[:n]
    np.testing.assert_allclose(dec.t_end[:n], full.t_end[:n], atol=8 / FS)
    assert np.max(np.abs(dec.amplitude[:n][v] - full.amplitude[:n][v])) < 2e-3
    assert np.max(np.abs(dec.delay[:n][v] - full.delay[:n][v])) < 5e-5


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"target": np.zeros(10), "measured": np.zeros(11)}, "equal length"),
        ({"target": np.r_[np.zeros(99), np.nan], "measured": np.zeros(100)}, "finite"),
        ({"window_s": 20.0}, "longer than the record"),
        ({"window_s": -1.0}, "positive"),
        ({"hop": 0}, "hop"),
        ({"decimate": 0}, "decimate"),
        ({"method": "fast"}, "unknown FEI method"),
        ({"window_s": 0.001}, "at least 8"),
    ],
)
def test_bad_inputs_raise_one_clear_error(kwargs, message):
    args = {
        "target": np.sin(np.arange(100.0)),
        "measured": np.sin(np.arange(100.0)),
        "fs": 10.0,
        "window_s": 2.0,
    }
    args.update(kwargs)
    with pytest.raises(InputError, match=message):
        F.moving_fei(**args)


def test_online_rejects_mismatched_blocks():
    online = F.OnlineFEI(FS, 1.0)
    with pytest.raises(InputError, match="differ in length"):
        online.update(np.zeros(3), np.zeros(4))


def test_online_first_window_ending_inside_the_first_block():
    """The first block already holds a whole window that ends before its last sample (a short
    window at a low loop rate): the one-window path with no history yet equals the batch."""
    x, y = sdof_pair("el_centro_1940_NS_chopra_0p02.csv", 2.0, 0.005, 1.1, seconds=4)
    n = int(FS)  # one-second window
    online = F.OnlineFEI(FS, 1.0, hop=n)
    first = online.update(x[: n + 5], y[: n + 5])
    batch = F.moving_fei(x[:n], y[:n], FS, 1.0)
    assert first.t_end.size == 1 and batch.t_end.size == 1
    np.testing.assert_allclose(first.t_end, batch.t_end)
    np.testing.assert_array_equal(first.valid, batch.valid)
    np.testing.assert_allclose(first.amplitude, batch.amplitude, rtol=1e-9)

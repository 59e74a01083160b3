"""Pieces of the discrepancy workflow against independent references.

Localisation (noise level, when, frequency, regime) on hand-made residuals whose answer is known
in closed form; the compiled effect paths against the catalogue; the delay/gain projection
against an explicit least-squares solve; the joint re-fit; the record generator.
"""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay
from rths_hil.sim_backends.effects import EFFECTS, draw_effect_params, make_effect
from rths_hil.sim_backends.modelfile import (
    ActuatorSpec,
    EffectSpec,
    ModelSpec,
    dump_model,
    load_model,
)
from scipy import signal

from rths_hil.diagnose import localise, noise_level
from rths_hil.diagnose._fast import fractional_delay as fast_delay
from rths_hil.diagnose._fast import simulate_effect
from rths_hil.diagnose.candidates import Data, Model, _rss, polish
from rths_hil.diagnose.synthetic import make_case

FS = 1024.0


def _drive(n: int = int(30 * FS), seed: int = 0) -> np.ndarray:
    """1 Hz-ish SDOF-like response: band-passed noise, 10 mm rms."""
    rng = np.random.default_rng(seed)
    sos = signal.butter(2, [0.6, 1.6], btype="band", fs=FS, output="sos")
    x = signal.sosfilt(sos, rng.standard_normal(n))
    return 0.01 * x / np.std(x)


def test_noise_level_ignores_the_smooth_signal_and_sparse_kinks():
    rng = np.random.default_rng(1)
    x = _drive()
    sigma = 1.3e-5
    r = 0.05 * x + sigma * rng.standard_normal(len(x))  # a 0.5 mm rms structural residual
    r[::500] += 1e-3  # sparse spikes
    assert noise_level(r) == pytest.approx(sigma, rel=0.03)


def test_when_finds_a_window_with_an_added_bump():
    rng = np.random.default_rng(2)
    x = _drive()
    t = np.arange(len(x)) / FS
    sigma = 1e-5
    y = x + sigma * rng.standard_normal(len(x))
    y[(t >= 12.0) & (t < 16.0)] += 1e-4  # 10 σ for 4 s
    loc = localise(x, y, x, FS, window_s=1.0)
    iv = loc.when["intervals_s"]
    assert len(iv) == 1
    a, b = iv[0]
    # windows overlapping the bump by more than the band's margin are flagged
    assert 11.0 <= a <= 12.0 and 16.0 <= b <= 17.0
    assert loc.noise == pytest.approx(sigma, rel=0.05)


def test_when_finds_nothing_in_white_noise():
    rng = np.random.default_rng(3)
    x = _drive()
    y = x + 1e-5 * rng.standard_normal(len(x))
    loc = localise(x, y, x, FS)
    assert loc.when["intervals_s"] == []
    assert loc.when["fei"]["fraction_outside"] <= 0.01
    assert loc.frequency["deviating_hz"] == []


def test_frequency_recovers_a_delay_and_gain_error():
    """Measured = 0.95 × predicted delayed by 4 ms: H_m/H_p = 0.95·exp(−2πj f·4 ms)."""
    rng = np.random.default_rng(4)
    x = _drive()
    y = 0.95 * fractional_delay(x, 0.004, FS) + 1e-5 * rng.standard_normal(len(x))
    loc = localise(x, y, x, FS)
    fr = loc.frequency
    assert fr["amplitude_ratio"] == pytest.approx(0.95, rel=2e-3)
    assert fr["delay_s"] == pytest.approx(0.004, abs=1e-4)
    lo, hi = fr["band_hz"]
    assert lo <= 1.0 <= hi
    assert fr["deviating_fraction"] > 0.9
    # the moving FEI sees the same, everywhere
    fei = loc.when["fei"]
    assert fei["fraction_outside"] > 0.95
    assert fei["delay_range_s"][0] == pytest.approx(0.004, abs=3e-4)
    assert fei["amplitude_range"][1] == pytest.approx(0.95, abs=0.01)


@pytest.mark.parametrize(
    "kind, dominant",
    [
        ("offset", "mean"),
        ("drift", "time"),
        ("gain", "amplitude"),
        ("delay", "velocity"),
        ("backlash", "direction"),
    ],
)
def test_regime_names_the_signature_of_each_residual(kind, dominant):
    rng = np.random.default_rng(5)
    x = _drive()
    t = np.arange(len(x)) / FS
    y = {
        "offset": x + 3e-4,
        "drift": x + 2e-5 * t,
        "gain": 0.97 * x,
        "delay": fractional_delay(x, 0.003, FS),
        "backlash": make_effect("backlash", 1 / FS, width=4e-4).simulate(x),
    }[kind] + 1e-5 * rng.standard_normal(len(x))
    loc = localise(x, y, x, FS, force=None)
    assert loc.regime["dominant"] == dominant
    if kind == "backlash":  # the play shows up around direction reversals
        rev = loc.regime["reversals"]
        assert rev["count"] > 20


def test_force_regime_for_a_force_proportional_residual():
    rng = np.random.default_rng(6)
    x = _drive()
    v = np.gradient(x) * FS
    force = 1e6 * x + 2e5 * v  # a damper-like specimen: force is not ∝ x
    y = x - force / 5e7 + 1e-5 * rng.standard_normal(len(x))
    loc = localise(x, y, x, FS, force=force)
    assert loc.regime["dominant"] == "force"
    assert loc.regime["r2"]["force"] > 0.9


@pytest.mark.parametrize(
    "kind", ["velocity_limit", "backlash", "servo_lag", "force_feedback", "time_varying_delay"]
)
def test_fast_effect_paths_equal_the_catalogue(kind):
    rng = np.random.default_rng(7)
    x = _drive(int(10 * FS))
    for _ in range(5):
        p = draw_effect_params(kind, rng)
        if kind == "velocity_limit":
            p["limit"] *= 0.2  # active much of the time
        ref = make_effect(kind, 1 / FS, **p).simulate(x)
        out = simulate_effect(kind, p, x, 1 / FS)
        if kind in ("velocity_limit", "backlash"):
            assert np.array_equal(out, ref)  # same recursion, same comparisons
        else:
            np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12 * np.max(np.abs(ref)))


def test_fast_fractional_delay_equals_the_catalogue():
    x = _drive(5000)
    for d in (0.0, 0.3 / FS, 1.7 / FS, 0.0123, 0.25):
        np.testing.assert_allclose(fast_delay(x, d, FS), fractional_delay(x, d, FS), atol=1e-17)


def test_projected_rss_is_the_least_squares_delay_gain_correction():
    """``Data.project``: RSS after the LS fit of ``r`` on ``[p, ṗ]`` (explicit lstsq reference)."""
    rng = np.random.default_rng(8)
    x = _drive(int(10 * FS))
    y = 1.01 * fractional_delay(x, 0.002, FS) + 1e-5 * rng.standard_normal(len(x))
    pred = x
    d = Data(x, y, FS, project=True)
    r = y - pred
    a = np.column_stack([pred, np.gradient(pred)])
    coef, *_ = np.linalg.lstsq(a, r, rcond=None)
    ref = float(np.sum((r - a @ coef) ** 2))
    assert _rss(d, pred) == pytest.approx(ref, rel=1e-9)
    assert _rss(Data(x, y, FS), pred) == pytest.approx(float(r @ r))


def test_polish_recovers_two_effects_and_the_delay_jointly():
    """Start every parameter off by 10-30 %; the joint re-fit returns to the truth."""
    rng = np.random.default_rng(9)
    u = _drive(int(20 * FS))
    truth = ModelSpec(
        ActuatorSpec(
            delay=0.012,
            gain=0.98,
            effects=[
                EffectSpec("backlash", {"width": 2e-4}),
                EffectSpec("offset", {"offset": 5e-4}),
            ],
        )
    )
    y = Model(truth, Data(u, np.zeros_like(u), FS)).pred + 1e-5 * rng.standard_normal(len(u))
    start = ModelSpec(
        ActuatorSpec(
            delay=0.0135,
            gain=0.95,
            effects=[
                EffectSpec("backlash", {"width": 2.6e-4}),
                EffectSpec("offset", {"offset": 4e-4}),
            ],
        )
    )
    spec, _, rss = polish(start, Data(u, y, FS), [0, 1], actuator=True)
    a = spec.actuator
    assert a.delay == pytest.approx(0.012, abs=2e-5)
    assert a.gain == pytest.approx(0.98, rel=1e-3)
    assert a.effects[0].params["width"] == pytest.approx(2e-4, rel=0.02)
    assert a.effects[1].params["offset"] == pytest.approx(5e-4, rel=0.01)
    assert rss / len(u) == pytest.approx(1e-10, rel=0.1)  # the noise variance


def test_generated_records_hide_the_drawn_effect():
    case = make_case(["servo_lag"], 11, duration=10.0)
    assert case.names == ["servo_lag"]
    # the measurement is the twin's (noise included), the base lacks the effect
    plant = case.twin.build(1.0 / case.fs)
    meas, force = plant.simulate(case.command)
    np.testing.assert_array_equal(meas, case.measured)
    np.testing.assert_array_equal(force, case.force)
    assert case.base.actuator.effects == []
    assert case.info["effect_rms"]["servo_lag"] > 0
    # reproducible from the seed
    again = make_case(["servo_lag"], 11, duration=10.0)
    np.testing.assert_array_equal(again.measured, case.measured)
    # every kind can be hidden
    for kind in EFFECTS:
        c = make_case([kind], 12, duration=6.0)
        assert c.info["effect_rms"][kind] > 0, kind


def test_model_file_round_trip_with_numpy_floats(tmp_path):
    """Fitted parameters are often numpy scalars; the model file must still be valid TOML
    (rths_hil.sim_backends.modelfile: ``repr(np.float64(x))`` is ``np.float64(x)`` in numpy 2)."""
    spec = ModelSpec(
        ActuatorSpec(
            delay=np.float64(0.0123),
            gain=np.float64(0.97),
            effects=[EffectSpec("offset", {"offset": np.float64(1.9e-3)})],
        )
    )
    path = tmp_path / "m.toml"
    dump_model(spec, path)
    back = load_model(path)
    assert back.actuator.delay == 0.0123
    assert back.actuator.gain == 0.97
    assert back.actuator.effects[0].params["offset"] == 1.9e-3

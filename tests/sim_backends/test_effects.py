"""The effects catalogue: each effect against an independent reference, step == simulate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay
from rths_hil.sim_backends.effects import (
    EFFECT_RANGES,
    EFFECTS,
    EffectChain,
    draw_effect_params,
    make_effect,
    validate_params,
)
from scipy import signal

from rths_hil.errors import InputError

DT = 1.0 / 1024.0
KINDS = [
    "offset",
    "drift",
    "backlash",
    "velocity_limit",
    "stroke_limit",
    "servo_lag",
    "time_varying_delay",
    "force_feedback",
]


def _record(n: int = 6144, seed: int = 0) -> np.ndarray:
    """Earthquake-like: 1 Hz carrier with an envelope plus coloured noise (m)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    env = np.sin(np.pi * t / t[-1])
    noise = signal.lfilter([0.05], [1, -0.95], rng.standard_normal(n))
    return env * (0.03 * np.sin(2 * np.pi * 1.1 * t) + 0.003 * noise)


def test_catalogue_names_are_the_issue_names():
    assert list(EFFECTS) == KINDS
    assert list(EFFECT_RANGES) == KINDS
    for kind, cls in EFFECTS.items():
        assert cls.kind == kind
        assert set(EFFECT_RANGES[kind]) <= {p.name for p in cls.PARAMS}
        for p in cls.PARAMS:
            assert p.unit and p.doc


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_step_equals_simulate_for_random_realistic_parameters(kind, seed):
    rng = np.random.default_rng(100 + seed)
    params = draw_effect_params(kind, rng)
    for name, value in params.items():
        r = EFFECT_RANGES[kind][name]
        assert r.low <= abs(value) <= r.high
        if not r.signed:
            assert value >= 0
    eff = make_effect(kind, DT, **params)
    x = _record(seed=seed)
    vec = eff.simulate(x)
    eff.reset()
    stepped = np.array([eff.step(v) for v in x])
    np.testing.assert_allclose(stepped, vec, rtol=0, atol=1e-15)
    # simulate restarts from rest
    np.testing.assert_array_equal(eff.simulate(x), vec)


def test_offset_and_drift_closed_form():
    x = _record()
    t = np.arange(len(x)) * DT
    np.testing.assert_allclose(make_effect("offset", DT, offset=-7e-4).simulate(x), x - 7e-4)
    rate = 3e-3 / 60
    np.testing.assert_allclose(
        make_effect("drift", DT, rate=rate).simulate(x), x + rate * t, rtol=0, atol=1e-17
    )


def _play_reference(x: np.ndarray, width: float) -> np.ndarray:
    """Textbook play operator, written independently of the library's scan."""
    y = np.empty_like(x)
    prev = 0.0
    for i, v in enumerate(x):
        if v - prev > width / 2:
            prev = v - width / 2
        elif prev - v > width / 2:
            prev = v + width / 2
        y[i] = prev
    return y


@pytest.mark.parametrize("n", [1, 2, 63, 64, 65, 1000, 50000])
def test_backlash_against_play_reference(n):
    width = 3e-4
    x = _record(max(n, 64), seed=4)[:n] * 0.2  # small motions: the play matters
    eff = make_effect("backlash", DT, width=width)
    np.testing.assert_array_equal(eff.simulate(x), _play_reference(x, width))
    assert eff._y == _play_reference(x, width)[-1]  # state carried for further steps


def test_backlash_triangle_wave():
    width = 3e-4
    # triangle wave of amplitude A ≫ width: after the first turn the output lags by width/2
    n = 4096
    k = np.arange(n)
    tri = 5e-3 * signal.sawtooth(2 * np.pi * k / 1024, width=0.5)
    y = make_effect("backlash", DT, width=width).simulate(tri)
    slope = np.diff(tri, prepend=tri[0])
    # away from the turning points (the output holds until the input crosses the gap)
    inner = (k > 600) & (np.abs(tri) < 4.5e-3)
    up, down = inner & (slope > 0), inner & (slope < 0)
    np.testing.assert_allclose(y[up], tri[up] - width / 2, atol=1e-15)
    np.testing.assert_allclose(y[down], tri[down] + width / 2, atol=1e-15)
    # and at a turning point the output holds still
    turn = int(np.argmax(tri[600:])) + 600
    assert np.ptp(y[turn : turn + 7]) == 0.0


def test_backlash_zero_width_is_identity():
    x = _record()
    np.testing.assert_array_equal(make_effect("backlash", DT, width=0.0).simulate(x), x)


def test_velocity_limit():
    t = np.arange(4096) * DT
    amp, f = 0.02, 2.0  # peak velocity 2π·f·A = 0.251 m/s
    x = amp * np.sin(2 * np.pi * f * t)
    fast = make_effect("velocity_limit", DT, limit=0.3).simulate(x)
    np.testing.assert_allclose(fast, x, atol=1e-18)  # never reaches the limit
    lim = 0.1
    y = make_effect("velocity_limit", DT, limit=lim).simulate(x)
    v = np.diff(y, prepend=0.0) / DT
    assert np.max(np.abs(v)) <= lim * (1 + 1e-9)
    assert np.max(np.abs(v)) == pytest.approx(lim, rel=1e-9)  # the limit is hit
    # slewing: during a rate-limited stretch the output moves at exactly ±limit
    assert np.mean(np.isclose(np.abs(v), lim, rtol=1e-9)) > 0.3
    # against the textbook recursion y += clip(x − y, ±limit·dt), on a record that hits the
    # limit only now and then
    x = _record(30000, seed=6)
    y = make_effect("velocity_limit", DT, limit=0.25).simulate(x)
    ref = np.empty_like(x)
    prev = 0.0
    for i, xi in enumerate(x):
        prev = prev + np.clip(xi - prev, -0.25 * DT, 0.25 * DT)
        ref[i] = prev
    assert 0.05 < np.mean(y != x) < 0.5
    np.testing.assert_allclose(y, ref, rtol=0, atol=1e-17)


def test_stroke_limit():
    x = _record()
    y = make_effect("stroke_limit", DT, limit=0.01, center=0.002).simulate(x)
    np.testing.assert_array_equal(y, np.clip(x, -0.008, 0.012))


def test_servo_lag_ramp_closed_form():
    tc, r = 0.012, 0.08
    t = np.arange(600) * DT
    y = make_effect("servo_lag", DT, time_constant=tc).simulate(r * t)
    np.testing.assert_allclose(y, r * (t - tc + tc * np.exp(-t / tc)), rtol=0, atol=1e-15)


def test_time_varying_delay_constant_equals_fractional_delay():
    x = _record()
    y = make_effect("time_varying_delay", DT, delay=0.0137, amplitude=0.0).simulate(x)
    np.testing.assert_allclose(y, fractional_delay(x, 0.0137, 1 / DT), rtol=0, atol=1e-15)


def test_time_varying_delay_follows_tau_of_t():
    t = np.arange(20480) * DT
    w = 2 * np.pi * 0.8
    x = 0.01 * np.sin(w * t)
    d0, d1, period = 0.015, 0.004, 5.0
    y = make_effect("time_varying_delay", DT, delay=d0, amplitude=d1, period=period).simulate(x)
    tau = d0 + d1 * np.sin(2 * np.pi * t / period)
    exact = 0.01 * np.sin(w * (t - tau))
    settled = t > 0.05
    # Lagrange interpolation error O((ω dt)^4): ~1e-12 of the amplitude at 0.8 Hz
    np.testing.assert_allclose(y[settled], exact[settled], atol=1e-10)


def test_force_feedback_static_and_lag():
    kh, ks = 5e7, 2e6
    g = kh / (kh + ks)
    x = _record()
    y = make_effect("force_feedback", DT, actuator_stiffness=kh, specimen_stiffness=ks).simulate(x)
    np.testing.assert_allclose(y, g * x, rtol=1e-15)
    cs = 1e5  # damper: T = cs/(kh + ks) ≈ 1.9 ms
    tc = cs / (kh + ks)
    t = np.arange(300) * DT
    r = 0.05
    y = make_effect(
        "force_feedback", DT, actuator_stiffness=kh, specimen_stiffness=ks, specimen_damping=cs
    ).simulate(r * t)
    np.testing.assert_allclose(y, g * r * (t - tc + tc * np.exp(-t / tc)), rtol=0, atol=1e-15)


def test_chain_applies_in_order():
    x = _record()
    a = make_effect("stroke_limit", DT, limit=0.01)
    b = make_effect("offset", DT, offset=0.002)
    np.testing.assert_allclose(EffectChain([a, b]).simulate(x), np.clip(x, -0.01, 0.01) + 0.002)
    np.testing.assert_allclose(EffectChain([b, a]).simulate(x), np.clip(x + 0.002, -0.01, 0.01))
    np.testing.assert_array_equal(EffectChain().simulate(x), x)


def test_validation_messages_name_the_parameter():
    """Effect parameters read as configuration keys (rths_hil.config.check_table): one
    wording with the run configuration, profiles and model files."""
    with pytest.raises(InputError, match=r"kind: unknown effect 'foo' \(known: offset, drift"):
        make_effect("foo", DT)
    with pytest.raises(
        InputError, match=r"^width: required by effect 'backlash' \(total play, m\)$"
    ):
        make_effect("backlash", DT)
    with pytest.raises(
        InputError, match=r"^widht: unknown key \(did you mean 'width'\?\); known keys: width$"
    ):
        make_effect("backlash", DT, widht=1e-4)
    with pytest.raises(InputError, match=r"^width: must be ≥ 0 m, got -0\.0001$"):
        make_effect("backlash", DT, width=-1e-4)
    with pytest.raises(InputError, match=r"^limit: must be > 0 m/s, got 0$"):
        make_effect("velocity_limit", DT, limit=0.0)
    with pytest.raises(InputError, match="amplitude: must not exceed delay"):
        make_effect("time_varying_delay", DT, delay=0.005, amplitude=0.006)
    with pytest.raises(InputError, match=r"^offset: expected a number in m, got an array$"):
        make_effect("offset", DT, offset=[0.001])
    with pytest.raises(InputError, match=r"^offset: must be a finite number, got inf$"):
        make_effect("offset", DT, offset=math.inf)
    with pytest.raises(InputError, match=r"^here: effects\[2\]\.rate: required by effect 'drift'"):
        validate_params("drift", {}, "here", "effects[2]")
    with pytest.raises(InputError, match=r"^here: effects\[2\]\.amplitude: must not exceed"):
        validate_params(
            "time_varying_delay", {"delay": 0.001, "amplitude": 0.002}, "here", "effects[2]"
        )
    # a value may carry its unit, as in a model file; numpy scalars are numbers
    assert make_effect("offset", DT, offset="1.5 mm").params["offset"] == pytest.approx(1.5e-3)
    assert make_effect("offset", DT, offset=np.int64(1)).params["offset"] == 1.0
    assert validate_params("offset", {"offset": "2 kN"}, units={"offset": "N"}) == {
        "offset": 2000.0
    }


def test_ranges_are_physical_and_consistent():
    r = EFFECT_RANGES
    assert r["offset"]["offset"].low == pytest.approx(1e-4)
    assert r["offset"]["offset"].high == pytest.approx(2e-3)
    assert r["drift"]["rate"].high == pytest.approx(5e-3 / 60)
    assert r["backlash"]["width"].low == pytest.approx(5e-5)
    # time-varying delay ranges never produce amplitude > delay
    assert r["time_varying_delay"]["amplitude"].high <= r["time_varying_delay"]["delay"].low
    rng = np.random.default_rng(5)
    for kind in KINDS:
        for _ in range(20):
            make_effect(kind, DT, **draw_effect_params(kind, rng))

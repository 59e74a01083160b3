"""Actuator models, specimen and the composite TwinPlant against closed forms and references."""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends import delay as delay_mod
from rths_hil.sim_backends.base import Plant
from rths_hil.sim_backends.effects import make_effect
from rths_hil.sim_backends.models import (
    BENCHMARK_NOMINAL,
    BenchmarkServo,
    DelayGain,
    FirstOrderServo,
    Series,
    benchmark_transfer_function,
    make_model,
)
from rths_hil.sim_backends.plant import Sensor, TwinPlant
from rths_hil.sim_backends.specimen import KelvinVoigt
from scipy import signal

from rths_hil.errors import InputError

DT = 1.0 / 1024.0


def _record(n: int = 8192, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    return 0.02 * np.sin(2 * np.pi * 0.9 * t) + 0.004 * signal.lfilter(
        [0.05], [1, -0.95], rng.standard_normal(n)
    )


def test_delay_gain_is_the_seed_block():
    assert DelayGain is delay_mod.DelayGain
    m = make_model("delay_gain", DT, delay=0.0123, gain=0.97)
    x = _record()
    ref = 0.97 * delay_mod.fractional_delay(x, 0.0123, 1 / DT)
    np.testing.assert_allclose(m.simulate(x), ref, rtol=0, atol=1e-15)


def test_first_order_ramp_is_exact():
    # First-order hold is exact for piecewise-linear input: ramp r·t → r(t − T + T e^{−t/T}).
    tc, r = 0.008, 0.05
    n = 400
    t = np.arange(n) * DT
    m = FirstOrderServo(tc, DT)
    y = m.simulate(r * t)
    exact = r * (t - tc + tc * np.exp(-t / tc))
    np.testing.assert_allclose(y, exact, rtol=0, atol=1e-15)


def test_first_order_sine_amplitude_and_phase():
    tc, f = 0.01, 2.0
    n = 8192
    t = np.arange(n) * DT
    y = FirstOrderServo(tc, DT).simulate(np.sin(2 * np.pi * f * t))
    w = 2 * np.pi * f
    exact = np.sin(w * t - np.arctan(w * tc)) / np.sqrt(1 + (w * tc) ** 2)
    tail = t > 10 * tc
    np.testing.assert_allclose(y[tail], exact[tail], atol=2e-5)


@pytest.mark.parametrize(
    "name,params",
    [("delay_gain", {}), ("servo_lag", {"time_constant": 0.006}), ("benchmark", {})],
)
def test_step_path_equals_simulate(name, params):
    m = make_model(name, DT, delay=0.0071, gain=1.03, **params)
    x = _record(4096, seed=3)
    vec = m.simulate(x)
    m.reset()
    stepped = np.array([m.step(v) for v in x])
    # state space (step) vs second-order sections (simulate): same system, other arithmetic
    np.testing.assert_allclose(stepped, vec, rtol=0, atol=1e-11 * np.max(np.abs(x)))


def _benchmark_tf_by_interconnection(p: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Silva et al. 2020 block diagram assembled with polynomial algebra, independently."""
    # G0 = Ga·Ge / (1 + Ga·Ge·a2 s), Ga = 1/(s + a3), Ge = 1/(m s² + c s + k)
    ga_ge_den = np.polymul(
        [1, p["a3"]], [p["specimen_mass"], p["specimen_damping"], p["specimen_stiffness"]]
    )
    g0_den = np.polyadd(ga_ge_den, [p["a2"], 0])  # numerator 1
    # open loop L = Gsv·G0 = a1b0 / ((s² + β1 s + β2)·g0_den); closed loop L/(1+L)
    ol_den = np.polymul([1, p["beta1"], p["beta2"]], g0_den)
    return np.array([p["a1b0"]]), np.polyadd(ol_den, [p["a1b0"]])


def test_benchmark_matches_block_diagram_and_discretisation():
    p = dict(BENCHMARK_NOMINAL)
    num, den = benchmark_transfer_function(**p, plant_gain=1.0)  # the paper's Eq. 21
    rnum, rden = _benchmark_tf_by_interconnection(p)
    np.testing.assert_allclose(num, rnum, rtol=0)
    np.testing.assert_allclose(den, rden, rtol=1e-14)
    m = BenchmarkServo(DT, plant_gain=1.0)  # the paper's Eq. 21
    freqs = np.array([0.2, 1.0, 2.0, 5.0, 10.0, 30.0, 67.0])
    _, hc = signal.freqs(num, den, worN=2 * np.pi * freqs)
    hd = m.frequency_response(freqs)
    # the first-order (triangle) hold of a sampled sinusoid has amplitude sinc²(f·dt): the
    # discrete model is the continuous plant times exactly that, up to the 67 Hz mode
    np.testing.assert_allclose(hd, hc * np.sinc(freqs * DT) ** 2, rtol=1e-8)
    # DC gain a1β0/(β2·a3·k + a1β0) and the documented ~25 ms delay, 0.974 amplitude at 1 Hz
    dc = p["a1b0"] / (p["beta2"] * p["a3"] * p["specimen_stiffness"] + p["a1b0"])
    assert m.dc_gain() == pytest.approx(dc, rel=1e-12)
    assert abs(hc[1]) == pytest.approx(0.974, abs=1e-3)
    assert -np.angle(hc[1]) / (2 * np.pi) == pytest.approx(0.0249, abs=2e-4)


def test_benchmark_time_response_matches_lsim():
    # lsim interpolates the input linearly between samples, as the first-order hold assumes
    num, den = benchmark_transfer_function()
    t = np.arange(4096) * DT
    x = _record(4096, seed=1) * np.minimum(t / 0.05, 1.0)  # from rest: x[0] = 0
    _, ref, _ = signal.lsim((num, den), x, t)
    y = BenchmarkServo(DT).simulate(x)
    assert np.max(np.abs(y - ref)) < 1e-10 * np.max(np.abs(x))


def test_benchmark_default_gain_is_the_distributed_codes():
    # F1_input_file.m: G_plant = gain*feedback(Gs*G0,1,-1) with gain = 1.0261
    freqs = np.array([0.5, 1.0, 5.0, 20.0])
    paper = BenchmarkServo(DT, plant_gain=1.0).frequency_response(freqs)
    code = BenchmarkServo(DT).frequency_response(freqs)
    np.testing.assert_allclose(code / paper, 1.0261, rtol=1e-9)
    assert make_model("benchmark", DT).models[0].dc_gain() == pytest.approx(
        1.0261 * BenchmarkServo(DT, plant_gain=1.0).dc_gain(), rel=1e-12
    )
    with pytest.raises(InputError, match="plant_gain"):
        BenchmarkServo(DT, plant_gain=0.0)


def test_benchmark_stiffer_specimen_lowers_gain_and_lengthens_delay():
    # control-structure interaction: a stiffer specimen loads the actuator more
    soft = BenchmarkServo(DT, specimen_stiffness=5e5).frequency_response(np.array([1.0]))[0]
    stiff = BenchmarkServo(DT, specimen_stiffness=5e6).frequency_response(np.array([1.0]))[0]
    assert abs(stiff) < abs(soft)
    assert -np.angle(stiff) > -np.angle(soft)


def test_make_model_errors():
    with pytest.raises(InputError, match="unknown actuator model 'foo'"):
        make_model("foo", DT)
    with pytest.raises(InputError, match="time_constant: required"):
        make_model("servo_lag", DT)
    with pytest.raises(InputError, match="delay: must be ≥ 0"):
        make_model("delay_gain", DT, delay=-0.001)
    with pytest.raises(InputError, match="beta9: not a parameter"):
        make_model("benchmark", DT, beta9=1.0)
    with pytest.raises(InputError, match="time_constant: must be > 0"):
        FirstOrderServo(0.0, DT)


def test_series_composes():
    a = FirstOrderServo(0.005, DT)
    b = DelayGain(0.01, 0.9, DT)
    x = _record(2048)
    np.testing.assert_allclose(Series([a, b]).simulate(x), b.simulate(a.simulate(x)), atol=0)


# -- specimen ---------------------------------------------------------------------------------


def test_kelvin_voigt_force_closed_form():
    k, c, m = 2.0e6, 500.0, 10.0
    spec = KelvinVoigt(k, c, DT, mass=m)
    n = 2048
    t = np.arange(n) * DT
    w = 2 * np.pi * 1.5
    x = 0.01 * np.sin(w * t)
    f = spec.simulate(x)
    # backward differences of a sinusoid: v = (x[k]−x[k−1])/dt, a = (v[k]−v[k−1])/dt
    v = np.concatenate([[x[0] / DT], np.diff(x) / DT])
    a = np.concatenate([[v[0] / DT], np.diff(v) / DT])
    np.testing.assert_allclose(f, k * x + c * v + m * a, rtol=1e-12, atol=1e-9)
    # and close to the continuous force away from the start (dt/2 lag of the difference)
    fc = k * x + c * 0.01 * w * np.cos(w * t) - m * 0.01 * w**2 * np.sin(w * t)
    assert np.max(np.abs(f[10:] - fc[10:])) < 1e-3 * np.max(np.abs(fc))
    spec.reset()
    np.testing.assert_allclose([spec.step(v_) for v_ in x], f, rtol=0, atol=0)


def test_specimen_rejects_negative():
    with pytest.raises(InputError, match="stiffness"):
        KelvinVoigt(-1.0, 0.0, DT)


# -- plant ------------------------------------------------------------------------------------


def _plant(seed: int = 7, **sensor) -> TwinPlant:
    kw = dict(
        displacement_noise=1e-5,
        force_noise=3.0,
        displacement_resolution=1e-6,
        force_resolution=0.5,
        seed=seed,
    )
    kw.update(sensor)
    return TwinPlant(
        make_model("servo_lag", DT, delay=0.004, gain=0.98, time_constant=0.006),
        [make_effect("backlash", DT, width=2e-4), make_effect("offset", DT, offset=5e-4)],
        KelvinVoigt(1.0e6, 200.0, DT),
        Sensor(**kw),
    )


def test_plant_is_a_plant_and_step_equals_simulate():
    p = _plant()
    assert isinstance(p, Plant)
    x = _record(6000)
    d, f = p.simulate(x)
    steps = np.array([p.step(v) for v in x])
    np.testing.assert_allclose(steps[:, 0], d, rtol=0, atol=1e-15)
    np.testing.assert_allclose(steps[:, 1], f, rtol=0, atol=1e-9)
    # reproducible from reset, different with another seed
    d2, _ = p.simulate(x)
    np.testing.assert_array_equal(d, d2)
    d3, _ = _plant(seed=8).simulate(x)
    assert np.max(np.abs(d3 - d)) > 1e-6


def test_plant_noise_statistics_and_quantisation():
    n = 40000
    x = _record(n)
    noiseless = _plant(
        displacement_noise=0.0, force_noise=0.0, displacement_resolution=0.0, force_resolution=0.0
    )
    true_d, true_f = noiseless.simulate(x)
    noisy = _plant(displacement_resolution=0.0, force_resolution=0.0)
    d, f = noisy.simulate(x)
    assert np.std(d - true_d) == pytest.approx(1e-5, rel=0.03)
    assert np.std(f - true_f) == pytest.approx(3.0, rel=0.03)
    assert abs(np.corrcoef(d - true_d, f - true_f)[0, 1]) < 0.03
    dq, fq = _plant().simulate(x)
    np.testing.assert_allclose(dq / 1e-6, np.round(dq / 1e-6), atol=1e-6)
    np.testing.assert_allclose(fq / 0.5, np.round(fq / 0.5), atol=1e-9)
    # same noise stream: quantised = round(noisy)
    np.testing.assert_allclose(dq, 1e-6 * np.round(d / 1e-6), atol=1e-18)


def test_plant_force_comes_from_achieved_displacement():
    p = _plant(
        displacement_noise=0.0, force_noise=0.0, displacement_resolution=0.0, force_resolution=0.0
    )
    x = _record(3000)
    d, f = p.simulate(x)
    ref = KelvinVoigt(1.0e6, 200.0, DT).simulate(d)
    np.testing.assert_allclose(f, ref, rtol=1e-12, atol=1e-9)
    p.reset()
    p.step(0.01)
    assert p.true_force == pytest.approx(
        1.0e6 * p.true_displacement + 200.0 * p.true_displacement / DT
    )


def test_plant_quantisation_survives_nan_command():
    p = TwinPlant(
        make_model("delay_gain", DT),
        specimen=KelvinVoigt(1e6, 0.0, DT),
        sensor=Sensor(displacement_resolution=1e-6, force_resolution=0.5),
    )
    md, mf = p.step(float("nan"))
    assert np.isnan(md) and np.isnan(mf)


def test_plant_noise_is_drawn_before_the_first_step_and_in_small_blocks():
    """The first step's reply does not pay for drawing the noise; later refills stay small.

    The stream is the one a single draw from the sensor's seed gives, whatever the block size.
    """
    import sim_backends.plant as plant_mod

    p = _plant()
    calls: list[int] = []
    for name in ("_rng_d", "_rng_f"):
        rng = getattr(p, name)
        draw = rng.standard_normal

        def counted(*a, _draw=draw, **kw):
            out = kw.get("out")
            calls.append(out.size if out is not None else int(a[0]))
            return _draw(*a, **kw)

        setattr(p, name, type("R", (), {"standard_normal": staticmethod(counted)})())
    n = plant_mod._BLOCK
    steps = [p.step(1e-3)[0] for _ in range(n)]
    assert calls == []  # reset() drew the first block
    steps.append(p.step(1e-3)[0])
    assert calls == [n, n] and n <= 512
    disp_seq, _ = np.random.SeedSequence(int(p.sensor.seed)).spawn(2)
    ref = np.random.Generator(np.random.PCG64(disp_seq)).standard_normal(n + 1)
    x = np.asarray(steps) - p.true_displacement  # constant command: settled achieved value
    q = p.sensor.displacement_resolution  # the sensor quantises (rounds to q)
    np.testing.assert_allclose(x[-10:], p.sensor.displacement_noise * ref[-10:], atol=q / 2)
    assert np.max(np.abs(x[-10:] - p.sensor.displacement_noise * ref[-11:-1])) > q

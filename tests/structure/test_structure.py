"""SDOF integrators (CR, Newmark) and the Bouc-Wen model against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lsim

from rths_hil.errors import InputError
from rths_hil.groundmotion import default_record
from rths_hil.structures.sdof import (
    K_A_PAPER,
    BoucWen,
    BoucWenParams,
    CRStepper,
    NewmarkStepper,
    simulate_sdof,
)


def _zero_crossings(x: np.ndarray, dt: float) -> np.ndarray:
    """Times of upward zero crossings, linearly interpolated."""
    i = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    return (i + x[i] / (x[i] - x[i + 1])) * dt


def _peaks(x: np.ndarray) -> np.ndarray:
    """Heights of the local maxima, refined by a parabola through 3 samples."""
    i = np.nonzero((x[1:-1] > x[:-2]) & (x[1:-1] >= x[2:]) & (x[1:-1] > 0))[0] + 1
    a, b, c = x[i - 1], x[i], x[i + 1]
    return b - 0.125 * (a - c) ** 2 / (a - 2 * b + c)


def _free(stepper_cls, dt, n, **kw):
    st = stepper_cls(2.0, kw.pop("zeta"), kw.pop("k"), dt, x0=0.01, **kw)
    x = np.empty(n)
    x[0] = st.x
    for i in range(1, n):
        st.step(0.0)
        x[i] = st.x
    return x


@pytest.mark.parametrize("cls", [CRStepper, NewmarkStepper])
def test_free_vibration_period_and_decay(cls):
    m, fn, zeta = 2.0, 1.3, 0.05
    k = m * (2 * np.pi * fn) ** 2
    dt = 1 / 2048
    x = _free(cls, dt, int(8 / dt), zeta=zeta, k=k)
    td = 1 / (fn * math.sqrt(1 - zeta**2))
    periods = np.diff(_zero_crossings(x, dt))
    np.testing.assert_allclose(periods, td, rtol=2e-5)
    ratios = _peaks(x)[1:] / _peaks(x)[:-1]
    np.testing.assert_allclose(ratios, math.exp(-2 * math.pi * zeta / math.sqrt(1 - zeta**2)), 1e-4)


@pytest.mark.parametrize("wdt", [0.5, 3.0, 30.0, 3000.0])
def test_cr_undamped_matches_its_closed_form_at_any_step(wdt):
    """x[n+1] − 2x[n] + x[n−1] = −αΩ²x[n], α = 4/(4+Ω²): cos θ = (4−Ω²)/(4+Ω²) (trapezoidal
    period, tan(θ/2) = Ω/2), unit-modulus roots: no growth and no numerical damping."""
    omega = 2 * np.pi
    dt = wdt / omega
    n = 2000
    x = _free(CRStepper, dt, n, zeta=0.0, k=2.0 * omega**2) / 0.01
    alpha = 4 / (4 + wdt**2)
    theta = 2 * math.atan(wdt / 2)
    x1 = 1 - alpha * wdt**2
    b = (x1 - math.cos(theta)) / math.sin(theta)
    k = np.arange(n)
    ref = np.cos(k * theta) + b * np.sin(k * theta)
    np.testing.assert_allclose(x, ref, atol=1e-9 * math.hypot(1, b) * max(1, wdt))
    assert np.max(np.abs(x)) <= math.hypot(1, b) * (1 + 1e-9)


def test_cr_stable_with_damping_and_bouc_wen_at_large_step():
    for bw in (None, True):
        st = CRStepper(1.0, 0.05, fn=50.0, dt=0.1, bouc_wen=bw, v0=1.0)  # ω·Δt ≈ 31
        peak = 0.0
        for _ in range(5000):
            peak = max(peak, abs(st.step(0.0)))
        assert math.isfinite(peak) and peak < 1.0
        assert abs(st.v) < 1e-9  # motion has died out (numerical damping of c only)
        if bw is None:
            assert abs(st.x) < 1e-9 * peak


@pytest.mark.parametrize("ratio", [0.7, 1.0, 1.6])
@pytest.mark.parametrize("method", ["cr", "newmark"])
def test_steady_state_harmonic_amplitude(ratio, method):
    fs, fn, zeta, amp = 1024.0, 1.0, 0.05, 0.3
    w = 2 * np.pi * fn
    wf = ratio * w
    t = np.arange(int(40 * fs)) / fs
    ag = amp * np.sin(wf * t)
    x = simulate_sdof(ag, fs, fn, zeta, method=method)
    closed = amp / math.sqrt((w**2 - wf**2) ** 2 + (2 * zeta * w * wf) ** 2)
    tail = x[t > 30]
    assert np.max(np.abs(tail)) == pytest.approx(closed, rel=2e-3)


def _exact_linear(ag, dt, fn, zeta):
    w = 2 * np.pi * fn
    sys = ([-1.0], [1.0, 2 * zeta * w, w * w])
    t = np.arange(ag.size) * dt
    return lsim(sys, ag, t, interp=True)[1]  # exact for piecewise-linear ground acceleration


def test_cr_and_newmark_converge_at_second_order():
    gm = default_record()
    a100 = gm.accel[:800]  # first 8 s, dt = 0.01, piecewise linear between samples
    fn, zeta = 2.0, 0.02
    ref = _exact_linear(a100, 0.01, fn, zeta)
    errs = {"cr": [], "newmark": []}
    diffs = []
    for sub in (1, 2, 4, 8):
        t_fine = np.arange((a100.size - 1) * sub + 1) * (0.01 / sub)
        ag = np.interp(t_fine, np.arange(a100.size) * 0.01, a100)
        xs = {m: simulate_sdof(ag, 100.0 * sub, fn, zeta, method=m)[::sub] for m in errs}
        for m in errs:
            errs[m].append(np.max(np.abs(xs[m] - ref)) / np.max(np.abs(ref)))
        diffs.append(np.max(np.abs(xs["cr"] - xs["newmark"])))
    for m, e in errs.items():
        orders = np.log2(np.array(e[:-1]) / np.array(e[1:]))
        assert np.all(orders > 1.8), (m, e)
        assert e[-1] < 2e-3
    d_orders = np.log2(np.array(diffs[:-1]) / np.array(diffs[1:]))
    assert np.all(d_orders > 1.8), diffs


def test_linear_displacement_does_not_depend_on_stiffness():
    ag = default_record().resampled(256).accel[:2000]
    x1 = simulate_sdof(ag, 256, 1.5, 0.02, k=1.0)
    x2 = simulate_sdof(ag, 256, 1.5, 0.02)
    np.testing.assert_allclose(x1, x2, rtol=1e-9, atol=1e-15)
    r = simulate_sdof(ag, 256, 1.5, 0.02, full=True)
    np.testing.assert_allclose(r.force, K_A_PAPER * r.x)
    assert r.mass == pytest.approx(K_A_PAPER / (2 * np.pi * 1.5) ** 2)


# ------------------------------------------------------------------ hybrid (explicit) use


class _SpringPlant:
    """A specimen that is a linear spring: force = k·imposed displacement."""

    def __init__(self, k):
        self.k = k
        self.imposed = []

    def step(self, command):
        self.imposed.append(command)
        return command, self.k * command


@pytest.mark.parametrize("bouc_wen", [False, True])
def test_hybrid_loop_with_measured_force_reproduces_monolithic_model(bouc_wen):
    """Split k into numerical part k1 and a 'specimen' k2 measured at the explicit target: the
    loop of the CRStepper docstring must give the monolithic model (numerical k1+k2) exactly."""
    fs, m, k1, k2 = 1024.0, 1000.0, 3.0e4, 1.0e4
    ag = default_record().scaled("0.3g").resampled(fs).accel[: int(10 * fs)]
    c = 2 * 0.02 * math.sqrt((k1 + k2) * m)
    zeta_split = c / (2 * math.sqrt(k1 * m))
    if bouc_wen:
        mono_bw = BoucWenParams(x_y=0.005, k_a=k1)  # nonlinear part numerical in both cases
        mono = CRStepper(m, zeta_split, k1, 1 / fs, bouc_wen=mono_bw, k_specimen=k2, ag0=ag[0])
        mono_x = [mono.x]
        for a in ag[1:]:
            mono.step(a, extra_force=k2 * mono.x_next)  # spring evaluated at the same x
            mono_x.append(mono.x)
        hybrid_bw = mono_bw
    else:
        mono_x = simulate_sdof(ag, fs, math.sqrt((k1 + k2) / m) / (2 * math.pi), 0.02, k=k1 + k2)
        hybrid_bw = None
    plant = _SpringPlant(k2)
    st = CRStepper(m, zeta_split, k1, 1 / fs, bouc_wen=hybrid_bw, k_specimen=k2, ag0=ag[0])
    x_target = st.x_next
    for a in ag[1:]:
        f_meas = plant.step(x_target)[1]
        x_target = st.step(a, extra_force=f_meas)
    imposed = np.array(plant.imposed)
    np.testing.assert_allclose(imposed, np.asarray(mono_x)[1:], rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(imposed)) > 0.01


def test_cr_next_displacement_independent_of_current_force():
    st1 = CRStepper(1.0, 0.02, fn=1.0, dt=0.01)
    st2 = CRStepper(1.0, 0.02, fn=1.0, dt=0.01)
    for s in (st1, st2):
        s.step(0.5)
    x_before = st1.x_next
    st1.step(0.3, extra_force=0.0)
    st2.step(0.3, extra_force=100.0)
    assert st1.x == st2.x == x_before  # the step's displacement was fixed beforehand
    assert st1.a != st2.a and st1.x_next != st2.x_next


# ------------------------------------------------------------------ Bouc-Wen


def test_bouc_wen_monotonic_loading_closed_form():
    """β+γ = 1, q = 2, loading: dz/dx = (1 − z²)/x_y → z = tanh(x/x_y); η = 0 saturates."""
    p = BoucWenParams()
    bw = BoucWen(p)
    xs = np.linspace(0, 10 * p.x_y, 4001)[1:]
    r = np.array([bw.update(x) for x in xs])
    np.testing.assert_allclose(r, p.k_a * p.x_y * np.tanh(xs / p.x_y), rtol=1e-9)
    assert r[-1] == pytest.approx(p.k_a * p.x_y, rel=1e-7)  # 117.65 kN
    assert np.all(r <= p.k_a * p.x_y)
    # initial stiffness is k_a
    bw2 = BoucWen(p)
    assert bw2.update(1e-7) / 1e-7 == pytest.approx(p.k_a, rel=1e-9)
    # one big step gives the same (sub-stepping)
    bw3 = BoucWen(p)
    assert bw3.update(0.03) == pytest.approx(p.k_a * p.x_y * math.tanh(3.0), rel=1e-7)


@pytest.mark.parametrize(
    "params",
    [
        BoucWenParams(),
        BoucWenParams(beta=0.1, gamma=0.9, q=1.5),
        BoucWenParams(beta=0.9, gamma=0.3),
    ],
)
def test_bouc_wen_z_stays_within_bound(params):
    rng = np.random.default_rng(4)
    bw = BoucWen(params)
    path = np.cumsum(rng.normal(0, 0.4 * params.x_y, 6000))
    zmax = params.z_max
    zs = []
    for x in path:
        bw.update(x)
        zs.append(bw.z)
    zs = np.array(zs)
    assert np.max(np.abs(zs)) <= zmax * (1 + 1e-9)
    assert np.max(np.abs(zs)) > 0.95 * zmax  # the path does reach the bound region


def test_bouc_wen_hysteresis_dissipates_energy():
    p = BoucWenParams()
    for amp, dissipates in ((0.001 * p.x_y, False), (3 * p.x_y, True)):
        bw = BoucWen(p)
        t = np.linspace(0, 3, 30001)
        x = amp * np.sin(2 * np.pi * t)
        r = np.array([bw.update(v) for v in x])
        last = t >= 2.0  # one full steady cycle
        energy = np.sum(0.5 * (r[last][1:] + r[last][:-1]) * np.diff(x[last]))
        elastic_scale = 0.5 * p.k_a * amp**2
        if dissipates:
            # a loop close to elastic-perfectly-plastic: between 50 % and 100 % of 4·F_y·(2A−2x_y)
            epp = 4 * p.k_a * p.x_y * (amp - p.x_y)
            assert 0.5 * epp < energy < 1.05 * epp
        else:
            assert 0 < energy < 1e-3 * elastic_scale


def test_bouc_wen_tangent_matches_finite_difference():
    bw = BoucWen()
    bw.update(0.015)
    for x_new in (0.0151, 0.0149):
        r0, kt = bw.trial(x_new)
        h = 1e-9
        r1, _ = bw.trial(x_new + h)
        assert kt == pytest.approx((r1 - r0) / h, rel=1e-4)


def test_bouc_wen_cr_and_newmark_agree_and_converge():
    gm = default_record().scaled("0.3g")
    diffs = []
    for fs in (256, 1024):
        ag = gm.resampled(fs).accel[: int(15 * fs)]
        xc = simulate_sdof(ag, fs, 1.0, 0.02, bouc_wen=True)
        xn = simulate_sdof(ag, fs, 1.0, 0.02, bouc_wen=True, method="newmark")
        assert np.max(np.abs(xc)) > 3 * BoucWenParams().x_y  # well into the nonlinear range
        diffs.append(np.max(np.abs(xc - xn)) / np.max(np.abs(xc)))
    assert diffs[1] < diffs[0] / 8 and diffs[1] < 1e-3


def test_bouc_wen_force_history_bounded_in_simulation():
    gm = default_record().scaled("0.5g").resampled(512)
    r = simulate_sdof(gm.accel, 512, 0.8, 0.02, bouc_wen=True, full=True)
    assert np.max(np.abs(r.force)) <= K_A_PAPER * 0.01 * (1 + 1e-9)
    assert np.max(np.abs(r.x)) > 0.02


# ------------------------------------------------------------------ input checking


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mass": -1.0, "zeta": 0.02, "k": 1.0, "dt": 0.01}, "mass"),
        ({"mass": 1.0, "zeta": -0.1, "k": 1.0, "dt": 0.01}, "zeta"),
        ({"mass": 1.0, "zeta": 0.02, "dt": 0.01}, "stiffness k"),
        ({"mass": 1.0, "zeta": 0.02, "k": 1.0, "dt": 0.01, "fn": 1.0}, "not both"),
        ({"mass": 1.0, "zeta": 0.02, "k": 1.0, "dt": 0.0}, "time step"),
        ({"mass": 1.0, "zeta": 0.02, "fn": -2.0, "dt": 0.01}, "natural frequency"),
        ({"mass": 1.0, "zeta": 0.02, "k": 5.0, "dt": 0.01, "bouc_wen": BoucWenParams()}, "k_a"),
    ],
)
def test_bad_structure_arguments(kwargs, message):
    for cls in (CRStepper, NewmarkStepper):
        with pytest.raises(InputError, match=message):
            cls(**kwargs)


def test_bad_simulate_arguments():
    ag = np.zeros(100)
    with pytest.raises(InputError, match="natural frequency"):
        simulate_sdof(ag, 100, -1.0, 0.02)
    with pytest.raises(InputError, match="Nyquist"):
        simulate_sdof(ag, 100, 60.0, 0.02)
    with pytest.raises(InputError, match="method"):
        simulate_sdof(ag, 100, 1.0, 0.02, method="rk4")
    with pytest.raises(InputError, match="x_y"):
        BoucWenParams(x_y=0)


def test_numpy_scalar_inputs_keep_python_float_state():
    st = CRStepper(1.0, 0.02, fn=1.0, dt=0.01, ag0=np.float64(0.1))
    st.step(np.float64(0.2), extra_force=np.float64(0.0))
    assert type(st.x_next) is float and type(st.a) is float
    nm = NewmarkStepper(1.0, 0.02, fn=1.0, dt=0.01, bouc_wen=BoucWenParams(k_a=(2 * np.pi) ** 2))
    nm.step(np.float64(0.2))
    assert type(nm.x) is float

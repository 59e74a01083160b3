"""The energy stability indicator against closed forms.

References computed here, independently of the module:

* a harmonic target through a pure delay τ onto an elastic specimen k_e injects
  ``π k_e X² sin ωτ`` per cycle (the work of ``f_m = k_e x_t(t − τ)`` along ``x_m − x_t``);
* the coupled SDOF ``m ẍ + c ẋ + k_n x + k_e x(t − τ) = 0`` is on its stability boundary when
  its characteristic equation ``m s² + c s + k_n + k_e e^{−sτ} = 0`` has a root ``s = iω``:
  ``(mω² − k_n)² + (cω)² = k_e²`` gives ω, and ``τ_c = atan2(cω, mω² − k_n)/ω``;
* the delay differential equation itself, integrated by RK4 with the delayed displacement
  taken from the history (τ a whole number of steps).
"""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from rths_hil.stability import (
    StabilityIndicator,
    damping_along,
    injected_energy,
    stability_indicator,
)

# the coupled SDOF of the analytic cases: 1 t, 0.5 Hz numerical frame with 2 % damping on its
# own stiffness, a specimen of a quarter of the frame's stiffness
M = 1000.0
KN = M * (2 * math.pi * 0.5) ** 2
ZETA = 0.02
C = 2 * ZETA * math.sqrt(KN * M)
KE = 0.25 * KN


def critical_delay(m: float, c: float, kn: float, ke: float) -> tuple[float, float]:
    """(τ_c, ω_c) of ``m s² + c s + kn + ke e^{−sτ} = 0`` (the smallest delay, ke > kn·0)."""
    b = 2 * m * kn - c * c
    w2 = (b + math.sqrt(b * b - 4 * m * m * (kn * kn - ke * ke))) / (2 * m * m)
    w = math.sqrt(w2)
    return math.atan2(c * w, m * w2 - kn) / w, w


def simulate_delay_sdof(tau: float, dt: float, duration: float, x0: float = 0.01):
    """RK4 of ``m ẍ + c ẋ + kn x = −ke x(t − τ)`` from rest at x0 (history x = x0 before 0).

    Returns time, x_t (the structure's displacement), x_m = x_t(t − τ) (the actuator's),
    f_m = ke·x_m and the velocity.
    """
    nd = round(tau / dt)
    assert nd >= 1 and abs(nd * dt - tau) < 1e-12
    n = round(duration / dt) + 1
    x = np.empty(n)
    v = np.empty(n)
    x[0], v[0] = x0, 0.0

    def delayed(i: float) -> float:  # x at step index i − nd (half steps: the mean)
        j = i - nd
        if j <= 0:
            return x0
        lo = math.floor(j)
        return x[lo] if j == lo else 0.5 * (x[lo] + x[lo + 1])

    def acc(xx: float, vv: float, xd: float) -> float:
        return -(C * vv + KN * xx + KE * xd) / M

    for i in range(n - 1):
        d0, dh, d1 = delayed(i), delayed(i + 0.5), delayed(i + 1)
        k1x, k1v = v[i], acc(x[i], v[i], d0)
        k2x, k2v = v[i] + 0.5 * dt * k1v, acc(x[i] + 0.5 * dt * k1x, v[i] + 0.5 * dt * k1v, dh)
        k3x, k3v = v[i] + 0.5 * dt * k2v, acc(x[i] + 0.5 * dt * k2x, v[i] + 0.5 * dt * k2v, dh)
        k4x, k4v = v[i] + dt * k3v, acc(x[i] + dt * k3x, v[i] + dt * k3v, d1)
        x[i + 1] = x[i] + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v[i + 1] = v[i] + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    t = np.arange(n) * dt
    xm = np.concatenate([np.full(nd, x0), x[: n - nd]])
    return t, x, xm, KE * xm, v


# ---------------------------------------------------------------------------------------------
# harmonic motion through a pure delay


@pytest.mark.parametrize("tau", [0.004, 0.012, -0.008])
def test_energy_per_cycle_of_a_delay(tau):
    fs, f0, X = 4096.0, 1.25, 0.02
    w = 2 * math.pi * f0
    cycles = 6
    t = np.arange(round(cycles * fs / f0) + 1) / fs
    xt = X * np.sin(w * t)
    xm = X * np.sin(w * (t - tau))
    e = injected_energy(xt, xm, KE * xm)
    per_cycle = math.pi * KE * X**2 * math.sin(w * tau)
    assert e[-1] / cycles == pytest.approx(per_cycle, rel=1e-4)
    # a lag injects (> 0), a lead (over-compensation) absorbs (< 0)
    assert np.sign(e[-1]) == np.sign(tau)


@pytest.mark.parametrize("tau", [0.003, 0.009, -0.005])
def test_steady_ratio_is_negative_damping_over_damping(tau):
    """S = k_e sin(ωτ)/(c ω) in steady harmonic motion, online and batch."""
    fs, f0, X = 2048.0, 0.8, 0.01
    w = 2 * math.pi * f0
    t = np.arange(round(40 / f0 * fs)) / fs
    xt = X * np.sin(w * t)
    xm = X * np.sin(w * (t - tau))
    v = X * w * np.cos(w * t)
    window = 5 / f0
    res = stability_indicator(xt, xm, KE * xm, v, fs, window, C)
    expected = KE * math.sin(w * tau) / (C * w)
    tail = res.ratio[-round(5 / f0 * fs) :]
    assert np.all(res.valid[-len(tail) :])
    # the window (5 periods) leaves a ripple of a few % at twice the frequency
    assert np.allclose(tail, expected, rtol=0.05)
    assert np.mean(tail) == pytest.approx(expected, rel=0.005)
    assert res.total_ratio == pytest.approx(expected, rel=0.01)


# ---------------------------------------------------------------------------------------------
# the coupled SDOF: the indicator's 1 is the characteristic equation's stability boundary


def test_critical_delay_small_delay_limit():
    """τ_c → c/k_e for small damping (the negative damping k_e·τ equals c)."""
    tc, _ = critical_delay(M, 0.01 * C, KN, KE)
    assert tc == pytest.approx(0.01 * C / KE, rel=0.01)


@pytest.fixture(scope="module")
def boundary():
    tc, wc = critical_delay(M, C, KN, KE)
    dt = 5e-4
    return tc, wc, dt


@pytest.mark.parametrize("factor", [0.6, 1.5])
def test_coupled_sdof_sign_and_growth(boundary, factor):
    tc, wc, dt = boundary
    tau = round(factor * tc / dt) * dt
    t, xt, xm, f, v = simulate_delay_sdof(tau, dt, 24.0)
    fs = 1 / dt
    window = 2 * 2 * math.pi / wc
    res = stability_indicator(xt, xm, f, v, fs, window, C)
    half = len(t) // 2
    first = np.abs(xt[half // 2 : half]).max()
    last = np.abs(xt[-(half // 2) :]).max()
    s = res.ratio[half:][res.valid[half:]]
    assert len(s) > 0.9 * (len(t) - half)
    if factor < 1:
        assert last < first  # the motion decays ...
        assert np.all(s < 1)  # ... and the interface injects less than the damping removes
        assert np.all(s > 0)  # (a lag: it does inject)
    else:
        assert last > 1.2 * first
        assert np.all(s > 1)


def test_coupled_sdof_at_the_boundary_reads_one(boundary):
    """At τ = τ_c the motion neither grows nor decays and S → 1 (what the theory says)."""
    tc, wc, _ = boundary
    dt = tc / round(tc / 5e-4)  # τ_c exactly a whole number of steps
    _, xt, xm, f, v = simulate_delay_sdof(tc, dt, 40.0)
    res = stability_indicator(xt, xm, f, v, 1 / dt, 3 * 2 * math.pi / wc, C)
    tail = res.ratio[-round(5.0 / dt) :]
    assert np.allclose(tail, 1.0, atol=0.08)  # the window's ripple (3 periods: ±5 %)
    # over the last whole cycles the interface injects what the damper dissipates
    n = round(4 * 2 * math.pi / wc / dt)
    per_cycles = (res.injected[-1] - res.injected[-1 - n]) / (
        res.dissipated[-1] - res.dissipated[-1 - n]
    )
    assert per_cycles == pytest.approx(1.0, abs=0.01)
    # and the envelope is flat there (the other roots have died out)
    a = np.abs(xt[-round(10 / dt) : -round(5 / dt)]).max()
    b = np.abs(xt[-round(5 / dt) :]).max()
    assert b == pytest.approx(a, rel=0.02)


# ---------------------------------------------------------------------------------------------
# online = batch, O(1) per step, validity


def _signals(n: int, fs: float, seed: int = 1):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    xt = 0.01 * np.sin(3.0 * t) * (1 + 0.5 * np.sin(0.3 * t)) + 1e-4 * rng.standard_normal(n)
    xm = np.roll(xt, 7) * 0.99 + 2e-6 * rng.standard_normal(n)
    xm[:7] = 0.0
    f = 2e5 * xm + 50 * rng.standard_normal(n)
    v = np.gradient(xt, 1 / fs)
    return xt, xm, f, v


def test_online_equals_batch():
    fs = 1024.0
    xt, xm, f, v = _signals(20000, fs)
    ind = StabilityIndicator(fs, 1.5, 3e3, min_velocity=2e-3)
    on = np.array([ind.push(*s) for s in zip(xt, xm, f, v, strict=True)])
    res = stability_indicator(xt, xm, f, v, fs, 1.5, 3e3, min_velocity=2e-3)
    assert np.array_equal(np.isnan(on), ~res.valid)
    assert res.valid.sum() > 15000
    assert np.allclose(on, res.ratio, rtol=1e-9, atol=0, equal_nan=True)
    assert ind.injected == pytest.approx(res.injected[-1], rel=1e-9)
    assert ind.dissipated == pytest.approx(res.dissipated[-1], rel=1e-9)
    assert ind.total_ratio == pytest.approx(res.total_ratio, rel=1e-9)


def test_constant_memory_per_step():
    """No buffer grows with the run: 100 000 more steps allocate nothing that stays."""
    fs = 1024.0
    xt, xm, f, v = (a.tolist() for a in _signals(2000, fs))
    ind = StabilityIndicator(fs, 2.0, 3e3)
    push = ind.push
    for s in zip(xt, xm, f, v, strict=True):
        push(*s)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for _ in range(50):
        for s in zip(xt, xm, f, v, strict=True):
            push(*s)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(d.size_diff for d in after.compare_to(before, "filename") if d.size_diff > 0)
    assert grown < 4096
    assert not hasattr(ind, "__dict__")  # a fixed set of slots


def test_at_rest_is_not_valid():
    fs = 1024.0
    n = 5000
    rng = np.random.default_rng(0)
    noise = 2e-6 * rng.standard_normal(n)
    res = stability_indicator(
        np.zeros(n), noise, 5 * rng.standard_normal(n), 1e-5 * rng.standard_normal(n), fs, 2, C
    )
    assert not res.valid.any()
    assert math.isnan(res.peak)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="damping"):
        StabilityIndicator(1024.0, 2.0, 0.0)
    with pytest.raises(ValueError, match="window"):
        StabilityIndicator(1024.0, math.nan, 1.0)
    with pytest.raises(ValueError, match="one length"):
        injected_energy(np.zeros(3), np.zeros(4), np.zeros(3))


# ---------------------------------------------------------------------------------------------
# damping along the actuator


def test_damping_along_sdof_and_shear_building():
    assert damping_along([[C]], [[KN]], [[M]], [1.0]) == pytest.approx(C)
    # two storeys, stiffness-proportional damping: the first mode's modal damping,
    # referred to the roof, from numpy's general eigensolver
    m1, m2, k1, k2, beta = 2000.0, 1000.0, 4e6, 2e6, 0.004
    Mm = np.diag([m1, m2])
    Km = np.array([[k1 + k2, -k2], [-k2, k2]])
    Cm = beta * Km
    lam, vec = np.linalg.eig(np.linalg.solve(Mm, Km))
    phi = vec[:, np.argmin(lam)]
    phi = phi / phi[1]  # the roof moves by one
    w1 = math.sqrt(lam.min())
    zeta1 = beta * w1 / 2
    expected = 2 * zeta1 * w1 * float(phi @ Mm @ phi)  # c* = 2 ζ ω m*
    assert damping_along(Cm, Km, Mm, [0.0, 1.0]) == pytest.approx(expected, rel=1e-9)
    # a specimen of stiffness ks at the first storey: the coupled structure's mode, referred
    # to the first storey (where the actuator is)
    ks = 3e6
    Kc = Km + np.diag([ks, 0.0])
    lam, vec = np.linalg.eig(np.linalg.solve(Mm, Kc))
    phi = vec[:, np.argmin(lam)]
    phi = phi / phi[0]
    expected = float(phi @ Cm @ phi)
    got = damping_along(Cm, Km, Mm, [1.0, 0.0], k_specimen=ks)
    assert got == pytest.approx(expected, rel=1e-9)
    assert got != pytest.approx(damping_along(Cm, Km, Mm, [1.0, 0.0]), rel=0.01)
    with pytest.raises(ValueError, match="fundamental mode"):
        damping_along(np.eye(2), np.eye(2), np.eye(2) * [1, 2], [0.0, 0.0])

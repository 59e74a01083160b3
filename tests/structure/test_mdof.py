"""MDOF models and the CR integrator in matrix form (rths_hil.structures.mdof).

Independent references: modal superposition with each mode's response from scipy.signal.lsim of
its continuous state-space model (exact for the piecewise-linear ground motion), the SDOF
CRStepper, scipy.integrate.solve_ivp on the nonlinear state, and the closed-form Rayleigh
damping of each mode.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.signal import lsim

from rths_hil.errors import InputError
from rths_hil.groundmotion import bundled_path, default_record, load
from rths_hil.structures.mdof import (
    MDOFCRStepper,
    from_matrices,
    load_csv,
    load_npz,
    rayleigh_coefficients,
    shear_building,
    simulate_mdof,
)
from rths_hil.structures.sdof import BoucWenParams, CRStepper

FS = 1024.0
# A 3-storey laboratory-scale shear building: floor masses (kg), storey stiffnesses (N/m)
MASSES = [2.0e4, 2.0e4, 1.5e4]
STIFFNESSES = [3.0e7, 2.5e7, 2.0e7]


def _nrms(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - ref) ** 2)) / np.sqrt(np.mean(ref**2)))


def _modal_reference(model, ag: np.ndarray, fs: float) -> np.ndarray:
    """u(t) = Σ φ_i·q_i(t), q̈_i + 2ζ_i·ω_i·q̇_i + ω_i²·q_i = −Γ_i·a_g(t) (Chopra Eq. 13.1.5).

    Modes from numpy's eigen-solver on L⁻¹·K·L⁻ᵀ, M = L·Lᵀ (not the model's own modes()),
    each modal SDOF solved exactly for linearly interpolated a_g by scipy.signal.lsim.
    """
    M, K, C = model.M, model.K, model.C
    L = np.linalg.cholesky(M)  # M = L·Lᵀ ; K·φ = ω²·M·φ  ⇔  (L⁻¹·K·L⁻ᵀ)·ψ = ω²·ψ, φ = L⁻ᵀ·ψ
    Li = np.linalg.inv(L)
    lam, psi = np.linalg.eigh(Li @ K @ Li.T)
    phi = Li.T @ psi  # mass-normalised: φᵀ·M·φ = I
    omega = np.sqrt(lam)
    zeta = np.diag(phi.T @ C @ phi) / (2 * omega)
    # classical damping: Φᵀ·C·Φ is diagonal
    off = phi.T @ C @ phi - np.diag(np.diag(phi.T @ C @ phi))
    assert np.max(np.abs(off)) < 1e-9 * np.max(np.abs(np.diag(phi.T @ C @ phi)))
    gamma = phi.T @ M @ model.influence
    t = np.arange(ag.size) / fs
    u = np.zeros((ag.size, model.n))
    for i in range(model.n):
        A = [[0.0, 1.0], [-(omega[i] ** 2), -2 * zeta[i] * omega[i]]]
        B = [[0.0], [-gamma[i]]]
        _, q, _ = lsim((A, B, [[1.0, 0.0]], [[0.0]]), ag, t, interp=True)
        u += np.outer(q, phi[:, i])
    return u


@pytest.fixture(scope="module")
def el_centro() -> np.ndarray:
    return default_record().resampled(FS).accel


def test_linear_3dof_matches_modal_superposition(el_centro):
    model = shear_building(MASSES, STIFFNESSES, zeta=0.05)
    u = simulate_mdof(model, el_centro, FS)
    ref = _modal_reference(model, el_centro, FS)
    for dof in range(3):
        assert _nrms(u[:, dof], ref[:, dof]) < 1e-3, dof
    # the storey drifts too (a relative check that is harder than floor displacements)
    drift, drift_ref = np.diff(u, axis=1, prepend=0.0), np.diff(ref, axis=1, prepend=0.0)
    for s in range(3):
        assert _nrms(drift[:, s], drift_ref[:, s]) < 1e-3, s
    assert np.max(np.abs(ref[:, 2])) > 1e-3  # a real response, millimetres


def test_linear_3dof_chichi_rayleigh_given():
    """Another record (Chi-Chi TCU045, 200 Hz → 1024 Hz) and α/β given directly."""
    gm = load(bundled_path("chichi_1999_TCU045_N.csv"))
    ag = gm.resampled(FS).accel[: int(30 * FS)]
    model = shear_building(MASSES, STIFFNESSES, rayleigh=(0.4, 0.002))
    u = simulate_mdof(model, ag, FS)
    ref = _modal_reference(model, ag, FS)
    for dof in range(3):
        assert _nrms(u[:, dof], ref[:, dof]) < 1e-3, dof


def test_matrices_consistent_mass_modal_damping_matches_modal_superposition(el_centro):
    """A 4-DOF model with a non-diagonal M, a damping ratio per mode and ι ≠ 1 (a DOF that
    the ground motion does not load directly) against modal superposition."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(4, 4))
    M = np.diag([3e4, 2e4, 2e4, 1e4]) + 2e3 * (A @ A.T) / 4
    k = np.array([4e7, 3e7, 3e7, 2e7])
    D = np.eye(4) - np.eye(4, k=-1)
    K = D.T @ np.diag(k) @ D
    model = from_matrices(M, K, modal_damping=[0.02, 0.04, 0.06, 0.08], influence=[1, 1, 1, 0])
    assert np.max(model.frequencies) < 20.0
    ag = el_centro[: int(30 * FS)]
    u = simulate_mdof(model, ag, FS)
    ref = _modal_reference(model, ag, FS)
    for dof in range(4):
        assert _nrms(u[:, dof], ref[:, dof]) < 1e-3, dof


def test_rayleigh_reproduces_zeta_on_modes_1_and_2():
    for zeta in (0.02, (0.02, 0.05)):
        model = shear_building(MASSES, STIFFNESSES, zeta=zeta)
        z = model.modal_damping_ratios()
        z1, z2 = (zeta, zeta) if isinstance(zeta, float) else zeta
        assert z[0] == pytest.approx(z1, rel=1e-10)
        assert z[1] == pytest.approx(z2, rel=1e-10)
        # mode 3 follows ζ(ω) = a0/(2ω) + a1·ω/2 (above ω2: more damped for equal ratios)
        w = model.modes()[0]
        a0, a1 = rayleigh_coefficients(w[0], w[1], z1, z2)
        assert z[2] == pytest.approx(a0 / (2 * w[2]) + a1 * w[2] / 2, rel=1e-10)
        np.testing.assert_allclose(model.C, a0 * model.M + a1 * model.K, rtol=1e-12)


def test_rayleigh_coefficients_closed_form():
    # equal ratios: a0 = 2ζ·ω1·ω2/(ω1 + ω2), a1 = 2ζ/(ω1 + ω2)
    a0, a1 = rayleigh_coefficients(2.0, 6.0, 0.05)
    assert a0 == pytest.approx(2 * 0.05 * 12 / 8)
    assert a1 == pytest.approx(2 * 0.05 / 8)
    # hand-solved 2×2 system: ζ = a0/(2ω) + a1·ω/2 at (ω, ζ) = (1, 0.1) and (3, 0.2)
    a0, a1 = rayleigh_coefficients(1.0, 3.0, 0.1, 0.2)
    assert a0 / 2 + a1 / 2 == pytest.approx(0.1)
    assert a0 / 6 + a1 * 3 / 2 == pytest.approx(0.2)
    assert (a0, a1) == pytest.approx((0.075, 0.125))


def test_modal_damping_matrix():
    K = np.array([[4.0e7, -2.0e7, 0.0], [-2.0e7, 4.0e7, -2.0e7], [0.0, -2.0e7, 2.0e7]])
    M = np.diag([1e4, 1e4, 8e3])
    model = from_matrices(M, K, modal_damping=[0.02, 0.03, 0.05])
    np.testing.assert_allclose(model.modal_damping_ratios(), [0.02, 0.03, 0.05], rtol=1e-10)
    _, phi = model.modes()
    off = phi.T @ model.C @ phi
    assert np.max(np.abs(off - np.diag(np.diag(off)))) < 1e-9 * np.max(np.abs(off))


@pytest.mark.parametrize("bouc_wen", [None, True])
def test_one_dof_reproduces_crstepper(el_centro, bouc_wen):
    """n = 1 with a specimen spring in α and in the loop equals CRStepper to round-off."""
    k = 1.1765e7
    m = k / (2 * math.pi * 1.5) ** 2
    ks = 2.0e6
    ag = el_centro * 3.0  # into the Bouc-Wen range
    sd = CRStepper(m, 0.02, k, 1 / FS, bouc_wen=bouc_wen, k_specimen=ks, ag0=ag[0])
    md = MDOFCRStepper(
        shear_building([m], [k], zeta=0.02, bouc_wen=bouc_wen),
        1 / FS,
        transforms=[[1.0]],
        k_specimen=[ks],
        ag0=ag[0],
    )
    assert md.alpha[0, 0] == pytest.approx(sd.alpha, rel=1e-14)
    xs, xm = np.empty(ag.size), np.empty(ag.size)
    xs[0] = sd.x_next
    xm[0] = md.x_next[0]
    for i in range(1, ag.size):
        xs[i] = sd.step(ag[i], ks * sd.x_next)  # a linear specimen at the target
        xm[i] = md.step(ag[i], np.array([ks * md.x_next[0]]))[0]
    peak = np.max(np.abs(xs))
    assert np.max(np.abs(xs - xm)) <= 1e-12 * peak
    assert md.restoring_force[0] == pytest.approx(sd.restoring_force, rel=1e-9, abs=1e-9 * k)
    if bouc_wen:
        assert peak > 0.010  # beyond x_y: the hysteresis is exercised


def test_bouc_wen_storeys_match_solve_ivp():
    """3 Bouc-Wen storeys vs solve_ivp on [u, v, z] (Wen's ODE in time, tight tolerances)."""
    gm = default_record().scaled("0.6g").resampled(FS)
    ag = gm.accel[: int(6 * FS)]  # the strong part of the record
    p = BoucWenParams(x_y=0.004)
    model = shear_building(MASSES, STIFFNESSES, zeta=0.03, bouc_wen=p)
    u = simulate_mdof(model, ag, FS)
    M, C, D = model.M, model.C, model.drift
    kk = np.array(STIFFNESSES)
    minv = np.linalg.inv(M)
    t = np.arange(ag.size) / FS

    def rhs(tt, y):
        x, v, z = y[:3], y[3:6], y[6:]
        a_g = np.interp(tt, t, ag)
        r = p.eta * kk * (D @ x) + (1 - p.eta) * kk * p.x_y * z
        dv = D @ v
        s = p.beta + p.gamma * np.sign(dv * z)
        dz = dv * (1 - s * np.abs(z) ** p.q) / p.x_y
        return np.concatenate([v, -a_g - minv @ (C @ v + D.T @ r), dz])

    sol = solve_ivp(rhs, (0, t[-1]), np.zeros(9), t_eval=t, rtol=1e-8, atol=1e-12)
    ref = sol.y[:3].T
    drift = np.diff(u, axis=1, prepend=0.0)
    assert np.max(np.abs(drift[:, 0])) > 1.5 * p.x_y  # yielding in storey 1
    for dof in range(3):
        assert _nrms(u[:, dof], ref[:, dof]) < 2e-3, dof


def _amplification(st: MDOFCRStepper) -> np.ndarray:
    """The linear map (u[n], v[n]) → (u[n+1], v[n+1]) of one step, column by column."""
    n = st.n_dof
    cols = []
    for i in range(2 * n):
        s0 = np.zeros(2 * n)
        s0[i] = 1.0
        st.reset(x0=s0[:n], v0=s0[n:])
        st.step(0.0, None)
        cols.append(np.concatenate([st.x, st.v]))
    return np.array(cols).T


@pytest.mark.parametrize("dt", [1 / 1024, 1 / 50, 0.5])
def test_unconditionally_stable_no_numerical_damping(dt):
    """Spectral radius of the CR step: exactly 1 undamped (no numerical damping), < 1 damped,
    at steps up to ω_max·Δt ≈ 1000 (Chen & Ricles 2008: unconditionally stable if linear)."""
    masses = [1.0e3] * 10
    stiff = np.linspace(4e8, 1e8, 10)
    undamped = shear_building(masses, stiff)
    w_max = undamped.modes()[0][-1]
    rho = np.abs(np.linalg.eigvals(_amplification(MDOFCRStepper(undamped, dt))))
    assert np.max(np.abs(rho - 1.0)) < 1e-9, (w_max * dt, rho)
    damped = MDOFCRStepper(shear_building(masses, stiff, zeta=0.05), dt)
    assert np.max(np.abs(np.linalg.eigvals(_amplification(damped)))) < 1.0 - 1e-6
    # with a stiff specimen in α as well
    st = MDOFCRStepper(undamped, dt, transforms=np.eye(10)[:2], k_specimen=[1e9, 1e9])
    assert np.max(np.abs(np.linalg.eigvals(_amplification(st)))) <= 1.0 + 1e-9
    if dt == 0.5:
        assert w_max * dt > 500


def test_explicit_interface_and_reset(el_centro):
    model = shear_building(MASSES, STIFFNESSES, zeta=0.05)
    st = MDOFCRStepper(model, 1 / FS, ag0=el_centro[0])
    first = st.x_next.copy()
    targets = [first]
    for a in el_centro[1:200]:
        x_before = st.x_next
        out = st.step(a, np.zeros(3))
        assert out is st.x_next and out is not x_before
        np.testing.assert_array_equal(st.x, x_before)  # committed the announced target
        targets.append(out.copy())
    assert st.n == 199
    st.reset(ag0=el_centro[0])
    np.testing.assert_array_equal(st.x_next, first)
    np.testing.assert_array_equal(st.step(el_centro[1], np.zeros(3)), targets[1])


def test_hybrid_partition_equals_monolithic_model(el_centro):
    """A spring specimen between floors 1 and 2, imposed through T = [-1, 1, 0] with its force
    returned as Tᵀ·f, gives the response of the building with that spring inside K."""
    ks = 8.0e6
    T = np.array([[-1.0, 1.0, 0.0]])
    model = shear_building(MASSES, STIFFNESSES, rayleigh=(0.5, 0.001))
    mono = from_matrices(model.M, model.K + ks * T.T @ T, model.C)
    ag = el_centro[: int(20 * FS)]
    ref = simulate_mdof(mono, ag, FS)
    st = MDOFCRStepper(model, 1 / FS, transforms=T, k_specimen=[ks], ag0=ag[0])
    u = np.empty_like(ref)
    u[0] = st.x
    target = st.x_next
    for i in range(1, ag.size):
        u[i] = target
        f = ks * (T @ target)  # the specimen's force at the imposed actuator displacement
        target = st.step(ag[i], T.T @ f)
    assert np.max(np.abs(u - ref)) <= 1e-9 * np.max(np.abs(ref))
    # without the specimen in α the partitioned run differs (α is part of the scheme)
    st2 = MDOFCRStepper(model, 1 / FS, ag0=ag[0])
    target = st2.x_next
    for i in range(1, 2000):
        target = st2.step(ag[i], T.T @ (ks * (T @ target)))
    assert np.max(np.abs(st2.x - ref[1999])) > 1e-9 * np.max(np.abs(ref))


def test_specimen_stiffness_through_transforms():
    """α includes Tᵀ·diag(k)·T: an inter-storey actuator [-1, 1, 0] adds k to a 2×2 block."""
    model = shear_building(MASSES, STIFFNESSES, zeta=0.05)
    dt = 1 / FS
    ks = 5.0e6
    st = MDOFCRStepper(model, dt, transforms=[[-1.0, 1.0, 0.0]], k_specimen=[ks])
    Ka = model.K.copy()
    Ka[0, 0] += ks
    Ka[1, 1] += ks
    Ka[0, 1] -= ks
    Ka[1, 0] -= ks
    np.testing.assert_allclose(st.k_alpha, Ka)
    M, C = model.M, model.C
    alpha = np.linalg.inv(M + dt / 2 * C + dt * dt / 4 * Ka) @ M
    np.testing.assert_allclose(st.alpha, alpha, rtol=1e-12)


def test_files_npz_and_csv(tmp_path, el_centro):
    model = shear_building(MASSES, STIFFNESSES, zeta=0.05)
    np.savez(tmp_path / "frame.npz", M=model.M, K=model.K, C=model.C)
    m2 = load_npz(tmp_path / "frame.npz")
    for name in ("M", "K", "C"):
        np.savetxt(tmp_path / f"{name}.csv", getattr(model, name), delimiter=",")
    m3 = load_csv(tmp_path / "M.csv", tmp_path / "K.csv", tmp_path / "C.csv")
    ag = el_centro[:2000]
    u = simulate_mdof(model, ag, FS)
    for other in (m2, m3):
        np.testing.assert_allclose(simulate_mdof(other, ag, FS), u, rtol=1e-12, atol=1e-15)
    # an influence vector as a CSV column
    (tmp_path / "iota.csv").write_text("# influence\n1\n1\n0.5\n")
    m5 = load_csv(tmp_path / "M.csv", tmp_path / "K.csv", influence=tmp_path / "iota.csv")
    np.testing.assert_array_equal(m5.influence, [1.0, 1.0, 0.5])
    # damping from the file's modes
    np.savez(tmp_path / "mk.npz", m=model.M, k=model.K)
    m4 = load_npz(tmp_path / "mk.npz", modal_damping=0.04)
    np.testing.assert_allclose(m4.modal_damping_ratios(), 0.04, rtol=1e-10)


def _one_line_error(excinfo, *words):
    msg = str(excinfo.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg


def test_bad_matrices_give_one_line_errors(tmp_path):
    K = np.array([[4.0, -2.0], [-2.0, 2.0]]) * 1e7
    M = np.diag([1e4, 1e4])
    with pytest.raises(InputError) as e:
        from_matrices(M, K + np.array([[0, 1e5], [0, 0]]))
    _one_line_error(e, "K", "not symmetric", "[0, 1]")
    with pytest.raises(InputError) as e:
        from_matrices(np.diag([1e4, 0.0]), K)
    _one_line_error(e, "M", "not positive definite")
    with pytest.raises(InputError) as e:
        from_matrices(M, np.array([[1.0, -1.0], [-1.0, 1.0]]) * 1e7)  # rigid-body mode
    _one_line_error(e, "K", "not positive definite")
    with pytest.raises(InputError) as e:
        from_matrices(M, np.ones((3, 3)))
    _one_line_error(e, "K", "3×3", "2×2")
    with pytest.raises(InputError) as e:
        from_matrices(M, K, C=np.array([[np.nan, 0], [0, 1.0]]))
    _one_line_error(e, "C", "non-finite", "row 0")
    with pytest.raises(InputError) as e:
        from_matrices(np.ones((2, 3)), K)
    _one_line_error(e, "M", "square")

    np.savez(tmp_path / "bad.npz", M=M, K=K.T + np.array([[0, 0], [1e6, 0]]))
    with pytest.raises(InputError) as e:
        load_npz(tmp_path / "bad.npz")
    _one_line_error(e, "bad.npz", "K", "not symmetric")
    np.savez(tmp_path / "nok.npz", M=M)
    with pytest.raises(InputError) as e:
        load_npz(tmp_path / "nok.npz")
    _one_line_error(e, "nok.npz", "'K'")
    with pytest.raises(InputError) as e:
        load_npz(tmp_path / "missing.npz")
    _one_line_error(e, "missing.npz", "no such file")
    np.save(tmp_path / "single.npy", M)
    with pytest.raises(InputError) as e:
        load_npz(tmp_path / "single.npy")
    _one_line_error(e, "single.npy", ".npz")
    (tmp_path / "text.npz").write_text("M = [[1]]\n")
    with pytest.raises(InputError) as e:
        load_npz(tmp_path / "text.npz")
    _one_line_error(e, "text.npz", "not a NumPy .npz archive")
    # a truncated archive (a copy cut short): every cut of a real one is refused in one line
    np.savez_compressed(tmp_path / "whole.npz", M=M, K=K)
    whole = (tmp_path / "whole.npz").read_bytes()
    for cut in range(1, len(whole), max(1, len(whole) // 23)):
        (tmp_path / "cut.npz").write_bytes(whole[:cut])
        with pytest.raises(InputError) as e:
            load_npz(tmp_path / "cut.npz")
        _one_line_error(e, "cut.npz", "truncated or damaged")

    (tmp_path / "M.csv").write_text("1e4, 0\n0, 1e4\n")
    (tmp_path / "K.csv").write_text("4e7, -2e7\n-2e7, nan\n")
    with pytest.raises(InputError) as e:
        load_csv(tmp_path / "M.csv", tmp_path / "K.csv")
    _one_line_error(e, "K.csv", "non-finite", "row 1")
    (tmp_path / "K.csv").write_text("4e7, -2e7\n-2e7, 2e7, 5\n")
    with pytest.raises(InputError) as e:
        load_csv(tmp_path / "M.csv", tmp_path / "K.csv")
    _one_line_error(e, "K.csv", "line 2")
    (tmp_path / "K.csv").write_text("4e7, -2e7\n-2e7, abc\n")
    with pytest.raises(InputError) as e:
        load_csv(tmp_path / "M.csv", tmp_path / "K.csv")
    _one_line_error(e, "K.csv", "line 2")

    with pytest.raises(InputError) as e:
        shear_building([1e4, 1e4], [2e7])
    _one_line_error(e, "2 floor masses")
    with pytest.raises(InputError) as e:
        shear_building([1e4, -1.0], [2e7, 2e7])
    _one_line_error(e, "floor 2")
    with pytest.raises(InputError) as e:
        shear_building([1e4], [2e7], zeta=0.05, rayleigh=(0.1, 0.001))
    _one_line_error(e, "only one")
    with pytest.raises(InputError) as e:
        shear_building([1e4, 1e4], [2e7, 2e7], bouc_wen=[BoucWenParams(k_a=2e7)])
    _one_line_error(e, "bouc_wen", "one per storey")
    with pytest.raises(InputError) as e:
        shear_building([1e4], [2e7], bouc_wen=[BoucWenParams(k_a=1e7)])
    _one_line_error(e, "k_a", "storey 1")
    with pytest.raises(InputError) as e:
        MDOFCRStepper(
            shear_building([1e4, 1e4], [2e7, 2e7]), 1e-3, transforms=[[1, 0, 0]], k_specimen=[1e6]
        )
    _one_line_error(e, "transforms", "2 columns")


def test_stepper_loads_its_kernel_before_the_first_step():
    """Constructing the stepper loads the numba kernel (a fresh process: nothing loaded yet).

    numba loads a cached kernel lazily at its first call (6–11 ms here): that must happen
    while the test is assembled, not in the real-time loop's first step. The warm-up call
    works on copies: the first step equals a stepper built from the same model again.
    """
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from rths_hil.structures import mdof\n"
        "m = mdof.shear_building([2e5, 2e5], [1e8, 1e8], zeta=0.02)\n"
        "assert len(mdof._cr_step.overloads) == 0\n"
        "s = mdof.MDOFCRStepper(m, 1 / 1024)\n"
        "assert len(mdof._cr_step.overloads) == 1, mdof._cr_step.overloads\n"
        "a = s.step(0.5, np.array([10.0, -5.0]))\n"
        "b = mdof.MDOFCRStepper(m, 1 / 1024).step(0.5, np.array([10.0, -5.0]))\n"
        "assert np.array_equal(a, b) and np.any(a != 0)\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]

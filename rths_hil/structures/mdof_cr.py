"""The CR integrator in matrix form: :class:`MDOFCRStepper` and :func:`simulate_mdof`.

The explicit CR algorithm of Chen & Ricles (2008) for the MDOF models of
:mod:`rths_hil.structures.mdof`, with the same interface as
:class:`rths_hil.structures.sdof.CRStepper`: after every call the next displacement vector
:attr:`~MDOFCRStepper.x_next` is known before the specimen forces of that step are measured.
For n = 1 it reproduces :class:`~rths_hil.structures.sdof.CRStepper` to round-off. The step is
a numba kernel (:func:`_cr_step`, with the Bouc-Wen element update); :func:`simulate_mdof` runs
a whole ground-motion history offline.

References
----------
C. Chen, J. M. Ricles, "Development of direct integration algorithms for structural dynamics
using discrete control theory", J. Eng. Mech. 134(8), 676–683, 2008.
C. Chen, J. M. Ricles, T. M. Marullo, O. Mercan, "Real-time hybrid testing using the
unconditionally stable explicit CR integration algorithm", Earthquake Eng. Struct. Dyn. 38(1),
23–44, 2009 (the CR algorithm in a hybrid test, α including the specimen's stiffness).
Y.-K. Wen, "Method for random vibration of hysteretic systems", J. Eng. Mech. Div. 102(2), 1976.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

from ..errors import InputError
from ..units import positive_number
from .sdof import BoucWenParams

if TYPE_CHECKING:
    from .mdof import MDOFModel

__all__ = ["MDOFCRStepper", "MDOFResponse", "simulate_mdof"]

_finite_positive = positive_number  # one checker for the package (rths_hil.units)


def _as_vector(a: Any, n: int, what: str) -> np.ndarray:
    try:
        v = np.array(a, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{what} is not a numeric vector") from None
    if v.size != n:
        raise InputError(f"{what} has {v.size} entries, expected {n} (one per DOF)")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{what} has a non-finite entry at index {int(np.argmin(np.isfinite(v)))}")
    return v


# --------------------------------------------------------------------------------------------
# the CR integrator in matrix form
# --------------------------------------------------------------------------------------------
#: Columns of the Bouc-Wen parameter table the kernel reads, one row per element.
_BW_XY, _BW_A, _BW_B, _BW_BETA, _BW_GAMMA, _BW_Q = range(6)


def _bouc_wen_table(params: tuple[BoucWenParams, ...]) -> np.ndarray:
    """Rows [x_y, η·k_a, (1 − η)·k_a·x_y, β, γ, q] (the FEI paper's Eq. 4.1 coefficients)."""
    return np.array(
        [
            [p.x_y, p.eta * p.k_a, (1.0 - p.eta) * p.k_a * p.x_y, p.beta, p.gamma, p.q]
            for p in params
        ],
        dtype=float,
    ).reshape(-1, 6)


@numba.njit(cache=True, nogil=True)
def _bw_dzdx(z, pos, bp, bm, q, xy):  # pragma: no cover - numba
    # dz/dx = (1 − (β + γ·sgn(Δx·z))·|z|^q) / x_y   (Wen 1976; the FEI paper's Eq. 4.2)
    s = bp if (z > 0.0) == pos else bm
    zq = z * z if q == 2.0 else abs(z) ** q
    return (1.0 - s * zq) / xy


@numba.njit(cache=True, nogil=True)
def _bw_update(bw, ex, ez, d, r_el):  # pragma: no cover - numba
    """Move each Bouc-Wen element from ``ex`` to ``d``: z by RK4 in x, as structure.BoucWen.

    Sub-steps of at most x_y/20; r = η·k_a·d + (1 − η)·k_a·x_y·z (the FEI paper's Eq. 4.1).
    """
    for e in range(d.size):
        xy = bw[e, 0]
        q = bw[e, 5]
        dx = d[e] - ex[e]
        z = ez[e]
        if dx != 0.0:
            nsub = 1 + int(abs(dx) * 20.0 / xy)
            h = dx / nsub
            bp = bw[e, 3] + bw[e, 4]  # loading:   sgn(Δx·z) > 0
            bm = bw[e, 3] - bw[e, 4]  # unloading: sgn(Δx·z) < 0
            pos = dx > 0.0
            for _ in range(nsub):
                k1 = _bw_dzdx(z, pos, bp, bm, q, xy)
                k2 = _bw_dzdx(z + 0.5 * h * k1, pos, bp, bm, q, xy)
                k3 = _bw_dzdx(z + 0.5 * h * k2, pos, bp, bm, q, xy)
                k4 = _bw_dzdx(z + h * k3, pos, bp, bm, q, xy)
                z += h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
        ez[e] = z
        ex[e] = d[e]
        r_el[e] = bw[e, 1] * d[e] + bw[e, 2] * z


#: Rows of the constant matrix stack the kernel reads: M⁻¹, C, K, Δt·α1, Δt²·α2.
_MINV, _C, _K, _ADT, _ADT2 = range(5)


@numba.njit(cache=True, nogil=True)
def _cr_step(x, v, ag, f, mats, iota, dt, D, bw, est):  # pragma: no cover - numba
    """One CR step in matrix form (Chen & Ricles 2008), plain loops on small arrays.

    ``x`` = u[n+1] and ``v`` = v[n+1] were announced by the previous step. Returns one new
    (4, n) array with the rows R(u[n+1]), a[n+1], u[n+2], v[n+2]; ``mats`` stacks M⁻¹, C, K,
    Δt·α1 and Δt²·α2; ``est`` holds the committed Bouc-Wen deformations and z (rows 0, 1) and
    receives the element forces (row 2). One returned array: numba boxes a tuple of arrays
    several times slower.
    """
    n = x.size
    out = np.empty((4, n))
    r = out[0]
    a = out[1]
    ne = bw.shape[0]
    if ne == 0:
        # R = K·u
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += mats[2, i, j] * x[j]
            r[i] = s
    else:
        # element deformations d = D·u, Bouc-Wen forces r(d), R = Dᵀ·r(d)
        d = np.empty(ne)
        for e in range(ne):
            s = 0.0
            for j in range(n):
                s += D[e, j] * x[j]
            d[e] = s
        _bw_update(bw, est[0], est[1], d, est[2])
        for i in range(n):
            s = 0.0
            for e in range(ne):
                s += D[e, i] * est[2, e]
            r[i] = s
    # a = −ι·a_g − M⁻¹·(C·v + R + f_e)   (M·a = −M·ι·a_g − C·v − R − f_e)
    sv = np.empty(n)
    for i in range(n):
        s = r[i] + f[i]
        for j in range(n):
            s += mats[1, i, j] * v[j]
        sv[i] = s
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += mats[0, i, j] * sv[j]
        a[i] = -iota[i] * ag - s
    # u[n+2] = u[n+1] + Δt·v[n+1] + Δt²·α2·a[n+1] ;  v[n+2] = v[n+1] + Δt·α1·a[n+1]
    for i in range(n):
        s1 = 0.0
        s2 = 0.0
        for j in range(n):
            s1 += mats[3, i, j] * a[j]
            s2 += mats[4, i, j] * a[j]
        out[2, i] = x[i] + dt * v[i] + s2
        out[3, i] = v[i] + s1
    return out


class MDOFCRStepper:
    """Explicit CR integrator (Chen & Ricles 2008) for an MDOF model, one call per step.

    The CR algorithm in matrix form, with integration parameter matrices (γ = 1/2, β = 1/4)::

        α1 = α2 = (M + γ·Δt·C + β·Δt²·K_α)⁻¹·M = 4·(4M + 2Δt·C + Δt²·K_α)⁻¹·M
        K_α = K + Tᵀ·diag(k_spec)·T

    (``K`` the initial stiffness of the numerical part, ``T`` the actuator transforms and
    ``k_spec`` estimates of the specimens' stiffnesses seen through them; Chen et al. 2009 put
    the specimen's stiffness into α the same way). The step is explicit in displacement and
    velocity::

        v[n+1] = v[n] + Δt·α1·a[n]
        u[n+1] = u[n] + Δt·v[n] + Δt²·α2·a[n]
        M·a[n+1] = −M·ι·a_g[n+1] − C·v[n+1] − R(u[n+1]) − f_e[n+1]

    For a linear model it has the characteristic equation of Newmark's average acceleration
    method mode by mode: unconditionally stable, no numerical damping.

    **Explicit property, hybrid loop.** After every call the next displacement vector
    ``u[n+1]`` is known (:attr:`x_next`) before anything of step n+1 is measured: impose
    ``T·x_next`` with the actuators, measure the forces ``f``, then call :meth:`step` with the
    ground acceleration of step n+1 and ``Tᵀ·f``; it returns ``u[n+2]``, the next target.
    The interface is that of :class:`rths_hil.structures.sdof.CRStepper` with vectors of length n.

    Parameters
    ----------
    model : MDOFModel
        The numerical substructure.
    dt : float
        Time step (s).
    transforms : array_like, shape (n_act, n), optional
        Actuator transformation rows T (actuator displacement = T·u). Default: identity when
        ``k_specimen`` has n entries.
    k_specimen : array_like, shape (n_act,), optional
        Estimated initial stiffness of each specimen (N/m), used only in α.
    x0, v0 : array_like, shape (n,), optional
        Initial displacements (m) and velocities (m/s); default rest.
    ag0 : float
        Ground acceleration at t = 0 (m/s²), for a[0].
    extra_force0 : array_like, shape (n,), optional
        External (specimen) force vector at t = 0 (N).

    Attributes
    ----------
    x, v, a : ndarray, shape (n,)
        Committed state at step n (m, m/s, m/s²).
    x_next : ndarray, shape (n,)
        Displacements of step n+1 (m), already determined. A new array after every step.
    restoring_force : ndarray, shape (n,)
        Numerical restoring force R(u[n]) (N).
    element_forces : ndarray, shape (n_el,), or None
        Bouc-Wen element (storey) forces r(d[n]) (N).
    alpha : ndarray, shape (n, n)
        α1 = α2.
    """

    explicit = True

    def __init__(
        self,
        model: MDOFModel,
        dt: float,
        *,
        transforms: Any = None,
        k_specimen: Any = None,
        x0: Any = None,
        v0: Any = None,
        ag0: float = 0.0,
        extra_force0: Any = None,
    ) -> None:
        self.model = model
        self.dt = _finite_positive(dt, "time step dt (s)")
        n = model.n
        self.k_alpha = model.K.copy()
        if k_specimen is not None:
            ks = np.array(k_specimen, dtype=float).reshape(-1)
            T = np.eye(n) if transforms is None else np.array(transforms, dtype=float)
            if T.ndim == 1:
                T = T.reshape(1, -1)
            if T.ndim != 2 or T.shape[1] != n:
                raise InputError(f"actuator transforms must have {n} columns, got shape {T.shape}")
            if ks.size != T.shape[0]:
                raise InputError(
                    f"k_specimen has {ks.size} entries for {T.shape[0]} actuator transforms"
                )
            if not np.all(np.isfinite(ks)) or np.any(ks < 0):
                raise InputError(f"k_specimen must be finite and ≥ 0 N/m, got {ks.tolist()}")
            # specimen stiffness seen through the actuators: Tᵀ·diag(k_spec)·T
            self.k_alpha = self.k_alpha + T.T @ (ks[:, None] * T)
        self.transforms = None if transforms is None else np.array(transforms, dtype=float)
        M, C = model.M, model.C
        dt_ = self.dt
        # α = 4·(4M + 2Δt·C + Δt²·K_α)⁻¹·M
        self.alpha = np.linalg.solve(4.0 * M + 2.0 * dt_ * C + dt_ * dt_ * self.k_alpha, 4.0 * M)
        self._adt = dt_ * self.alpha  # Δt·α1
        self._adt2 = dt_ * dt_ * self.alpha  # Δt²·α2
        self._minv = np.linalg.inv(M)
        self._C = C.copy()
        self._K = model.K.copy()
        self._iota = model.influence.copy()
        if model.bouc_wen is not None and model.drift is not None:
            self._D = np.ascontiguousarray(model.drift, dtype=float)
            self._bw = _bouc_wen_table(model.bouc_wen)
        else:
            self._D = np.zeros((0, n))
            self._bw = np.zeros((0, 6))
        ne = self._bw.shape[0]
        # committed element deformations d, Bouc-Wen variables z, element forces r
        self._est = np.zeros((3, ne))
        self._zero = np.zeros(n)
        self._mats = np.ascontiguousarray(
            np.stack([self._minv, self._C, self._K, self._adt, self._adt2])
        )
        self.reset(x0, v0, ag0, extra_force0)
        # load (or compile) the kernel now, on copies, so that the real-time loop's first
        # step does not: numba loads a cached kernel lazily, ≈ 6–11 ms at its first call
        _cr_step(
            self.x_next.copy(),
            self._v_next.copy(),
            0.0,
            self._zero.copy(),
            self._mats,
            self._iota,
            self.dt,
            self._D,
            self._bw,
            self._est.copy(),
        )

    # ----------------------------------------------------------------------------------------
    @property
    def n_dof(self) -> int:
        """Number of DOFs."""
        return self.model.n

    @property
    def t(self) -> float:
        """Time of the committed step (s)."""
        return self.n * self.dt

    @property
    def element_forces(self) -> np.ndarray | None:
        """Bouc-Wen element (storey) forces r(d[n]) (N), ``None`` for a linear model."""
        return self._est[2].copy() if self._est.shape[1] else None

    @property
    def element_deformations(self) -> np.ndarray | None:
        """Bouc-Wen element deformations d[n] = D·u[n] (m; storey drifts), ``None`` if linear."""
        return self._est[0].copy() if self._est.shape[1] else None

    def _vec(self, a: Any, what: str) -> np.ndarray:
        if a is None:
            return np.zeros(self.model.n)
        return _as_vector(a, self.model.n, what)

    def reset(
        self, x0: Any = None, v0: Any = None, ag0: float = 0.0, extra_force0: Any = None
    ) -> None:
        """Restart from the given initial state (t = 0); defaults: rest, no force."""
        x = self._vec(x0, "x0")
        v = self._vec(v0, "v0")
        f = self._vec(extra_force0, "extra_force0")
        if self._bw.shape[0]:
            # element deformations d = D·u, z = 0: r = η·k_a·d ; R = Dᵀ·r
            d = self._D @ x
            self._est[0] = d
            self._est[1] = 0.0
            self._est[2] = self._bw[:, _BW_A] * d
            r = self._D.T @ self._est[2]
        else:
            r = self._K @ x
        self.x, self.v = x, v
        self.restoring_force = r
        self.extra_force = f
        # a[0] = −ι·a_g[0] − M⁻¹·(C·v[0] + R(u[0]) + f_e[0])
        self.a = -self._iota * float(ag0) - self._minv @ (self._C @ v + r + f)
        self.n = 0
        self.x_next = x + self.dt * v + self._adt2 @ self.a
        self._v_next = v + self._adt @ self.a

    def step(self, ag: float, extra_force: Any = None) -> np.ndarray:
        """Commit step n+1 and return the displacements of step n+2 (m), shape (n,).

        Parameters
        ----------
        ag : float
            Ground acceleration at step n+1 (m/s²).
        extra_force : ndarray, shape (n,), optional
            External force vector at step n+1 (N) — ``Tᵀ·f`` of the specimen forces measured
            at :attr:`x_next` (n floats; not checked on this hot path). ``None``: no force.

        Returns
        -------
        ndarray
            The new :attr:`x_next`, to be imposed next.
        """
        x = self.x_next
        v = self._v_next
        if extra_force is None:
            f = self._zero
        elif type(extra_force) is np.ndarray and extra_force.dtype == np.float64:
            f = extra_force
        else:
            f = np.ascontiguousarray(extra_force, dtype=float)
        out = _cr_step(
            x, v, float(ag), f, self._mats, self._iota, self.dt, self._D, self._bw, self._est
        )
        self.x, self.v, self.a = x, v, out[1]
        self.restoring_force = out[0]
        self.extra_force = f
        self.n += 1
        xn = out[2]
        self.x_next = xn
        self._v_next = out[3]
        return xn


@dataclass
class MDOFResponse:
    """Offline response history, one row per sample of the ground motion.

    Attributes
    ----------
    x, v, a : ndarray, shape (N, n)
        Relative displacements (m), velocities (m/s), accelerations (m/s²).
    force : ndarray, shape (N, n)
        Numerical restoring force vector R (N).
    """

    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    force: np.ndarray


def simulate_mdof(
    model: MDOFModel, ag: Any, fs: float, full: bool = False
) -> np.ndarray | MDOFResponse:
    """Relative displacements (N, n) of ``model`` under ground acceleration ``ag``, from rest.

    CR integration (:class:`MDOFCRStepper`) with ``Δt = 1/fs``; ``ag[0]`` is at t = 0.
    """
    acc = np.asarray(ag, dtype=float)
    if acc.ndim != 1 or acc.size < 2:
        raise InputError("ground acceleration must be a 1-D array of ≥ 2 samples")
    fs = _finite_positive(fs, "sampling rate fs (Hz)")
    st = MDOFCRStepper(model, 1.0 / fs, ag0=float(acc[0]))
    N, n = acc.size, model.n
    x = np.empty((N, n))
    x[0] = st.x
    ag_list = acc.tolist()
    if not full:
        xn = st.x_next
        for i in range(1, N):
            x[i] = xn
            xn = st.step(ag_list[i])
        return x
    v, a, r = np.empty((N, n)), np.empty((N, n)), np.empty((N, n))
    v[0], a[0], r[0] = st.v, st.a, st.restoring_force
    for i in range(1, N):
        st.step(ag_list[i])
        x[i], v[i], a[i], r[i] = st.x, st.v, st.a, st.restoring_force
    return MDOFResponse(x, v, a, r)

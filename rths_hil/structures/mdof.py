"""MDOF numerical substructures (shear buildings, given matrices) and the CR integrator.

Equation of motion of the numerical substructure (relative displacements ``u``, n DOFs)::

    M·ü + C·u̇ + R(u) + f_e = −M·ι·a_g(t)

``M``, ``C`` and ``K`` are n×n, ``ι`` the ground-motion influence vector (ones for a building
shaken horizontally), ``R`` the numerical restoring force — linear ``K·u``, or Bouc-Wen elements
acting on element deformations ``d = D·u`` (storey drifts of a shear building) with
``R = Dᵀ·r(d)`` — and ``f_e`` the force vector the physical specimens exert on the structure
(``Tᵀ·f`` for actuators with displacement ``T·u`` and measured forces ``f``).

* :class:`MDOFModel` holds M, C, K, ι and the Bouc-Wen elements; :func:`shear_building`,
  :func:`from_matrices`, :func:`load_npz` and :func:`load_csv` build it, checking shapes,
  symmetry and definiteness (one-line :class:`~rths_hil.errors.InputError` naming the file/key).
* :func:`partition` takes a physical specimen (mass, damping, stiffness along an actuator)
  out of a reference structure and returns the numerical substructure, as the RTHS benchmark
  partitions its frame (Silva et al. 2020).
* Damping: Rayleigh ``C = a0·M + a1·K`` from damping ratios on modes 1 and 2
  (:func:`rayleigh_coefficients`, Chopra 2012 Eq. 11.4.9) or given (a0, a1); or modal damping
  ``C = M·Φ·diag(2ζ_i·ω_i)·Φᵀ·M`` with mass-normalised modes (Chopra 2012 Eq. 11.5.8).
* :class:`MDOFCRStepper` — the explicit CR algorithm of Chen & Ricles (2008) in matrix form,
  with the same interface as :class:`rths_hil.structures.sdof.CRStepper`: after every call the next
  displacement vector :attr:`~MDOFCRStepper.x_next` is known before the specimen forces of that
  step are measured. For n = 1 it reproduces :class:`~rths_hil.structures.sdof.CRStepper` to
  round-off.
* :func:`simulate_mdof` runs a whole ground-motion history offline.

References
----------
C. Chen, J. M. Ricles, "Development of direct integration algorithms for structural dynamics
using discrete control theory", J. Eng. Mech. 134(8), 676–683, 2008.
C. E. Silva, D. Gomez, A. Maghareh, S. J. Dyke, B. F. Spencer Jr., "Benchmark control problem
for real-time hybrid simulation", Mech. Syst. Signal Process. 135, 106381, 2020 (the partition of
a reference structure into numerical and physical substructures).
C. Chen, J. M. Ricles, T. M. Marullo, O. Mercan, "Real-time hybrid testing using the
unconditionally stable explicit CR integration algorithm", Earthquake Eng. Struct. Dyn. 38(1),
23–44, 2009 (the CR algorithm in a hybrid test, α including the specimen's stiffness).
A. K. Chopra, *Dynamics of Structures*, 4th ed., Prentice Hall, 2012 (Rayleigh and modal damping,
Section 11.4–11.5; modal analysis, Chapter 13).
Y.-K. Wen, "Method for random vibration of hysteretic systems", J. Eng. Mech. Div. 102(2), 1976.
"""

from __future__ import annotations

import csv
import logging
import math
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np
import scipy.linalg

from ..errors import InputError
from ..units import positive_number
from .sdof import BoucWenParams

log = logging.getLogger(__name__)

__all__ = [
    "MDOFCRStepper",
    "MDOFModel",
    "MDOFResponse",
    "from_matrices",
    "load_csv",
    "load_npz",
    "partition",
    "rayleigh_coefficients",
    "shear_building",
    "simulate_mdof",
]

#: Relative tolerance of the symmetry check ``max|A − Aᵀ| ≤ SYMMETRY_RTOL · max|A|``.
SYMMETRY_RTOL = 1e-9


# --------------------------------------------------------------------------------------------
# checks
# --------------------------------------------------------------------------------------------
_finite_positive = positive_number  # one checker for the package (rths_hil.units)


def _as_matrix(a: Any, what: str) -> np.ndarray:
    try:
        m = np.array(a, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} is not a numeric matrix") from None
    if m.ndim == 0:
        m = m.reshape(1, 1)
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] == 0:
        raise InputError(f"{what} must be a square matrix, got shape {m.shape}")
    bad = np.argwhere(~np.isfinite(m))
    if bad.size:
        i, j = bad[0]
        raise InputError(f"{what} has a non-finite entry ({m[i, j]}) at row {i}, column {j}")
    return m


def _check_symmetric(m: np.ndarray, what: str) -> None:
    diff = np.abs(m - m.T)
    scale = float(np.max(np.abs(m))) or 1.0
    if float(diff.max()) > SYMMETRY_RTOL * scale:
        i, j = np.unravel_index(int(np.argmax(diff)), diff.shape)
        raise InputError(
            f"{what} is not symmetric: [{i}, {j}] = {m[i, j]:g} but [{j}, {i}] = {m[j, i]:g}"
        )


def _check_definite(m: np.ndarray, what: str, semi: bool = False) -> None:
    lam = np.linalg.eigvalsh(m)
    scale = float(np.max(np.abs(m))) or 1.0
    lo = float(lam[0])
    if (semi and lo < -1e-9 * scale) or (not semi and lo <= 1e-12 * scale):
        kind = "positive semi-definite" if semi else "positive definite"
        raise InputError(f"{what} is not {kind} (smallest eigenvalue {lo:.6g})")


def _check_square_spd(a: Any, what: str, n: int | None = None, semi: bool = False) -> np.ndarray:
    m = _as_matrix(a, what)
    if n is not None and m.shape[0] != n:
        raise InputError(f"{what} is {m.shape[0]}×{m.shape[1]}, expected {n}×{n} (as M)")
    _check_symmetric(m, what)
    _check_definite(m, what, semi=semi)
    # exact symmetry from here on (the eigen-solver and the modal checks rely on it)
    return 0.5 * (m + m.T)


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
# the model
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class MDOFModel:
    """A linear or Bouc-Wen MDOF numerical substructure (SI units).

    Attributes
    ----------
    M, C, K : ndarray, shape (n, n)
        Mass (kg), viscous damping (N·s/m) and initial stiffness (N/m) matrices, symmetric;
        M and K positive definite, C positive semi-definite.
    influence : ndarray, shape (n,)
        Ground-motion influence vector ι (load ``−M·ι·a_g``).
    drift : ndarray, shape (n_el, n), or None
        Element deformations ``d = D·u`` of the Bouc-Wen elements (storey drifts of a shear
        building: ``d_i = u_i − u_{i−1}``); ``None`` for a linear model.
    bouc_wen : tuple of BoucWenParams, or None
        One parameter set per element (the same parameters as
        :class:`rths_hil.structures.sdof.BoucWenParams`; ``k_a`` is the element's initial stiffness,
        ``K = Dᵀ·diag(k_a)·D``).
    name : str
        Short description (``"shear building, 3 storeys"``, file name, …).
    """

    M: np.ndarray
    C: np.ndarray
    K: np.ndarray
    influence: np.ndarray
    drift: np.ndarray | None = None
    bouc_wen: tuple[BoucWenParams, ...] | None = None
    name: str = ""
    _modes: list = field(default_factory=list, repr=False, init=False)

    @property
    def n(self) -> int:
        """Number of degrees of freedom."""
        return int(self.M.shape[0])

    @property
    def linear(self) -> bool:
        """True when the restoring force is ``K·u``."""
        return self.bouc_wen is None

    def modes(self) -> tuple[np.ndarray, np.ndarray]:
        """Circular frequencies ω (rad/s, ascending) and mass-normalised mode shapes Φ.

        Generalised eigenproblem ``K·φ = ω²·M·φ`` (Chopra 2012 Eq. 10.2.4) solved by
        :func:`scipy.linalg.eigh`, so that ``Φᵀ·M·Φ = I``; each mode is signed with a positive
        top (last) DOF.
        """
        if not self._modes:
            lam, phi = scipy.linalg.eigh(self.K, self.M)
            phi = phi * np.where(phi[-1] < 0, -1.0, 1.0)
            self._modes.append((np.sqrt(lam), phi))
        omega, phi = self._modes[0]
        return omega.copy(), phi.copy()

    @property
    def frequencies(self) -> np.ndarray:
        """Natural frequencies (Hz) of the initial stiffness, ascending."""
        return self.modes()[0] / (2.0 * math.pi)

    def modal_damping_ratios(self) -> np.ndarray:
        """Damping ratio of each mode, ``ζ_i = φ_iᵀ·C·φ_i / (2·ω_i)`` (Chopra 2012 Eq. 12.4.3)."""
        omega, phi = self.modes()
        return np.einsum("ji,jk,ki->i", phi, self.C, phi) / (2.0 * omega)

    def participation(self) -> np.ndarray:
        """Modal participation factors ``Γ_i = φ_iᵀ·M·ι`` (mass-normalised modes)."""
        _, phi = self.modes()
        return phi.T @ self.M @ self.influence

    def describe(self) -> str:
        """One line: DOFs, frequencies, damping, restoring force."""
        f = ", ".join(f"{x:.3g}" for x in self.frequencies[:4])
        z = ", ".join(f"{x * 100:.2g}" for x in self.modal_damping_ratios()[:4])
        more = " …" if self.n > 4 else ""
        kind = "linear" if self.linear else f"Bouc-Wen on {len(self.bouc_wen or ())} elements"
        return f"{self.name or 'MDOF'}: n = {self.n}, f = [{f}{more}] Hz, ζ = [{z}{more}] %, {kind}"


def rayleigh_coefficients(
    omega1: float, omega2: float, zeta1: float, zeta2: float | None = None
) -> tuple[float, float]:
    """Rayleigh coefficients (a0, a1) of ``C = a0·M + a1·K`` giving ζ1 at ω1 and ζ2 at ω2.

    ``ζ(ω) = a0/(2ω) + a1·ω/2`` (Chopra 2012 Eq. 11.4.7); solving it at ω1 and ω2 (Eq. 11.4.9)::

        a0 = 2·ω1·ω2·(ζ1·ω2 − ζ2·ω1) / (ω2² − ω1²)
        a1 = 2·(ζ2·ω2 − ζ1·ω1) / (ω2² − ω1²)

    which for ζ1 = ζ2 = ζ is ``a0 = 2ζ·ω1·ω2/(ω1 + ω2)``, ``a1 = 2ζ/(ω1 + ω2)`` — also the
    limit used when ω1 = ω2.

    Parameters
    ----------
    omega1, omega2 : float
        Circular frequencies (rad/s).
    zeta1 : float
        Damping ratio at ω1.
    zeta2 : float, optional
        Damping ratio at ω2 (default: ζ1).
    """
    w1 = _finite_positive(omega1, "Rayleigh ω1 (rad/s)")
    w2 = _finite_positive(omega2, "Rayleigh ω2 (rad/s)")
    z1 = float(zeta1)
    z2 = z1 if zeta2 is None else float(zeta2)
    for z in (z1, z2):
        if not (math.isfinite(z) and z >= 0):
            raise InputError(f"damping ratio must be a finite number ≥ 0, got {z!r}")
    if abs(w2 - w1) <= 1e-12 * max(w1, w2):
        if z1 != z2:
            raise InputError("Rayleigh damping: modes 1 and 2 have the same frequency")
        return 2.0 * z1 * w1 * w2 / (w1 + w2), 2.0 * z1 / (w1 + w2)
    d = w2 * w2 - w1 * w1
    return 2.0 * w1 * w2 * (z1 * w2 - z2 * w1) / d, 2.0 * (z2 * w2 - z1 * w1) / d


def _zeta_pair(zeta: Any) -> tuple[float, float]:
    if isinstance(zeta, Sequence | np.ndarray) and not isinstance(zeta, str):
        vals = [float(z) for z in zeta]
        if len(vals) != 2:
            raise InputError(f"zeta must be one ratio or two (modes 1 and 2), got {list(zeta)}")
        return vals[0], vals[1]
    z = float(zeta)
    return z, z


def _damping(
    M: np.ndarray,
    K: np.ndarray,
    *,
    C: Any = None,
    zeta: Any = None,
    rayleigh: Any = None,
    modal_damping: Any = None,
    what: str = "damping",
) -> np.ndarray:
    """Damping matrix from exactly one of C, ζ on modes 1 and 2, (a0, a1) or modal ζ."""
    given = [k for k, v in {"C": C, "zeta": zeta, "rayleigh": rayleigh}.items() if v is not None]
    if modal_damping is not None:
        given.append("modal_damping")
    if len(given) > 1:
        raise InputError(f"{what}: give only one of {', '.join(given)}")
    n = M.shape[0]
    if C is not None:
        return _check_square_spd(C, "C", n, semi=True)
    if rayleigh is not None:
        try:
            a0, a1 = (float(x) for x in rayleigh)
        except (TypeError, ValueError):
            raise InputError(f"rayleigh must be two numbers (a0, a1), got {rayleigh!r}") from None
        if not (math.isfinite(a0) and math.isfinite(a1) and a0 >= 0 and a1 >= 0):
            raise InputError(f"rayleigh coefficients must be finite and ≥ 0, got {rayleigh!r}")
        return a0 * M + a1 * K
    if zeta is not None:
        z1, z2 = _zeta_pair(zeta)
        if n == 1:
            # one mode: c = 2ζ·√(k·m), the Rayleigh limit ω1 = ω2 (and rths_hil.structures.sdof's c)
            if z1 < 0 or not math.isfinite(z1):
                raise InputError(f"damping ratio must be a finite number ≥ 0, got {zeta!r}")
            return np.array([[2.0 * z1 * math.sqrt(K[0, 0] * M[0, 0])]])
        lam = scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=[0, 1])
        a0, a1 = rayleigh_coefficients(math.sqrt(lam[0]), math.sqrt(lam[1]), z1, z2)
        return a0 * M + a1 * K
    if modal_damping is not None:
        z = np.array(modal_damping, dtype=float).reshape(-1)
        if z.size == 1:
            z = np.full(n, z[0])
        if z.size != n or not np.all(np.isfinite(z)) or np.any(z < 0):
            raise InputError(
                f"modal_damping must be one ratio ≥ 0 or {n} (one per mode), got {modal_damping!r}"
            )
        lam, phi = scipy.linalg.eigh(K, M)
        mp = M @ phi
        # C = M·Φ·diag(2ζ_i·ω_i)·Φᵀ·M (Chopra 2012 Eq. 11.5.8, mass-normalised Φ)
        c = mp @ np.diag(2.0 * z * np.sqrt(lam)) @ mp.T
        return 0.5 * (c + c.T)
    return np.zeros_like(M)


def _storey_bouc_wen(bouc_wen: Any, k: np.ndarray | None, n: int) -> tuple[BoucWenParams, ...]:
    """One BoucWenParams per storey from True, one parameter set, a mapping or a sequence."""

    def params(p: Any, where: str) -> BoucWenParams:
        if isinstance(p, BoucWenParams):
            return p
        if isinstance(p, Mapping):
            try:
                return BoucWenParams(**{str(a): float(b) for a, b in p.items()})
            except TypeError as exc:
                raise InputError(f"{where}: {exc}") from None
        raise InputError(f"{where}: expected Bouc-Wen parameters, got {p!r}")

    if bouc_wen is True:
        if k is None:
            raise InputError("shear building: give the storey stiffnesses")
        return tuple(BoucWenParams(k_a=float(ki)) for ki in k)
    if isinstance(bouc_wen, BoucWenParams | Mapping):
        shape = params(bouc_wen, "bouc_wen")
        if k is None:
            return (shape,) * n
        # the shape (x_y, η, β, γ, q) of every storey; each storey's k_a is its stiffness
        return tuple(shape.with_stiffness(float(ki)) for ki in k)
    if isinstance(bouc_wen, Sequence) and not isinstance(bouc_wen, str):
        if len(bouc_wen) != n:
            raise InputError(f"bouc_wen has {len(bouc_wen)} entries, expected {n} (one per storey)")
        out = tuple(params(p, f"bouc_wen[{i}]") for i, p in enumerate(bouc_wen))
        if k is not None:
            for i, (p, ki) in enumerate(zip(out, k, strict=True)):
                if abs(p.k_a - ki) > 1e-9 * ki:
                    raise InputError(
                        f"bouc_wen[{i}].k_a = {p.k_a:g} N/m differs from storey {i + 1}'s "
                        f"stiffness {ki:g} N/m"
                    )
        return out
    raise InputError(f"bouc_wen must be true, Bouc-Wen parameters or a list, got {bouc_wen!r}")


def shear_building(
    masses: Sequence[float] | np.ndarray,
    stiffnesses: Sequence[float] | np.ndarray | None = None,
    *,
    zeta: float | Sequence[float] | None = None,
    rayleigh: tuple[float, float] | None = None,
    bouc_wen: bool | BoucWenParams | Mapping | Sequence | None = None,
    influence: Sequence[float] | np.ndarray | None = None,
) -> MDOFModel:
    """A shear building: lumped storey masses, storey springs, floors numbered from the ground.

    DOF i is the displacement of floor i+1 relative to the ground; storey i (between floors i
    and i+1, floor 0 the ground) has stiffness ``k_i`` and drift ``d_i = u_i − u_{i−1}``::

        M = diag(m_1 … m_n)
        K[i, i] = k_i + k_{i+1},  K[i, i+1] = K[i+1, i] = −k_{i+1}   (k_{n+1} = 0)

    Parameters
    ----------
    masses : sequence of float
        Floor masses (kg), from the first floor up.
    stiffnesses : sequence of float, optional
        Storey stiffnesses (N/m), storey 1 (ground to floor 1) first. May be omitted when
        ``bouc_wen`` is a list of parameter sets (their ``k_a``).
    zeta : float or (float, float), optional
        Damping ratio on modes 1 and 2 (one value for both, or ζ1, ζ2): Rayleigh damping from
        :func:`rayleigh_coefficients`. For one storey ``c = 2ζ·√(k·m)``.
    rayleigh : (float, float), optional
        Rayleigh coefficients (a0 in 1/s, a1 in s) of ``C = a0·M + a1·K``, instead of ``zeta``.
        Without ``zeta`` and ``rayleigh`` the model is undamped.
    bouc_wen : bool, BoucWenParams, mapping or sequence, optional
        Bouc-Wen storeys (the FEI paper's Eq. 4.1–4.2 on each storey drift). ``True``: the FEI
        paper's shape with ``k_a`` = storey stiffness; one parameter set (or mapping of its
        fields): that shape on every storey, each ``k_a`` its storey's stiffness; a sequence:
        one set per storey (each ``k_a`` must equal the storey's stiffness when both are given).
        Damping uses the initial stiffness.
    influence : sequence of float, optional
        Ground-motion influence vector (default: ones).
    """
    m = np.array(masses, dtype=float).reshape(-1)
    n = m.size
    if n == 0:
        raise InputError("shear building: give at least one storey mass")
    for i, mi in enumerate(m):
        _finite_positive(mi, f"shear building: mass of floor {i + 1} (kg)")
    bw = None
    if stiffnesses is None:
        if not bouc_wen or bouc_wen is True:
            raise InputError("shear building: give the storey stiffnesses (N/m)")
        bw = _storey_bouc_wen(bouc_wen, None, n)
        k = np.array([p.k_a for p in bw])
    else:
        k = np.array(stiffnesses, dtype=float).reshape(-1)
        if k.size != n:
            raise InputError(f"shear building: {k.size} storey stiffnesses for {n} floor masses")
        for i, ki in enumerate(k):
            _finite_positive(ki, f"shear building: stiffness of storey {i + 1} (N/m)")
        if bouc_wen is not None and bouc_wen is not False:
            bw = _storey_bouc_wen(bouc_wen, k, n)
    # storey drifts d = D·u: D[i, i] = 1, D[i, i−1] = −1 ; K = Dᵀ·diag(k)·D
    D = np.eye(n) - np.eye(n, k=-1)
    K = D.T @ np.diag(k) @ D
    M = np.diag(m)
    C = _damping(M, K, zeta=zeta, rayleigh=rayleigh, what="shear building")
    iota = np.ones(n) if influence is None else _as_vector(influence, n, "influence vector")
    return MDOFModel(
        M=M,
        C=C,
        K=K,
        influence=iota,
        drift=D if bw is not None else None,
        bouc_wen=bw,
        name=f"shear building, {n} storey{'s' if n > 1 else ''}",
    )


def from_matrices(
    M: Any,
    K: Any,
    C: Any = None,
    *,
    modal_damping: float | Sequence[float] | None = None,
    zeta: float | Sequence[float] | None = None,
    rayleigh: tuple[float, float] | None = None,
    influence: Any = None,
    name: str = "matrices",
) -> MDOFModel:
    """A linear model from its matrices (e.g. condensed from a finite-element model).

    Exactly one damping description (or none: undamped): the matrix ``C``; ``modal_damping``,
    one ratio or one per mode (``C = M·Φ·diag(2ζ_i·ω_i)·Φᵀ·M``, Chopra 2012 Eq. 11.5.8);
    ``zeta`` on modes 1 and 2 (Rayleigh); or ``rayleigh = (a0, a1)``.

    M and K must be symmetric positive definite (massless DOFs must be condensed out first);
    ``name`` prefixes every error message (the file the matrices came from).
    """
    Mm = _check_square_spd(M, f"{name}: M")
    n = Mm.shape[0]
    Km = _check_square_spd(K, f"{name}: K", n)
    if C is not None:
        Cm = _check_square_spd(C, f"{name}: C", n, semi=True)
        if modal_damping is not None or zeta is not None or rayleigh is not None:
            raise InputError(f"{name}: give either C or a damping description, not both")
    else:
        Cm = _damping(Mm, Km, zeta=zeta, rayleigh=rayleigh, modal_damping=modal_damping, what=name)
    iota = (
        np.ones(n) if influence is None else _as_vector(influence, n, f"{name}: influence vector")
    )
    return MDOFModel(M=Mm, C=Cm, K=Km, influence=iota, name=name)


def partition(
    reference: MDOFModel,
    transform: int | Sequence[float] | np.ndarray,
    *,
    mass: float = 0.0,
    damping: float = 0.0,
    stiffness: float = 0.0,
    name: str | None = None,
) -> MDOFModel:
    """The numerical substructure left when a physical specimen is taken out of ``reference``.

    The specimen (mass ``m_e``, damping ``c_e``, stiffness ``k_e``) acts along the actuator
    row ``t`` (a DOF number, 1-based, or a vector of n entries; the specimen's displacement is
    ``t·u``). The reference structure's equation of motion is split as in the RTHS benchmark
    (Silva et al. 2020, the partitioning of its reference structure)::

        M_N = M − m_e·tᵀt,   C_N = C − c_e·tᵀt,   K_N = K − k_e·tᵀt
        M_N·ü + C_N·u̇ + K_N·u + tᵀ·f_e = −M·ι·a_g,    f_e = m_e·(t·ü) + c_e·(t·u̇) + k_e·(t·u)

    so the numerical substructure keeps the ground-motion load of the whole structure: its
    influence vector is ``ι_N = M_N⁻¹·M·ι`` (load ``−M_N·ι_N·a_g = −M·ι·a_g``), and the
    specimen's measured force ``f_e`` holds only its relative inertia. With an ideal actuator
    the two together are the reference structure again.

    Parameters
    ----------
    reference : MDOFModel
        The whole structure (linear).
    transform : int or array_like
        DOF the specimen acts on (1 … n) or its actuator row ``t``.
    mass, damping, stiffness : float
        The specimen's ``m_e`` (kg), ``c_e`` (N·s/m) and ``k_e`` (N/m), each ≥ 0.
    name : str, optional
        Name of the result (default: the reference's, with "numerical").

    Raises
    ------
    InputError
        A non-linear reference, a bad row, or a remainder that is not a structure (M_N or K_N
        not positive definite, C_N not positive semi-definite).
    """
    if not reference.linear:
        raise InputError("partition: the reference structure must be linear")
    n = reference.n
    if isinstance(transform, int | np.integer):
        if not 1 <= int(transform) <= n:
            raise InputError(f"partition: DOF {transform} is out of range 1..{n}")
        t = np.zeros(n)
        t[int(transform) - 1] = 1.0
    else:
        t = _as_vector(transform, n, "partition: transform")
    values = {"mass": mass, "damping": damping, "stiffness": stiffness}
    for key, v in values.items():
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise InputError(f"partition: specimen {key} must be a finite number ≥ 0, got {v!r}")
    tt = np.outer(t, t)
    MN = reference.M - float(mass) * tt
    CN = reference.C - float(damping) * tt
    KN = reference.K - float(stiffness) * tt
    label = name or f"{reference.name or 'reference'} (numerical)"
    model = from_matrices(MN, KN, CN, name=label)  # checks M_N, K_N, C_N
    iota = np.linalg.solve(model.M, reference.M @ reference.influence)
    return MDOFModel(M=model.M, C=model.C, K=model.K, influence=iota, name=label)


_NPZ_KEYS = ("M", "K", "C", "influence")


def load_npz(path: str | Path, **damping: Any) -> MDOFModel:
    """Load ``M``, ``K`` and optionally ``C`` and ``influence`` from a NumPy ``.npz`` file.

    Keys are matched case-insensitively. ``damping`` takes :func:`from_matrices`'s
    ``modal_damping``, ``zeta`` or ``rayleigh`` when the file has no ``C``; a file's ``C``
    is used as it is and ``damping`` is then ignored.
    """
    p = Path(path)
    try:
        data = np.load(p, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        raise InputError(
            f"{p}: not a NumPy .npz archive of arrays (truncated or damaged?)"
        ) from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputError(f"{p}: a single array (.npy), expected an .npz archive with M and K")
    try:
        with data:
            arrays = {k: np.array(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error):
        raise InputError(
            f"{p}: an array in the archive cannot be read (truncated or damaged?)"
        ) from None
    by_lower = {k.lower(): k for k in arrays}
    found: dict[str, np.ndarray] = {}
    for key in _NPZ_KEYS:
        if key.lower() in by_lower:
            found[key] = arrays[by_lower[key.lower()]]
    for key in ("M", "K"):
        if key not in found:
            raise InputError(f"{p}: no array {key!r} (found: {', '.join(arrays) or 'none'})")
    if "C" in found:
        damping = {}  # the file's C is the damping (a configuration's default ζ does not apply)
    return from_matrices(
        found["M"],
        found["K"],
        found.get("C"),
        influence=found.get("influence"),
        name=f"{p.name}",
        **damping,
    )


def _read_csv_matrix(path: str | Path) -> np.ndarray:
    """A numeric matrix from a CSV file (comma- or whitespace-separated, ``#`` comments)."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read ({exc})") from None
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        cells = next(csv.reader([line])) if "," in line else line.split()
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise InputError(f"{p}, line {lineno}: not a row of numbers: {line[:60]!r}") from None
        if len(rows[-1]) != len(rows[0]):
            raise InputError(
                f"{p}, line {lineno}: {len(rows[-1])} values, the first row has {len(rows[0])}"
            )
    if not rows:
        raise InputError(f"{p}: no numbers")
    return np.array(rows)


def load_csv(
    M: str | Path,
    K: str | Path,
    C: str | Path | None = None,
    *,
    influence: str | Path | Sequence[float] | None = None,
    **damping: Any,
) -> MDOFModel:
    """Load the matrices from CSV files, one matrix per file (one row per line).

    ``influence`` is a CSV file (one row or one column) or a sequence of numbers. ``damping``
    as :func:`from_matrices` when ``C`` is not given. Errors name the file.
    """
    m = _check_square_spd(_read_csv_matrix(M), f"{Path(M)} (M)")
    n = m.shape[0]
    k = _check_square_spd(_read_csv_matrix(K), f"{Path(K)} (K)", n)
    c = None if C is None else _check_square_spd(_read_csv_matrix(C), f"{Path(C)} (C)", n, True)
    iota: Any = influence
    if isinstance(influence, str | Path):
        iota = _as_vector(_read_csv_matrix(influence), n, f"{Path(influence)} (influence)")
    return from_matrices(m, k, c, influence=iota, name=Path(M).name, **damping)


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

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
* :class:`MDOFCRStepper` (:mod:`rths_hil.structures.mdof_cr`) — the explicit CR algorithm of
  Chen & Ricles (2008) in matrix form,
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

import numpy as np
import scipy.linalg

from ..errors import InputError
from ..units import positive_number
from .mdof_cr import MDOFCRStepper, MDOFResponse, _as_vector, simulate_mdof
from .mdof_cr import _cr_step as _cr_step  # the kernel, for its compile count
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

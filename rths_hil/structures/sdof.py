"""SDOF structures (linear or Bouc-Wen) and step-by-step integrators for RTHS.

Equation of motion of the numerical substructure (relative displacement ``x``, the FEI paper's
Section 4)::

    m·ẍ + c·ẋ + r(x) + f_e = −m·a_g(t),      c = 2·ζ·√(k·m)

``r`` is the numerical restoring force — linear ``k·x`` or Bouc-Wen (the FEI paper's Eq. 4.1–4.2,
see :class:`BoucWen`) — and ``f_e`` an externally supplied restoring force: in a hybrid test, the
force measured on the physical specimen.

Integrators (one call per step, plain Python floats, no allocation per step):

* :class:`CRStepper` — the explicit, unconditionally stable CR algorithm of Chen & Ricles
  (2008), used by the FEI paper's experiment (Section 5). The displacement of step n+1 depends only
  on step n, so it can be sent to the actuator *before* the specimen force at n+1 is measured.
* :class:`NewmarkStepper` — Newmark average acceleration (β = 1/4, γ = 1/2), implicit
  (Newton iteration for Bouc-Wen), for comparison.

:func:`simulate_sdof` runs a whole ground-motion history offline.

References
----------
C. Chen, J. M. Ricles, "Development of direct integration algorithms for structural dynamics
using discrete control theory", J. Eng. Mech. 134(8), 676–683, 2008.
Y.-K. Wen, "Method for random vibration of hysteretic systems", J. Eng. Mech. Div. 102(2), 1976.
N. M. Newmark, "A method of computation for structural dynamics", J. Eng. Mech. Div. 85, 1959.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Literal, TypedDict, Unpack, overload

import numpy as np

from ..errors import InputError
from ..units import positive_number

log = logging.getLogger(__name__)

#: The FEI paper's analytical-substructure stiffness k_a = 11.765 kN/mm, in N/m (Section 4).
K_A_PAPER = 1.1765e7


@dataclass(frozen=True)
class BoucWenParams:
    """Bouc-Wen parameters (the FEI paper's Eq. 4.1–4.2), defaults as in the FEI paper, SI units.

    Attributes
    ----------
    x_y : float
        Yield displacement x_y in m (the FEI paper: 10 mm).
    k_a : float
        Initial (elastic) stiffness k_a in N/m (the FEI paper: 11.765 kN/mm = 1.1765e7 N/m).
    eta : float
        Ratio η of post- to pre-yield stiffness (the FEI paper: 0).
    beta, gamma : float
        Loop-shape parameters β, γ (the FEI paper: 0.55, 0.45).
    q : float
        Sharpness exponent q (the FEI paper: 2).
    """

    x_y: float = 0.010
    k_a: float = K_A_PAPER
    eta: float = 0.0
    beta: float = 0.55
    gamma: float = 0.45
    q: float = 2.0

    def __post_init__(self) -> None:
        positive_number(self.x_y, "Bouc-Wen x_y")
        positive_number(self.k_a, "Bouc-Wen k_a")
        positive_number(self.q, "Bouc-Wen q")
        if not (0.0 <= self.eta <= 1.0):
            raise InputError(f"Bouc-Wen eta must lie in [0, 1], got {self.eta}")
        if not (self.beta + self.gamma > 0 and math.isfinite(self.beta + self.gamma)):
            raise InputError("Bouc-Wen beta + gamma must be > 0 (bounded hysteresis)")

    @property
    def z_max(self) -> float:
        """Bound ``(β + γ)^(−1/q)`` of ``|z|`` (holds when ``|z(0)|`` is below it)."""
        return (self.beta + self.gamma) ** (-1.0 / self.q)

    @property
    def force_max_hysteretic(self) -> float:
        """Saturation of the hysteretic part ``(1 − η)·k_a·x_y·z_max`` (N)."""
        return (1.0 - self.eta) * self.k_a * self.x_y * self.z_max

    def with_stiffness(self, k_a: float) -> BoucWenParams:
        """Same shape, different initial stiffness."""
        return replace(self, k_a=float(k_a))


class BoucWen:
    """Bouc-Wen hysteretic restoring force, a state machine driven by displacement.

    The FEI paper's Eq. 4.1 and 4.2::

        r = η·k_a·x + (1 − η)·k_a·x_y·z
        x_y·ż + γ·|ẋ|·z·|z|^(q−1) + β·ẋ·|z|^q − ẋ = 0

    Over a step the displacement moves linearly from the committed ``x`` to the new one, so
    ``dz/dx = (1 − (β + γ·sgn(Δx·z))·|z|^q) / x_y`` is integrated in x with classical RK4
    (sub-steps of at most ``x_y / 20``; the right-hand side is continuous in z since ``|z|^q``
    vanishes where the sign flips). Rate-independent: only the path of x matters.

    Parameters
    ----------
    params : BoucWenParams, optional
        The FEI paper's defaults if omitted.
    """

    __slots__ = ("_a", "_b", "_c", "_q", "_q2", "_xy", "_zt", "k_a", "params", "x", "z")

    def __init__(self, params: BoucWenParams | None = None) -> None:
        self.params = params or BoucWenParams()
        p = self.params
        self.k_a = p.k_a
        self._xy = p.x_y
        self._a = p.eta * p.k_a
        self._b = (1.0 - p.eta) * p.k_a * p.x_y
        self._q = p.q
        self._q2 = p.q == 2.0
        self.x = 0.0
        self.z = 0.0
        self._zt = 0.0

    def reset(self, x: float = 0.0, z: float = 0.0) -> None:
        """Set the state (displacement in m, hysteretic variable)."""
        self.x = float(x)
        self.z = float(z)

    @property
    def force(self) -> float:
        """Restoring force at the committed state (N)."""
        return self._a * self.x + self._b * self.z

    def _z_at(self, x_new: float) -> float:
        p = self.params
        dx = x_new - self.x
        z = self.z
        if dx == 0.0:
            return z
        xy = self._xy
        nsub = 1 + int(abs(dx) * 20.0 / xy)
        h = dx / nsub
        bp, bm = p.beta + p.gamma, p.beta - p.gamma  # sgn(dx·z) > 0 : loading ; < 0 : unloading
        pos = dx > 0.0
        q = self._q
        if self._q2:
            for _ in range(nsub):
                zz = z
                k1 = (1.0 - (bp if (zz > 0.0) == pos else bm) * zz * zz) / xy
                zz = z + 0.5 * h * k1
                k2 = (1.0 - (bp if (zz > 0.0) == pos else bm) * zz * zz) / xy
                zz = z + 0.5 * h * k2
                k3 = (1.0 - (bp if (zz > 0.0) == pos else bm) * zz * zz) / xy
                zz = z + h * k3
                k4 = (1.0 - (bp if (zz > 0.0) == pos else bm) * zz * zz) / xy
                z += h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
        else:
            for _ in range(nsub):
                zz = z
                k1 = (1.0 - (bp if (zz > 0.0) == pos else bm) * abs(zz) ** q) / xy
                zz = z + 0.5 * h * k1
                k2 = (1.0 - (bp if (zz > 0.0) == pos else bm) * abs(zz) ** q) / xy
                zz = z + 0.5 * h * k2
                k3 = (1.0 - (bp if (zz > 0.0) == pos else bm) * abs(zz) ** q) / xy
                zz = z + h * k3
                k4 = (1.0 - (bp if (zz > 0.0) == pos else bm) * abs(zz) ** q) / xy
                z += h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
        return z

    def update(self, x_new: float) -> float:
        """Move to ``x_new`` (m), commit the state and return the restoring force (N)."""
        self.z = self._z_at(x_new)
        self.x = x_new
        return self._a * x_new + self._b * self.z

    def trial(self, x_new: float) -> tuple[float, float]:
        """Force (N) and tangent stiffness dr/dx (N/m) at ``x_new`` without committing.

        :meth:`commit_trial` accepts the last trial state.
        """
        p = self.params
        z = self._z_at(x_new)
        self._zt = z
        dx = x_new - self.x
        if dx == 0.0:
            return self._a * x_new + self._b * z, self.k_a
        s = p.beta + (p.gamma if (z > 0.0) == (dx > 0.0) else -p.gamma)
        dzdx = (1.0 - s * abs(z) ** self._q) / self._xy
        return self._a * x_new + self._b * z, self._a + self._b * dzdx

    def commit_trial(self, x_new: float) -> None:
        """Accept the state of the last :meth:`trial` call (made at ``x_new``)."""
        self.z = self._zt
        self.x = x_new


def _make_restoring(
    mass: float, k: float | None, fn: float | None, bouc_wen: BoucWenParams | BoucWen | bool | None
) -> tuple[float, BoucWen | None]:
    """Resolve the initial stiffness and the Bouc-Wen model from the constructor arguments."""
    if k is not None and fn is not None:
        raise InputError("give either the stiffness k or the natural frequency fn, not both")
    if isinstance(bouc_wen, bool):
        bw_params = BoucWenParams() if bouc_wen else None
        tie = True  # the FEI paper's shape, stiffness of the structure
    elif isinstance(bouc_wen, BoucWen):
        bw_params, tie = bouc_wen.params, False
    else:
        bw_params, tie = bouc_wen, False
    if k is not None:
        k0 = positive_number(k, "stiffness k (N/m)")
    elif fn is not None:
        k0 = mass * (2.0 * math.pi * positive_number(fn, "natural frequency fn (Hz)")) ** 2
    elif bw_params is not None:
        k0 = bw_params.k_a
    else:
        raise InputError("give the stiffness k (N/m) or the natural frequency fn (Hz)")
    if bw_params is None:
        return k0, None
    if tie:
        bw_params = bw_params.with_stiffness(k0)
    elif abs(bw_params.k_a - k0) > 1e-9 * k0:
        raise InputError(
            f"Bouc-Wen k_a = {bw_params.k_a:g} N/m differs from the structure's stiffness "
            f"{k0:g} N/m; use BoucWenParams(k_a=...) or bouc_wen=True"
        )
    bw = bouc_wen if isinstance(bouc_wen, BoucWen) else BoucWen(bw_params)
    return k0, bw


class SDOFOptions(TypedDict, total=False):
    """The keyword arguments every SDOF stepper takes (see :class:`CRStepper`)."""

    fn: float | None
    bouc_wen: BoucWenParams | BoucWen | bool | None
    x0: float
    v0: float
    ag0: float
    extra_force0: float


class _SDOFStepper:
    """Common state of the SDOF steppers (see :class:`CRStepper`).

    A subclass sets its own parameters, then calls this constructor, which computes the
    structure's ``k`` and ``c``, then the integrator's coefficients (:meth:`_coefficients`),
    then starts from the initial state (:meth:`reset`).
    """

    explicit: bool = False

    def __init__(
        self,
        mass: float,
        zeta: float,
        k: float | None = None,
        dt: float | None = None,
        *,
        fn: float | None = None,
        bouc_wen: BoucWenParams | BoucWen | bool | None = None,
        x0: float = 0.0,
        v0: float = 0.0,
        ag0: float = 0.0,
        extra_force0: float = 0.0,
    ) -> None:
        self.mass = positive_number(mass, "mass (kg)")
        z = float(zeta)
        if not (math.isfinite(z) and z >= 0):
            raise InputError(f"damping ratio zeta must be ≥ 0, got {zeta!r}")
        self.zeta = z
        if dt is None:
            raise InputError("give the time step dt (s)")
        self.dt = positive_number(dt, "time step dt (s)")
        self.k, self.bouc_wen = _make_restoring(self.mass, k, fn, bouc_wen)
        self.omega = math.sqrt(self.k / self.mass)
        self.c = 2.0 * self.zeta * self.omega * self.mass
        self.x = self.v = self.a = 0.0
        self.restoring_force = 0.0
        self.extra_force = 0.0
        self.n = 0
        self._coefficients()
        self.reset(x0, v0, ag0, extra_force0)

    def _coefficients(self) -> None:
        """The integrator's constants, from ``mass``, ``c``, ``k`` and ``dt``."""

    @property
    def fn(self) -> float:
        """Initial natural frequency in Hz."""
        return self.omega / (2.0 * math.pi)

    @property
    def t(self) -> float:
        """Time of the committed step (s)."""
        return self.n * self.dt

    def _r(self, x: float) -> float:
        bw = self.bouc_wen
        return self.k * x if bw is None else bw.update(x)

    def reset(
        self, x0: float = 0.0, v0: float = 0.0, ag0: float = 0.0, extra_force0: float = 0.0
    ) -> None:
        """Restart from the given initial state (t = 0)."""
        if self.bouc_wen is not None:
            self.bouc_wen.reset(x0, 0.0)
            r0 = self.bouc_wen.force
        else:
            r0 = self.k * x0
        self.x, self.v = float(x0), float(v0)
        self.restoring_force = float(r0)
        self.extra_force = float(extra_force0)
        self.a = -float(ag0) - (self.c * self.v + r0 + self.extra_force) / self.mass
        self.n = 0

    def step(self, ag: float, extra_force: float = 0.0) -> float:
        """Advance one step under ground acceleration ``ag`` (m/s²); returns x (m)."""
        raise NotImplementedError


class CRStepper(_SDOFStepper):
    """Explicit CR integrator (Chen & Ricles 2008) for an SDOF, one call per step.

    The CR algorithm with ``α = 4m / (4m + 2Δt·c + Δt²·K)`` (K: initial stiffness of the
    numerical part plus ``k_specimen``) is explicit in displacement and velocity::

        x[n+1] = x[n] + Δt·v[n] + α·Δt²·a[n]
        v[n+1] = v[n] + α·Δt·a[n]
        m·a[n+1] = −m·a_g[n+1] − c·v[n+1] − r(x[n+1]) − f_e[n+1]

    For a linear structure it has the characteristic equation of Newmark average acceleration:
    unconditionally stable, no numerical damping, period elongation
    ``tan(ω̄Δt/2) = ωΔt/2``.

    **Explicit property, hybrid loop.** After every call the *next* displacement
    ``x[n+1]`` is known (:attr:`x_next`) before anything of step n+1 is measured. Send it to the
    actuator, measure the specimen force there, then call :meth:`step` with the ground
    acceleration of step n+1 and that force; it returns ``x[n+2]``, the next target::

        st = CRStepper(mass, zeta, k, dt, bouc_wen=BoucWenParams(k_a=k), ag0=ground_accel[0])
        x_target = st.x_next                  # x[1], known from the initial state
        for ag in ground_accel[1:]:           # a_g[1], a_g[2], ...
            f_meas = plant.step(x_target)[1]  # impose x[n+1], measure the specimen force there
            x_target = st.step(ag, extra_force=f_meas)   # commit step n+1, return x[n+2]

    ``v`` is the backward-difference velocity ``(x[n] − x[n−1])/Δt`` (a property of CR with
    α1 = α2); the initial velocity ``v0`` is therefore the mean velocity of the step before t = 0.
    Start from rest with the record's first sample ``ag0`` to reproduce :func:`simulate_sdof`.

    ``extra_force`` is the force the specimen exerts on the structure (same sign convention as
    the restoring force: positive for positive displacement of a spring). Give ``k_specimen``,
    an estimate of the specimen's initial stiffness, so that α includes it (Chen & Ricles 2008).

    Parameters
    ----------
    mass : float
        Mass (kg).
    zeta : float
        Damping ratio of ``c = 2ζ√(k·m)`` (initial stiffness).
    k : float, optional
        Initial stiffness of the numerical part (N/m). Give ``fn=`` instead to set
        ``k = m·(2π·fn)²``. With ``bouc_wen`` and neither, ``k = bouc_wen.k_a``.
    dt : float
        Time step (s).
    fn : float, optional
        Natural frequency (Hz), alternative to ``k``.
    bouc_wen : BoucWenParams, BoucWen or bool, optional
        Bouc-Wen restoring force instead of ``k·x``. ``True`` means the FEI paper's shape parameters
        with ``k_a = k``. An explicit ``k_a`` must equal ``k``.
    k_specimen : float
        Estimated initial stiffness of the physical specimen (N/m), used only in α.
    x0, v0 : float
        Initial displacement (m) and velocity (m/s).
    ag0, extra_force0 : float
        Ground acceleration (m/s²) and external force (N) at t = 0 (for a[0]).

    Attributes
    ----------
    x, v, a : float
        Committed state at step n (m, m/s, m/s²).
    x_next : float
        Displacement of step n+1 (m), already determined.
    restoring_force : float
        Numerical restoring force r(x[n]) (N).
    alpha : float
        CR integration parameter α (α1 = α2 for an SDOF).
    """

    explicit = True

    def __init__(
        self,
        mass: float,
        zeta: float,
        k: float | None = None,
        dt: float | None = None,
        *,
        k_specimen: float = 0.0,
        **options: Unpack[SDOFOptions],
    ) -> None:
        ks = float(k_specimen)
        if not (math.isfinite(ks) and ks >= 0):
            raise InputError(f"k_specimen must be ≥ 0 N/m, got {k_specimen!r}")
        self.k_specimen = ks
        super().__init__(mass, zeta, k, dt, **options)

    def _coefficients(self) -> None:
        m, dt, c = self.mass, self.dt, self.c
        self.alpha = 4.0 * m / (4.0 * m + 2.0 * dt * c + dt * dt * (self.k + self.k_specimen))
        self._adt = self.alpha * dt
        self._adt2 = self.alpha * dt * dt

    def reset(
        self, x0: float = 0.0, v0: float = 0.0, ag0: float = 0.0, extra_force0: float = 0.0
    ) -> None:
        """Restart from the given initial state (t = 0); :attr:`x_next` is then x[1]."""
        super().reset(x0, v0, ag0, extra_force0)
        self.x_next = self.x + self.dt * self.v + self._adt2 * self.a
        self._v_next = self.v + self._adt * self.a

    def step(self, ag: float, extra_force: float = 0.0) -> float:
        """Commit step n+1 and return the displacement of step n+2 (m).

        Parameters
        ----------
        ag : float
            Ground acceleration at step n+1 (m/s²).
        extra_force : float
            External restoring force at step n+1 (N), e.g. the specimen force measured at
            :attr:`x_next`.

        Returns
        -------
        float
            The new :attr:`x_next`, to be imposed on the specimen next.
        """
        ag = float(ag)  # keep the state in Python floats (numpy scalars are ~5x slower)
        extra_force = float(extra_force)
        x = self.x_next
        v = self._v_next
        bw = self.bouc_wen
        r = self.k * x if bw is None else bw.update(x)
        a = -ag - (self.c * v + r + extra_force) / self.mass
        self.x = x
        self.v = v
        self.a = a
        self.restoring_force = r
        self.extra_force = extra_force
        self.n += 1
        xn = x + self.dt * v + self._adt2 * a
        self.x_next = xn
        self._v_next = v + self._adt * a
        return xn


class NewmarkStepper(_SDOFStepper):
    """Newmark average acceleration (β = 1/4, γ = 1/2) for an SDOF, one call per step.

    Implicit: the displacement of step n+1 solves ::

        m·a[n+1] + c·v[n+1] + r(x[n+1]) + f_e[n+1] = −m·a_g[n+1]
        x[n+1] = x[n] + Δt·v[n] + Δt²/4·(a[n] + a[n+1]),  v[n+1] = v[n] + Δt/2·(a[n] + a[n+1])

    directly for a linear structure and by Newton iteration on x[n+1] for Bouc-Wen (tangent
    stiffness from :meth:`BoucWen.trial`). Because x[n+1] depends on the force at n+1, this
    stepper cannot send the displacement before measuring the force; in a hybrid loop it would
    need the force of the previous step (a one-step lag). It is here for comparison and offline
    use. Parameters as :class:`CRStepper` (without ``k_specimen``).

    :meth:`step` returns the displacement x[n+1] of the step it commits.
    """

    explicit = False

    def __init__(
        self,
        mass: float,
        zeta: float,
        k: float | None = None,
        dt: float | None = None,
        *,
        tol: float = 1e-10,
        max_iter: int = 30,
        **options: Unpack[SDOFOptions],
    ) -> None:
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.iterations = 0
        super().__init__(mass, zeta, k, dt, **options)

    def _coefficients(self) -> None:
        dt = self.dt
        self._c0 = 4.0 / (dt * dt)
        self._c1 = 4.0 / dt
        self._k_dyn = self.mass * self._c0 + self.c * 2.0 / dt

    def step(self, ag: float, extra_force: float = 0.0) -> float:
        """Advance to step n+1 with ground acceleration ``ag`` and external force ``extra_force``.

        Returns
        -------
        float
            x[n+1] (m).
        """
        ag = float(ag)
        extra_force = float(extra_force)
        m, c, dt = self.mass, self.c, self.dt
        x0, v0, a0 = self.x, self.v, self.a
        # p = m·(c0·x0 + c1·v0 + a0) + c·(2/dt·x0 + v0) − m·ag − f_e, solve k_dyn·x + r(x) = p
        p = m * (self._c0 * x0 + self._c1 * v0 + a0) + c * (2.0 / dt * x0 + v0)
        p -= m * ag + extra_force
        bw = self.bouc_wen
        if bw is None:
            x = p / (self._k_dyn + self.k)
            r = self.k * x
            self.iterations = 1
        else:
            x = x0 + dt * v0 + 0.25 * dt * dt * a0
            kd = self._k_dyn
            x_y = bw.params.x_y
            it = 0
            for it in range(1, self.max_iter + 1):  # noqa: B007 (count kept for diagnostics)
                r, kt = bw.trial(x)
                dx = (p - kd * x - r) / (kd + kt)
                x += dx
                if abs(dx) <= self.tol * (abs(x) + x_y):
                    break
            else:
                log.warning("Newmark: Newton did not converge at step %d (|dx| = %g m)", self.n, dx)
            r, _ = bw.trial(x)
            bw.commit_trial(x)
            self.iterations = it
        a = self._c0 * (x - x0) - self._c1 * v0 - a0
        v = 2.0 / dt * (x - x0) - v0
        self.x, self.v, self.a = x, v, a
        self.restoring_force = r
        self.extra_force = extra_force
        self.n += 1
        return x


@dataclass
class SDOFResponse:
    """Offline response history (one value per sample of the ground motion).

    Attributes
    ----------
    x, v, a : ndarray
        Relative displacement (m), velocity (m/s), acceleration (m/s²).
    force : ndarray
        Numerical restoring force r (N).
    mass, k : float
        Mass (kg) and initial stiffness (N/m) used.
    """

    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    force: np.ndarray
    mass: float
    k: float


@overload
def simulate_sdof(
    ag: np.ndarray,
    fs: float,
    fn: float,
    zeta: float,
    k: float | None = ...,
    bouc_wen: BoucWenParams | bool | None = ...,
    method: Literal["cr", "newmark"] = ...,
    full: Literal[False] = ...,
) -> np.ndarray: ...
@overload
def simulate_sdof(
    ag: np.ndarray,
    fs: float,
    fn: float,
    zeta: float,
    k: float | None = ...,
    bouc_wen: BoucWenParams | bool | None = ...,
    method: Literal["cr", "newmark"] = ...,
    *,
    full: Literal[True],
) -> SDOFResponse: ...
def simulate_sdof(
    ag: np.ndarray,
    fs: float,
    fn: float,
    zeta: float,
    k: float | None = None,
    bouc_wen: BoucWenParams | bool | None = None,
    method: Literal["cr", "newmark"] = "cr",
    full: bool = False,
) -> np.ndarray | SDOFResponse:
    """Relative-displacement history of an SDOF under ground acceleration ``ag``, from rest.

    The mass is ``m = k / (2π·fn)²`` so that the initial natural frequency is ``fn``. The
    displacement of a linear SDOF does not depend on ``k``; with Bouc-Wen it depends on ``k``
    only through ``x_y`` (the FEI paper's Eq. 4.1–4.2), so ``k`` may be left at the FEI paper's k_a.

    Parameters
    ----------
    ag : array_like
        Ground acceleration (m/s²) sampled at ``fs``; ``ag[0]`` at t = 0.
    fs : float
        Sampling rate (Hz), the integration step is ``1/fs``.
    fn : float
        Initial natural frequency (Hz).
    zeta : float
        Damping ratio.
    k : float, optional
        Initial stiffness (N/m). Default: ``bouc_wen.k_a`` when Bouc-Wen parameters are given,
        else the FEI paper's k_a (:data:`K_A_PAPER`).
    bouc_wen : BoucWenParams or bool, optional
        ``None``/``False``: linear. ``True``: the FEI paper's Bouc-Wen with ``k_a = k``. Parameters:
        used as given (their ``k_a`` must equal ``k``; pass ``k=params.k_a``).
    method : {"cr", "newmark"}
        Integrator: CR (default) or Newmark average acceleration.
    full : bool
        Return an :class:`SDOFResponse` instead of the displacement array.

    Returns
    -------
    ndarray or SDOFResponse
    """
    acc = np.asarray(ag, dtype=float)
    if acc.ndim != 1 or acc.size < 2:
        raise InputError("ground acceleration must be a 1-D array of ≥ 2 samples")
    fs = positive_number(fs, "sampling rate fs (Hz)")
    fn = positive_number(fn, "natural frequency fn (Hz)")
    if k is None:
        k = bouc_wen.k_a if isinstance(bouc_wen, BoucWenParams) else K_A_PAPER
    k = positive_number(k, "stiffness k (N/m)")
    if fn >= fs / 2:
        raise InputError(
            f"natural frequency {fn:g} Hz is above the Nyquist frequency {fs / 2:g} Hz"
        )
    mass = k / (2.0 * math.pi * fn) ** 2
    if method == "cr":
        st: _SDOFStepper = CRStepper(mass, zeta, k, 1.0 / fs, bouc_wen=bouc_wen, ag0=acc[0])
    elif method == "newmark":
        st = NewmarkStepper(mass, zeta, k, 1.0 / fs, bouc_wen=bouc_wen, ag0=acc[0])
    else:
        raise InputError(f"unknown integration method {method!r} (use 'cr' or 'newmark')")
    n = acc.size
    ag_list = acc.tolist()
    x = [0.0] * n
    x[0] = st.x
    step = st.step
    if not full:
        if isinstance(st, CRStepper):
            xn = st.x_next
            for i in range(1, n):
                x[i] = xn
                xn = step(ag_list[i])
        else:
            for i in range(1, n):
                x[i] = step(ag_list[i])
        return np.asarray(x)
    v = [0.0] * n
    a = [0.0] * n
    r = [0.0] * n
    v[0], a[0], r[0] = st.v, st.a, st.restoring_force
    for i in range(1, n):
        step(ag_list[i])
        x[i], v[i], a[i], r[i] = st.x, st.v, st.a, st.restoring_force
    return SDOFResponse(np.asarray(x), np.asarray(v), np.asarray(a), np.asarray(r), mass, st.k)

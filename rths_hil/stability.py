"""Online energy-based stability indicator of a real-time hybrid test.

The tracking error of an actuator is an energy source at the interface between the numerical
and the experimental substructure. The indicator compares, per actuator channel and over a
moving (exponentially weighted) window, the energy that the tracking error *injects* into the
coupled test with the energy that the numerical structure's viscous damping *dissipates*:

.. math::

    S(t) = \\frac{\\int w(t-s)\\, f_m(s)\\,[\\dot x_m(s) - \\dot x_t(s)]\\,ds}
                 {\\int w(t-s)\\, c_a\\, v_a(s)^2\\,ds},
    \\qquad w(u) = e^{-u/T_w},

with ``x_t`` the target (the displacement the numerical structure computed and moves along),
``x_m`` the measured actuator displacement, ``f_m`` the measured force the structure receives,
``v_a`` the structure's velocity along the actuator and ``c_a`` its viscous damping coefficient
along the actuator (N·s/m). ``S`` is dimensionless; ``S > 1`` means the interface feeds more
energy into the test than the damping removes.

Source and derivation
---------------------
The method takes the approach of Gálmez & Fermandois (2020, "Online Stability Analysis for
Real-Time Hybrid Simulation Testing", Frontiers in Built Environment 6:134,
doi:10.3389/fbuil.2020.00134): as its abstract states, a stability analysis of the RTHS loop by
energy methods gives an online indicator meant to detect instability before the displacements
grow, shown on the virtual RTHS benchmark problem with several compensation strategies; its
keywords name the mechanism, the actuator's delay acting as negative damping. Only the paper's
abstract, keywords and the opening of its Section 1 (Introduction) are available to this
project, so no equation of the paper is cited here, and the definition below — the energy
balance at the interface, its normalisation, the window and the levels — is derived from first
principles. Where it may differ from the paper, these are this module's choices and why:

* *normalisation* by the energy the numerical structure's viscous damping dissipates in the
  same window, so that ``S = 1`` is exactly the linear stability boundary (below) and ``S``
  does not depend on the amplitude;
* *window*: exponential, time constant ``T_w`` (``safety.stability_window``, three natural
  periods by default), so that each step costs O(1) with a handful of floats of state, and two
  periods or more average the twice-per-cycle ripple of the energy flows;
* *levels*: warning at ``S = 1`` (the boundary) and trip at 1.5 (``safety.stability_warn``,
  ``safety.stability_limit``; the margin above the window's spread that the study in
  ``docs/stability.md`` measured).

*Energy balance.* The numerical structure moves along ``x_t`` and receives the measured force
``f_m``; the specimen moves along ``x_m`` and exerts ``f_m``. With ``E_n`` the numerical
structure's mechanical energy and ``E_s`` the specimen's stored energy,

* ``dE_n/dt = P_ext − P_d − f_m·ẋ_t`` (external input, viscous dissipation, work done on the
  interface along the structure's own displacement),
* ``dE_s/dt = f_m·ẋ_m − P_s`` (work received along the actuator's displacement, the specimen's
  own dissipation),

so the whole hybrid system obeys ``d(E_n + E_s)/dt = P_ext − P_d − P_s + P_inj`` with

    P_inj = f_m·(ẋ_m − ẋ_t) = −f_m·ė,   e = x_t − x_m.

Perfect tracking (``e ≡ 0``) makes the interface energy-neutral; any tracking error makes it a
source (``P_inj > 0``) or a sink. The injected energy is ``E_inj = −∫ f_m de``: the work of the
measured force along the tracking error, computed here by the trapezoidal rule (O(1) per step).

*Harmonic motion through a pure delay.* With ``x_t = X sin ωt``, ``x_m(t) = x_t(t − τ)`` and an
elastic specimen ``f_m = k_e x_m``, one cycle gives ``∮ f_m dx_m = 0`` and
``∮ f_m dx_t = −π k_e X² sin ωτ``, so the interface injects

    E_inj per cycle = π k_e X² sin ωτ  (> 0 for a lag, < 0 for a lead),

the energy of a negative viscous damper ``c_neg = k_e sin(ωτ)/ω ≈ k_e τ``. The structure's
damper ``c`` dissipates ``π c ω X²`` per cycle, so in steady harmonic motion

    S = k_e sin(ωτ) / (c ω).

*Stability limit.* For the coupled SDOF ``m ẍ + c ẋ + k_n x + k_e x(t − τ) = 0`` a root
``s = iω`` of the characteristic equation ``m s² + c s + k_n + k_e e^{−sτ} = 0`` needs
``c ω = k_e sin ωτ`` (imaginary part) and ``m ω² = k_n + k_e cos ωτ`` (real part): at the
exact stability boundary ``S = 1``. For small delays this is ``k_e τ = c`` (Chen & Ricles
2008 show the same destabilising role of the delay through the poles of the discrete loop).
Below it ``S < 1`` and the motion decays; above it ``S > 1`` and it grows (or settles into a
limit cycle where hysteresis of the structure or the specimen absorbs the excess). Because
the numerator and the denominator are weighted by the same window, ``S`` does not depend on
the amplitude: it reads the same margin at 0.5 mm as at 40 mm, which is what lets it warn
before the displacements grow.

What ``S`` leaves out (on purpose): hysteretic dissipation of the numerical structure and the
specimen's own dissipation. Both are real and can hold a test with ``S > 1`` bounded, but
hysteretic dissipation grows only linearly with the amplitude while the injected energy grows
with its square, so such a test oscillates in a limit cycle fed by the interface, at an
amplitude set by yielding. ``S`` is therefore the margin of the test *as if it stayed linear*,
a conservative reading. See ``docs/stability.md``.

Damping along the actuator
--------------------------
For an SDOF structure ``c_a`` is its damping coefficient. For a structure of several DOFs
:func:`damping_along` refers the damping of the coupled structure's fundamental mode (the
numerical structure stiffened by the estimated specimen stiffness along the actuator) to the
actuator: with the mode scaled so that the actuator moves by one (``r·φ = 1``),
``c_a = φᵀ C φ`` — exact when the response is in that mode, approximate otherwise (on the RTHS
benchmark's virtual problem it is within 2 % of the full ``vᵀ C v``).

Units are SI (m, N, s, J, N·s/m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

__all__ = [
    "DEFAULT_MIN_VELOCITY",
    "StabilityIndicator",
    "StabilityResult",
    "damping_along",
    "injected_energy",
    "stability_indicator",
]

#: Default lowest RMS structure velocity along the actuator (m/s) over the window for a valid
#: ratio: below it the structure is at rest and both energies are of the order of the noise.
DEFAULT_MIN_VELOCITY = 2e-4


def _check_scalar(name: str, value: float, *, positive: bool = True) -> float:
    v = float(value)
    if not math.isfinite(v) or (v <= 0 if positive else v < 0):
        kind = "> 0" if positive else "≥ 0"
        raise ValueError(f"{name} must be finite and {kind}, got {value!r}")
    return v


class StabilityIndicator:
    """Online energy stability indicator of one actuator channel, O(1) per step.

    Feed one sample per loop step with :meth:`push`; read :attr:`ratio` (the windowed
    ``S``, see the module docstring), :attr:`valid`, :attr:`injected` and :attr:`dissipated`
    (cumulative energies since the start, J). The state is a handful of floats: no buffer
    grows with the run.

    Parameters
    ----------
    fs : float
        Sampling rate of the loop (Hz).
    window : float
        Time constant ``T_w`` of the exponential window (s). Two natural periods or more
        average the twice-per-cycle ripple of the energy flows.
    damping : float
        Viscous damping coefficient of the numerical structure along the actuator ``c_a``
        (N·s/m, > 0; :func:`damping_along`).
    min_velocity : float, optional
        Lowest RMS structure velocity over the window (m/s) for a valid ratio. The ratio is
        valid once the window's RMS velocity has stayed above it for a whole window (not on the
        first cycles of motion from rest, when the window holds a fraction of a cycle).

    Examples
    --------
    >>> ind = StabilityIndicator(fs=1000.0, window=2.0, damping=1e3)
    >>> for k in range(5000):
    ...     t = k / 1000.0
    ...     x, xm = 0.01 * math.sin(5 * t), 0.01 * math.sin(5 * (t - 0.01))
    ...     _ = ind.push(x, xm, 1e5 * xm, 0.05 * math.cos(5 * t))
    >>> round(ind.ratio, 1)  # k_e·sin(ωτ)/(c·ω) = 1e5·sin(0.05)/(1e3·5)
    1.0
    """

    __slots__ = (
        "_a",
        "_b",
        "_c",
        "_dt",
        "_f",
        "_lam",
        "_min_b",
        "_n",
        "_settle",
        "_settled",
        "_v2",
        "_xe",
        "damping",
        "dissipated",
        "fs",
        "injected",
        "min_velocity",
        "ratio",
        "valid",
        "window",
    )

    def __init__(
        self,
        fs: float,
        window: float,
        damping: float,
        min_velocity: float = DEFAULT_MIN_VELOCITY,
    ) -> None:
        self.fs = _check_scalar("fs (Hz)", fs)
        self.window = _check_scalar("window (s)", window)
        self.damping = _check_scalar("damping (N·s/m)", damping)
        self.min_velocity = _check_scalar("min_velocity (m/s)", min_velocity, positive=False)
        self._dt = 1.0 / self.fs
        self._lam = math.exp(-self._dt / self.window)
        self._c = self.damping * self._dt
        # the window's dissipation at an RMS velocity of min_velocity, in steady state
        self._min_b = self.damping * self.min_velocity**2 * self._dt / (1.0 - self._lam)
        # a window is valid once the structure has moved for a whole window (not on the
        # first cycles of motion from rest, when it holds a fraction of a cycle)
        self._settle = max(1, round(self.window * self.fs))
        self.reset()

    def reset(self) -> None:
        """Forget every sample (the state at the start of a run)."""
        self._a = 0.0  # windowed injected energy (J)
        self._b = 0.0  # windowed dissipated energy (J)
        self._n = 0
        self._settled = 0
        self._f = self._xe = self._v2 = 0.0
        self.injected = 0.0
        self.dissipated = 0.0
        self.ratio = math.nan
        self.valid = False

    def push(self, target: float, measured: float, force: float, velocity: float) -> float:
        """Add one step; return the windowed ratio ``S`` (NaN until the window is valid).

        Parameters
        ----------
        target : float
            The structure's displacement along the actuator this step, ``x_t`` (m).
        measured : float
            Measured actuator displacement ``x_m`` (m).
        force : float
            Measured force ``f_m`` the structure receives (N).
        velocity : float
            The structure's velocity along the actuator ``v_a`` (m/s).
        """
        xe = measured - target  # −e
        v2 = velocity * velocity
        if self._n:
            # trapezoid: the force and the velocity² at both ends of the step
            de = (self._f + force) * 0.5 * (xe - self._xe)
            dd = self._c * 0.5 * (self._v2 + v2)
            self.injected += de
            self.dissipated += dd
            self._a = a = self._lam * self._a + de
            self._b = b = self._lam * self._b + dd
            if b > self._min_b:
                self._settled += 1
            else:
                self._settled = 0
            if self._settled >= self._settle:
                self.valid = True
                self.ratio = a / b
            else:
                self.valid = False
                self.ratio = math.nan
        self._n += 1
        self._f = force
        self._xe = xe
        self._v2 = v2
        return self.ratio

    @property
    def windowed(self) -> tuple[float, float]:
        """The window's injected and dissipated energies (J)."""
        return self._a, self._b

    @property
    def total_ratio(self) -> float:
        """Whole-run ratio: injected over dissipated energy since the start (NaN before)."""
        return self.injected / self.dissipated if self.dissipated > 0.0 else math.nan


@dataclass(frozen=True)
class StabilityResult:
    """The indicator over a whole record (:func:`stability_indicator`).

    Attributes
    ----------
    ratio : ndarray
        Windowed ``S`` at every sample (NaN where not valid), as :class:`StabilityIndicator`
        gives it online.
    valid : ndarray of bool
        The window's RMS velocity has been at least ``min_velocity`` for a whole window.
    injected, dissipated : ndarray
        Cumulative injected and dissipated energy (J) up to each sample.
    """

    ratio: np.ndarray
    valid: np.ndarray
    injected: np.ndarray
    dissipated: np.ndarray

    @property
    def total_ratio(self) -> float:
        """Whole-record ratio: all the injected over all the dissipated energy."""
        d = float(self.dissipated[-1]) if len(self.dissipated) else 0.0
        return float(self.injected[-1]) / d if d > 0.0 else math.nan

    @property
    def peak(self) -> float:
        """Largest valid windowed ratio (NaN when no window was valid)."""
        r = self.ratio[self.valid]
        return float(r.max()) if len(r) else math.nan

    def first_above(self, level: float, time: np.ndarray) -> float:
        """Time of the first valid sample with ``S > level`` (NaN: never)."""
        hit = np.flatnonzero(self.valid & (self.ratio > level))
        return float(time[hit[0]]) if len(hit) else math.nan


def injected_energy(target: np.ndarray, measured: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Cumulative energy the tracking error injected at the interface (J), per sample.

    ``E_inj[k] = Σ_{j≤k} ½(f_j + f_{j−1})·[(x_m − x_t)_j − (x_m − x_t)_{j−1}]``, the trapezoidal
    ``−∫ f_m de`` (module docstring); ``E_inj[0] = 0``.
    """
    xt = np.asarray(target, dtype=float)
    xm = np.asarray(measured, dtype=float)
    f = np.asarray(force, dtype=float)
    if not (xt.shape == xm.shape == f.shape) or xt.ndim != 1:
        raise ValueError("target, measured and force must be 1-D arrays of one length")
    out = np.zeros(len(xt))
    if len(xt) > 1:
        out[1:] = np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(xm - xt))
    return out


def stability_indicator(
    target: np.ndarray,
    measured: np.ndarray,
    force: np.ndarray,
    velocity: np.ndarray,
    fs: float,
    window: float,
    damping: float,
    min_velocity: float = DEFAULT_MIN_VELOCITY,
) -> StabilityResult:
    """The indicator over a whole record (vectorised; the same numbers as the online one).

    Parameters are those of :class:`StabilityIndicator` and :meth:`StabilityIndicator.push`,
    as arrays of one length (the record's ``target``, ``measured``, ``force`` and
    ``velocity`` columns of a channel).
    """
    fs = _check_scalar("fs (Hz)", fs)
    window = _check_scalar("window (s)", window)
    damping = _check_scalar("damping (N·s/m)", damping)
    min_velocity = _check_scalar("min_velocity (m/s)", min_velocity, positive=False)
    v = np.asarray(velocity, dtype=float)
    inj = injected_energy(target, measured, force)
    if v.shape != inj.shape:
        raise ValueError("velocity must have the length of target")
    n = len(v)
    dt = 1.0 / fs
    lam = math.exp(-dt / window)
    de = np.zeros(n)
    dd = np.zeros(n)
    if n > 1:
        de[1:] = np.diff(inj)
        v2 = v * v
        dd[1:] = damping * dt * 0.5 * (v2[1:] + v2[:-1])
    a = lfilter([1.0], [1.0, -lam], de)
    b = lfilter([1.0], [1.0, -lam], dd)
    min_b = damping * min_velocity**2 * dt / (1.0 - lam)
    moving = b > min_b
    moving[:1] = False
    valid = _held_for(moving, max(1, round(window * fs)))
    ratio = np.full(n, math.nan)
    np.divide(a, b, out=ratio, where=valid)
    return StabilityResult(ratio=ratio, valid=valid, injected=inj, dissipated=np.cumsum(dd))


def _held_for(flag: np.ndarray, n: int) -> np.ndarray:
    """True where ``flag`` has been true for the last ``n`` samples in a row (this one too)."""
    # length of the run of True ending at each sample
    idx = np.arange(len(flag))
    last_false = np.maximum.accumulate(np.where(flag, -1, idx))
    return (idx - last_false) >= n


def damping_along(
    C: np.ndarray,
    K: np.ndarray,
    M: np.ndarray,
    row: np.ndarray,
    k_specimen: float = 0.0,
) -> float:
    """Viscous damping of the coupled structure's fundamental mode referred to an actuator (N·s/m).

    The fundamental mode ``φ`` of ``(K + k_s rᵀr) φ = ω² M φ`` — the numerical structure
    stiffened by the specimen along the actuator's transform ``row`` (``r``), as the test
    oscillates — scaled so that the actuator moves by one, ``r·φ = 1``; then ``c_a = φᵀ C φ``,
    the damper that dissipates in the actuator's velocity what ``C`` dissipates in that mode.
    For one DOF it is ``C``.

    Parameters
    ----------
    C, K, M : array_like
        Damping (N·s/m), stiffness (N/m) and mass (kg) matrices of the numerical structure.
    row : array_like
        The actuator's transform row (its displacement is ``row·u``).
    k_specimen : float, optional
        Estimated specimen stiffness along the actuator (N/m). Without it the mode is the
        numerical structure's own, whose shape can differ much from the coupled one (the RTHS
        benchmark: 2.96 Hz alone, 3.61 Hz coupled, and 25 % less damping referred to the
        first storey).

    Raises
    ------
    ValueError
        The actuator does not move in the fundamental mode (``row·φ = 0``).
    """
    import scipy.linalg

    C = np.atleast_2d(np.asarray(C, dtype=float))
    K = np.atleast_2d(np.asarray(K, dtype=float))
    M = np.atleast_2d(np.asarray(M, dtype=float))
    r = np.atleast_1d(np.asarray(row, dtype=float))
    ks = _check_scalar("k_specimen (N/m)", k_specimen, positive=False)
    _, phi = scipy.linalg.eigh(K + ks * np.outer(r, r), M)
    p = phi[:, 0]
    s = float(r @ p)
    if abs(s) < 1e-12 * float(np.abs(p).max()) * max(1.0, float(np.abs(r).max())):
        raise ValueError("the actuator does not move in the fundamental mode (row·φ = 0)")
    p = p / s
    return float(p @ C @ p)

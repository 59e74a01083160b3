"""Online Kalman estimation of an actuator's gain and delay, and twin calibration from a record.

The FEI paper's actuator model (Fig. 4.1) is ``measured(t) = A·target(t − d)``. The FEI (the FEI
paper's Eq. 2.1–2.5) measures ``A`` and ``d`` in the frequency domain over a window; this module
tracks the same two numbers in the time domain, sample by sample, as a second opinion in the loop.

Formulation (:class:`DelayGainEstimator`)
-----------------------------------------
State ``x = [g, τ, b]`` (gain, delay in s, and optionally a displacement offset ``b`` in m)
with a random-walk process model ``x[k+1] = x[k] + w[k]``, ``w ~ N(0, Q)``,
``Q = diag(σ_g², σ_τ², σ_b²)·dt`` (rates per √s). The measurement is nonlinear in ``τ``::

    y[k − M] = g·u(t_k − M·dt − τ) + b + v,     v ~ N(0, R)

where ``u(t_k − D·dt)`` is the third-order Lagrange interpolation of the input history at the
fractional delay ``D = τ·fs + M`` samples (the interpolator of :mod:`rths_hil.sim_backends.delay`).
An extended Kalman filter (filterpy's :class:`~filterpy.kalman.ExtendedKalmanFilter` equations)
linearises it with the Jacobian ``H = [u(t−τ), g·∂u(t−τ)/∂τ, 1]``, the derivative taken analytically
on the Lagrange polynomial. ``M`` is a small look-ahead (the measurement is held ``M`` samples) so
that negative delays — a measured signal leading its target after over-compensation, the FEI paper's
Section 5 — can be tracked too; estimates are then ``M·dt`` old.

Why not the linear regression: ``y ≈ g·u − g·τ·u̇`` (:class:`LinearDelayGainKF`) is linear in
``θ = [g, −gτ]`` but is the first term of a Taylor series. On a sinusoid of angular frequency
ω it converges to ``θ1 = g·cos ωτ`` and ``θ2 = −g·sin(ωτ)/ω``, so it reports
``ĝ = g·cos ωτ`` and ``τ̂ = tan(ωτ)/ω``: at 2 Hz with τ = 40 ms (ωτ = 0.50 rad) that is a
12 % low gain and a delay 3.8 ms too long; at 1 Hz with τ = 20 ms, 0.8 % and 0.1 ms. The EKF
has no such bias.

Cost: the filter is 3-state with a scalar measurement. filterpy's generic matrix code costs
about 60-80 µs per sample here (numpy calls on 3×3 arrays dominate); the default
``backend="fast"`` evaluates the same equations, unrolled, in one plain ``numba.njit`` kernel
per sample (:func:`_ekf_update`: push, predict, correct) at about 1 µs including the call
(see ``benchmarks/bench_models.py``) and matches the filterpy path to round-off.

Calibration (:func:`calibrate`)
-------------------------------
Fits a twin (gain, delay, optionally a first-order servo lag and an offset) to a recorded test
by nonlinear least squares (:func:`scipy.optimize.least_squares`) on the whole record, starting
from a cross-correlation delay; the residual's standard deviation becomes the twin's
displacement noise and a quantisation step is detected from the measured values.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, overload

import numba
import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter
from scipy import optimize, signal

from rths_hil.sim_backends.delay import fractional_delay, lagrange_slopes_jit, lagrange_weights_jit
from rths_hil.sim_backends.effects import Offset
from rths_hil.sim_backends.first_order import FirstOrderServo
from rths_hil.sim_backends.modelfile import ActuatorSpec, EffectSpec, ModelSpec
from rths_hil.sim_backends.plant import Sensor

from .errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "CalibrationInfo",
    "DelayGainEstimator",
    "LinearDelayGainKF",
    "calibrate",
]


# Layout of the estimator's arrays, shared by the kernels below:
#   u: ring of the input history (size slots), y: ring of the last M+1 measurements,
#   st (int64): [position of the next input, samples pushed, look-ahead M],
#   x: [g, τ, b, last innovation], p: P row-major (3×3),
#   c: [fs, τ_lo, τ_hi, R, h2 (1 with the offset state, else 0), Q_g, Q_τ, Q_b].
_FS, _LO, _HI, _R, _H2, _QG, _QT, _QB = range(8)


@numba.njit(cache=True, nogil=True)
def _ekf_push(u, y, st, u_k, y_k):  # pragma: no cover - numba
    """Store input ``u_k`` and measurement ``y_k`` of sample k = st[1]."""
    pos = st[0]
    u[pos] = u_k
    st[0] = (pos + 1) % u.size
    y[st[1] % y.size] = y_k  # sample k in slot k mod (M+1): y[k−M] is then in slot (k+1) mod
    st[1] += 1


@numba.njit(cache=True, nogil=True)
def _ekf_predict(p, c):  # pragma: no cover - numba
    """Time update of the random walk: x unchanged, P ← P + Q (Q diagonal)."""
    p[0] += c[_QG]
    p[4] += c[_QT]
    p[8] += c[_QB]


@numba.njit(cache=True, nogil=True)
def _ekf_interp(u, st, tau, fs):  # pragma: no cover - numba
    """Input at t_k − M·dt − τ and its derivative d/dτ; ok False while the history is short.

    Third-order Lagrange interpolation at D = τ·fs + M samples back (as
    :mod:`rths_hil.sim_backends.delay`), the derivative taken on the polynomial.
    """
    d = tau * fs + st[2]
    if d < 0.0:
        d = 0.0
    n0 = int(d) - 1
    if n0 < 0:
        n0 = 0
    if st[1] < n0 + 4:
        return False, 0.0, 0.0
    h0, h1, h2, h3 = lagrange_weights_jit(d - n0)
    d0, d1, d2, d3 = lagrange_slopes_jit(d - n0)
    size = u.size
    b = st[0] - 1 - n0  # newest sample, n0 back
    u0 = u[b % size]
    u1 = u[(b - 1) % size]
    u2 = u[(b - 2) % size]
    u3 = u[(b - 3) % size]
    value = h0 * u0 + h1 * u1 + h2 * u2 + h3 * u3
    dvalue = (d0 * u0 + d1 * u1 + d2 * u2 + d3 * u3) * fs
    return True, value, dvalue


@numba.njit(cache=True, nogil=True)
def _ekf_correct(u, y, st, x, p, c):  # pragma: no cover - numba
    """EKF measurement update with z = y[k−M]; False while warming up (x, P unchanged).

    The 3-state update unrolled (filterpy's ``ExtendedKalmanFilter.update``); without the
    offset state h2 = 0 and the third row/column of P stay zero: the 2-state filter.
    """
    if st[1] <= st[2]:
        return False
    z = y[st[1] % y.size]
    g = x[0]
    tau = x[1]
    ok, v, dv = _ekf_interp(u, st, tau, c[_FS])
    if not ok:
        return False
    # H = [u(t−τ), g·∂u(t−τ)/∂τ, 1]
    h0 = v
    h1 = g * dv
    h2 = c[_H2]
    p00, p01, p02 = p[0], p[1], p[2]
    p10, p11, p12 = p[3], p[4], p[5]
    p20, p21, p22 = p[6], p[7], p[8]
    # a = P·Hᵀ
    a0 = p00 * h0 + p01 * h1 + p02 * h2
    a1 = p10 * h0 + p11 * h1 + p12 * h2
    a2 = p20 * h0 + p21 * h1 + p22 * h2
    # S = H·P·Hᵀ + R ;  innovation r = z − h(x) = z − (g·u(t−τ) + b)
    s = h0 * a0 + h1 * a1 + h2 * a2 + c[_R]
    r = z - (g * v + x[2])
    x[3] = r
    # K = P·Hᵀ/S ;  x ← x + K·r (τ clipped to its range)
    k0 = a0 / s
    k1 = a1 / s
    k2 = a2 / s
    x[0] = g + k0 * r
    tau = tau + k1 * r
    lo = c[_LO]
    hi = c[_HI]
    x[1] = lo if tau < lo else hi if tau > hi else tau
    x[2] += k2 * r
    # P ← P − K·(H·P) = P − K·aᵀ (P symmetric)
    p[0] = p00 - k0 * a0
    p[1] = p01 - k0 * a1
    p[2] = p02 - k0 * a2
    p[3] = p10 - k1 * a0
    p[4] = p11 - k1 * a1
    p[5] = p12 - k1 * a2
    p[6] = p20 - k2 * a0
    p[7] = p21 - k2 * a1
    p[8] = p22 - k2 * a2
    return True


@numba.njit(cache=True, nogil=True)
def _ekf_update(u, y, st, x, p, c, u_k, y_k):  # pragma: no cover - numba
    """One sample: push, predict, correct; return (g, τ)."""
    _ekf_push(u, y, st, u_k, y_k)
    _ekf_predict(p, c)
    _ekf_correct(u, y, st, x, p, c)
    return x[0], x[1]


class DelayGainEstimator:
    """Extended Kalman filter tracking gain, delay (and offset) of ``measured ≈ g·input(t−τ)+b``.

    Parameters
    ----------
    fs : float
        Sampling rate in Hz.
    gain0, delay0 : float
        Initial estimates (delay in s).
    gain_std0, delay_std0, offset_std0 : float
        Initial standard deviations (1, s, m).
    measurement_noise : float
        Standard deviation of the measured signal's noise plus model error, in the signal's
        unit (m). Too small makes the estimates noisy, too large makes them slow.
    gain_rate, delay_rate, offset_rate : float
        Random-walk intensities (per √s): how fast each parameter may wander. Defaults let the
        delay follow a step of several ms within about a second of strong excitation.
    delay_range : (float, float)
        Bounds on the delay in s; negative lower bound allows a leading measurement (the
        look-ahead ``M`` is sized from it).
    estimate_offset : bool
        Include the offset state ``b``.
    backend : {"fast", "filterpy"}
        ``"fast"``: the EKF equations on Python floats; ``"filterpy"``: filterpy's
        :class:`~filterpy.kalman.ExtendedKalmanFilter` (same numbers, slower).

    Examples
    --------
    >>> est = DelayGainEstimator(fs=1024.0)
    >>> for u, y in zip(target, measured):  # doctest: +SKIP
    ...     gain, delay = est.update(u, y)
    """

    def __init__(
        self,
        fs: float,
        *,
        gain0: float = 1.0,
        delay0: float = 0.0,
        gain_std0: float = 0.2,
        delay_std0: float = 0.02,
        offset_std0: float = 1e-3,
        measurement_noise: float = 5e-5,
        gain_rate: float = 0.01,
        delay_rate: float = 2e-3,
        offset_rate: float = 1e-4,
        delay_range: tuple[float, float] = (-0.02, 0.1),
        estimate_offset: bool = True,
        backend: Literal["fast", "filterpy"] = "fast",
    ) -> None:
        fs = float(fs)
        if not math.isfinite(fs) or fs <= 0:
            raise InputError(f"fs: must be a positive sampling rate in Hz, got {fs!r}")
        lo, hi = (float(v) for v in delay_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise InputError(f"delay_range: need two finite bounds lo < hi, got {delay_range!r}")
        if not lo <= delay0 <= hi:
            raise InputError(f"delay0: {delay0} s is outside delay_range {delay_range}")
        if measurement_noise <= 0:
            raise InputError(f"measurement_noise: must be > 0, got {measurement_noise!r}")
        if backend not in ("fast", "filterpy"):
            raise InputError(f"backend: must be 'fast' or 'filterpy', got {backend!r}")
        self.fs = fs
        self.dt = 1.0 / fs
        self.delay_range = (lo, hi)
        self.backend = backend
        self.estimate_offset = bool(estimate_offset)
        self.n = 3 if self.estimate_offset else 2
        # look-ahead M (samples) so that D = τ·fs + M ≥ 0 for τ ≥ lo
        self._m = max(math.ceil(-lo * fs), 0)
        self._dmax = hi * fs + self._m
        size = math.floor(self._dmax) + 8
        q = [gain_rate**2 * self.dt, delay_rate**2 * self.dt, offset_rate**2 * self.dt]
        p0 = [gain_std0**2, delay_std0**2, offset_std0**2]
        if not self.estimate_offset:
            q[2] = p0[2] = 0.0
        self.R = float(measurement_noise) ** 2
        # the kernels' arrays (layout above _FS): histories, counters, state, covariance
        self._u = np.zeros(size)
        self._y = np.zeros(self._m + 1)
        self._st = np.array([0, 0, self._m], dtype=np.int64)
        self._c = np.array([fs, lo, hi, self.R, 1.0 if self.estimate_offset else 0.0, *q])
        x0 = [float(gain0), float(delay0), 0.0][: self.n]
        self.kf = ExtendedKalmanFilter(dim_x=self.n, dim_z=1)
        self.kf.x = np.array(x0, dtype=float).reshape(self.n, 1)
        self.kf.P = np.diag(p0[: self.n]).astype(float)
        self.kf.Q = np.diag(q[: self.n])
        self.kf.R = np.array([[self.R]])
        self.kf.F = np.eye(self.n)
        self._x = np.array([float(gain0), float(delay0), 0.0, 0.0])  # g, τ, b, innovation
        self._p = np.diag(p0).ravel()
        self._arrays = (self._u, self._y, self._st, self._x, self._p, self._c)
        # held samples (a missed reply: the loop repeats the last measurement): one flag per
        # slot of the measurement ring, and how many are set (0: the fast path)
        self._held = bytearray(self._m + 1)
        self._n_held = 0
        self._innovation = 0.0  # filterpy backend
        # load the kernel now on a throwaway copy, not at the loop's first sample
        u, y, st, x, p, c = (a.copy() for a in self._arrays)
        _ekf_update(u, y, st, x, p, c, 0.0, 0.0)

    # -- state ------------------------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        """State estimate ``[g, τ(, b)]``."""
        if self.backend == "filterpy":
            return self.kf.x[:, 0].copy()
        return self._x[: self.n].copy()

    @property
    def P(self) -> np.ndarray:
        """State covariance."""
        if self.backend == "filterpy":
            return self.kf.P.copy()
        return self._p.reshape(3, 3)[: self.n, : self.n].copy()

    @property
    def gain(self) -> float:
        """Current gain estimate."""
        return float(self.x[0])

    @property
    def delay(self) -> float:
        """Current delay estimate in s (positive: measured lags input)."""
        return float(self.x[1])

    @property
    def offset(self) -> float:
        """Current offset estimate (0 when not estimated)."""
        return float(self.x[2]) if self.estimate_offset else 0.0

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the estimates (sqrt of the covariance diagonal)."""
        return np.sqrt(np.maximum(np.diag(self.P), 0.0))

    @property
    def innovation(self) -> float:
        """Innovation of the latest correction: measured minus predicted (m)."""
        if self.backend == "filterpy":
            return self._innovation
        return float(self._x[3])

    @property
    def latency(self) -> float:
        """Age of the measurement the latest update used, in s (the look-ahead ``M·dt``)."""
        return self._m * self.dt

    # -- filterpy-style steps ---------------------------------------------------------------
    def push(self, input_sample: float, measured_sample: float, fresh: bool = True) -> None:
        """Store one (input, measured) sample pair; call before :meth:`predict`/:meth:`correct`.

        ``fresh=False``: the measurement is a held one (no reply came; the loop repeats the
        last): the input goes into the history as usual, and :meth:`correct` skips the
        measurement update that would use this sample (``M`` samples later).
        """
        self._mark(fresh)
        _ekf_push(self._u, self._y, self._st, float(input_sample), float(measured_sample))

    def _mark(self, fresh: bool) -> None:
        """Flag the slot of the sample about to be pushed as fresh or held."""
        if fresh and not self._n_held:
            return
        slot = int(self._st[1]) % len(self._held)
        new = 0 if fresh else 1
        self._n_held += new - self._held[slot]
        self._held[slot] = new

    def _z_held(self) -> bool:
        """The measurement the next :meth:`correct` uses (``y[k−M]``) is a held one."""
        return bool(self._n_held) and bool(self._held[int(self._st[1]) % len(self._held)])

    def predict(self) -> None:
        """Time update of the random-walk model: ``x`` unchanged, ``P += Q``."""
        if self.backend == "filterpy":
            self.kf.predict()
            return
        _ekf_predict(self._p, self._c)

    def _interp(self, tau: float) -> tuple[float, float] | None:
        """Input at ``t_k − M·dt − τ`` and its derivative with respect to ``τ``."""
        ok, value, dvalue = _ekf_interp(self._u, self._st, float(tau), self.fs)
        return (value, dvalue) if ok else None

    def correct(self) -> bool:
        """Measurement update with the stored samples; return False while warming up.

        Also False (no update) when the measurement it would use was pushed as held.
        """
        if self._z_held():
            return False
        if self.backend == "filterpy":
            if self._st[1] <= self._m:
                return False
            return self._correct_filterpy(float(self._y[self._st[1] % self._y.size]))
        return _ekf_correct(*self._arrays)

    def _correct_filterpy(self, z: float) -> bool:
        kf = self.kf
        got = self._interp(float(kf.x[1, 0]))
        if got is None:
            return False
        v, dv = got
        g = float(kf.x[0, 0])
        row = [v, g * dv, 1.0][: self.n]
        jac = np.array([row])
        pred = g * v + (float(kf.x[2, 0]) if self.estimate_offset else 0.0)
        kf.update(np.array([[z]]), HJacobian=lambda _x: jac, Hx=lambda _x: np.array([[pred]]))
        self._innovation = float(kf.y[0, 0])
        lo, hi = self.delay_range
        kf.x[1, 0] = min(max(kf.x[1, 0], lo), hi)
        return True

    # -- per-sample convenience -------------------------------------------------------------
    def update(
        self, input_sample: float, measured_sample: float, fresh: bool = True
    ) -> tuple[float, float]:
        """Push one sample pair, predict, correct; return ``(gain, delay)``.

        The estimate refers to the measurement ``M`` samples back (:attr:`latency`).
        ``fresh=False`` marks a held measurement (a missed reply): it is never used as a
        measurement update (see :meth:`push`); the prediction still runs.
        """
        if not fresh or self._n_held:
            self.push(input_sample, measured_sample, fresh)
            self.predict()
            self.correct()
            return self.gain, self.delay
        if self.backend == "filterpy":
            self.push(input_sample, measured_sample)
            self.predict()
            self.correct()
            return float(self.kf.x[0, 0]), float(self.kf.x[1, 0])
        return _ekf_update(*self._arrays, float(input_sample), float(measured_sample))

    def run(self, inputs: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feed whole histories; return the gain and delay estimate after each sample."""
        u = np.asarray(inputs, dtype=float)
        y = np.asarray(measured, dtype=float)
        if u.shape != y.shape or u.ndim != 1:
            raise InputError(
                f"inputs and measured must be 1-D of equal length, got {u.shape}, {y.shape}"
            )
        gains = np.empty(len(u))
        delays = np.empty(len(u))
        update = self.update
        for i, (a, b) in enumerate(zip(u.tolist(), y.tolist(), strict=True)):
            gains[i], delays[i] = update(a, b)
        return gains, delays


class LinearDelayGainKF:
    """Linear KF on ``θ = [g, −g·τ]`` of the first-order model ``y ≈ θ1·u + θ2·u̇``.

    The regression uses a Savitzky–Golay smoother and differentiator (same window and order,
    :func:`scipy.signal.savgol_coeffs`, centred) on ``u`` and the same smoother on ``y`` so both
    carry the same group delay. Kept as the reference for the bias of the first-order
    approximation (module docstring): ``ĝ → g·cos ωτ``, ``τ̂ → tan(ωτ)/ω`` on a sinusoid.

    Parameters
    ----------
    fs : float
        Sampling rate in Hz.
    window : int
        Savitzky–Golay window (odd number of samples).
    polyorder : int
        Savitzky–Golay polynomial order.
    measurement_noise, gain_rate, delay_rate : float
        As in :class:`DelayGainEstimator` (``delay_rate`` applies to ``θ2``).
    """

    def __init__(
        self,
        fs: float,
        *,
        window: int = 31,
        polyorder: int = 3,
        measurement_noise: float = 5e-5,
        gain_rate: float = 0.01,
        delay_rate: float = 2e-3,
    ) -> None:
        if window % 2 == 0 or window <= polyorder:
            raise InputError(f"window: must be odd and > polyorder, got {window}")
        self.fs = float(fs)
        dt = 1.0 / self.fs
        self._s = signal.savgol_coeffs(window, polyorder, deriv=0, use="dot")
        self._d = signal.savgol_coeffs(window, polyorder, deriv=1, delta=dt, use="dot")
        self._u = np.zeros(window)
        self._y = np.zeros(window)
        self.kf = KalmanFilter(dim_x=2, dim_z=1)
        self.kf.x = np.array([[1.0], [0.0]])
        self.kf.P = np.diag([0.04, 0.02**2])
        self.kf.Q = np.diag([gain_rate**2 * dt, delay_rate**2 * dt])
        self.kf.R = np.array([[measurement_noise**2]])
        self._count = 0
        self._window = window

    def update(self, input_sample: float, measured_sample: float) -> tuple[float, float]:
        """One sample: smooth, predict, update; return ``(gain, delay)`` = ``(θ1, −θ2/θ1)``."""
        self._u[:-1] = self._u[1:]
        self._u[-1] = input_sample
        self._y[:-1] = self._y[1:]
        self._y[-1] = measured_sample
        self._count += 1
        self.kf.predict()
        if self._count >= self._window:
            us = float(self._s @ self._u)
            ud = float(self._d @ self._u)
            ys = float(self._s @ self._y)
            self.kf.update(np.array([[ys]]), H=np.array([[us, ud]]))
        g = float(self.kf.x[0, 0])
        return g, (-float(self.kf.x[1, 0]) / g if g != 0 else 0.0)

    def run(self, inputs: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feed whole histories; return gain and delay after each sample."""
        out = np.array(
            [
                self.update(a, b)
                for a, b in zip(
                    np.asarray(inputs).tolist(), np.asarray(measured).tolist(), strict=True
                )
            ]
        )
        return out[:, 0], out[:, 1]


# ---------------------------------------------------------------------------------------------
# calibration


@dataclass
class CalibrationInfo:
    """Diagnostics of :func:`calibrate`.

    Attributes
    ----------
    fs : float
        Sampling rate of the record (Hz).
    gain, delay : float
        Fitted gain and delay (s).
    time_constant : float or None
        Fitted servo lag (s) when requested.
    offset : float
        Fitted offset (m); written to the twin only when significant.
    residual_rms : float
        RMS of ``measured − model(input)`` (m).
    nrmse : float
        ``residual_rms / rms(measured)``.
    resolution : float
        Detected quantisation step of ``measured`` (0 when none).
    initial_delay : float
        Cross-correlation delay the fit started from (s).
    """

    fs: float
    gain: float
    delay: float
    time_constant: float | None
    offset: float
    residual_rms: float
    nrmse: float
    resolution: float
    initial_delay: float


def _check_signals(
    time: Sequence[float] | np.ndarray,
    inputs: Sequence[float] | np.ndarray,
    measured: Sequence[float] | np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float]:
    t = np.asarray(time, dtype=float)
    u = np.asarray(inputs, dtype=float)
    y = np.asarray(measured, dtype=float)
    if t.ndim != 1 or u.shape != t.shape or y.shape != t.shape:
        raise InputError(
            "time, input and measured must be 1-D of equal length, "
            f"got {t.shape}, {u.shape}, {y.shape}"
        )
    if len(t) < 16:
        raise InputError(f"record has {len(t)} samples, calibration needs at least 16")
    for name, a in (("time", t), ("input", u), ("measured", y)):
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise InputError(f"{name}: non-finite value at sample {bad[0]}")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise InputError(f"time: not strictly increasing at sample {int(np.argmax(dt <= 0)) + 1}")
    mean_dt = (t[-1] - t[0]) / (len(t) - 1)
    if np.max(np.abs(dt - mean_dt)) > 1e-3 * mean_dt:
        raise InputError("time: non-uniform sampling")
    if np.std(u) == 0:
        raise InputError("input: constant signal, nothing to calibrate against (no excitation)")
    return u, y, float(1.0 / mean_dt)


def _xcorr_delay(u: np.ndarray, y: np.ndarray, fs: float, lo: float, hi: float) -> float:
    """Integer-sample delay in [lo, hi] maximising the correlation of y with delayed u."""
    uc = u - u.mean()
    yc = y - y.mean()
    corr = signal.correlate(yc, uc, mode="full", method="fft")
    lags = signal.correlation_lags(len(yc), len(uc), mode="full")
    keep = (lags >= math.floor(lo * fs)) & (lags <= math.ceil(hi * fs))
    if not np.any(keep):
        return 0.0
    return float(lags[keep][np.argmax(corr[keep])] / fs)


def _detect_resolution(y: np.ndarray) -> float:
    """Quantisation step of ``y``: the smallest spacing of its values, if all lie on that grid."""
    vals = np.unique(y)
    if len(vals) < 3:
        return 0.0
    steps = np.diff(vals)
    q = float(np.min(steps))
    span = float(vals[-1] - vals[0])
    if q <= 0 or span / q > 1e7:
        return 0.0
    k = (vals - vals[0]) / q
    if np.max(np.abs(k - np.round(k))) > 1e-3:
        return 0.0
    # many values on a coarse grid → quantised; a continuous signal has unique values
    return float(f"{q:.6g}") if len(vals) < 0.9 * len(y) else 0.0


def _model_output(
    theta: np.ndarray, u: np.ndarray, fs: float, servo_lag: bool, fit_offset: bool
) -> np.ndarray:
    g, tau = theta[0], max(theta[1], 0.0)
    i = 2
    x = u
    if servo_lag:
        x = FirstOrderServo(max(theta[i], 1e-6), 1.0 / fs).simulate(u)
        i += 1
    out = g * fractional_delay(x, tau, fs)
    if fit_offset:
        out = out + theta[i]
    return out


@overload
def calibrate(
    time: Sequence[float] | np.ndarray,
    inputs: Sequence[float] | np.ndarray,
    measured: Sequence[float] | np.ndarray,
    *,
    servo_lag: bool = ...,
    fit_offset: bool = ...,
    delay_range: tuple[float, float] = ...,
    return_info: Literal[False] = ...,
) -> ModelSpec: ...
@overload
def calibrate(
    time: Sequence[float] | np.ndarray,
    inputs: Sequence[float] | np.ndarray,
    measured: Sequence[float] | np.ndarray,
    *,
    servo_lag: bool = ...,
    fit_offset: bool = ...,
    delay_range: tuple[float, float] = ...,
    return_info: Literal[True],
) -> tuple[ModelSpec, CalibrationInfo]: ...
def calibrate(
    time: Sequence[float] | np.ndarray,
    inputs: Sequence[float] | np.ndarray,
    measured: Sequence[float] | np.ndarray,
    *,
    servo_lag: bool = False,
    fit_offset: bool = True,
    delay_range: tuple[float, float] = (0.0, 0.2),
    return_info: bool = False,
) -> ModelSpec | tuple[ModelSpec, CalibrationInfo]:
    """Fit a twin model (delay + gain, optionally servo lag and offset) to a recorded test.

    Parameters
    ----------
    time : array_like
        Sample times (s), uniform.
    inputs : array_like
        Command (or target) displacement sent to the actuator (m).
    measured : array_like
        Measured displacement (m).
    servo_lag : bool
        Also fit a first-order servo lag (model ``servo_lag``). Delay and lag are only
        separable with excitation well above ``1/(2π·T)``; with narrow-band seismic response
        their sum is what the record determines.
    fit_offset : bool
        Fit a constant offset; it is written as an ``offset`` effect when larger than both
        1 µm and 5 times the residual RMS over √N.
    delay_range : (float, float)
        Search range of the delay (s) for the cross-correlation start.
    return_info : bool
        Also return :class:`CalibrationInfo`.

    Returns
    -------
    ModelSpec
        Actuator ``delay``/``gain`` (+ ``servo_lag`` ``time_constant``), optional ``offset``
        effect, ``[sensor]`` with the residual's standard deviation as displacement noise and
        the detected quantisation step. No ``[specimen]`` (a displacement record says nothing
        about it).
    """
    u, y, fs = _check_signals(time, inputs, measured)
    lo, hi = (float(v) for v in delay_range)
    if not (0.0 <= lo < hi):
        raise InputError(f"delay_range: need 0 ≤ lo < hi, got {delay_range!r}")
    tau0 = min(max(_xcorr_delay(u, y, fs, lo, hi), lo), hi)
    delayed = fractional_delay(u, tau0, fs)
    g0 = float(np.dot(delayed, y) / np.dot(delayed, delayed)) if np.any(delayed) else 1.0
    theta0 = [g0, tau0]
    lower = [-np.inf, lo]
    upper = [np.inf, hi]
    if servo_lag:
        theta0[1] = tau0 / 2
        theta0.append(max(tau0 / 2, 1.0 / fs))
        lower.append(1e-5)
        upper.append(1.0)
    if fit_offset:
        theta0.append(float(np.mean(y - g0 * delayed)))
        lower.append(-np.inf)
        upper.append(np.inf)
    scale = float(np.std(y)) or 1.0

    def residual(theta: np.ndarray) -> np.ndarray:
        return (_model_output(theta, u, fs, servo_lag, fit_offset) - y) / scale

    fit = optimize.least_squares(
        residual,
        np.clip(theta0, lower, upper),
        bounds=(lower, upper),
        x_scale=[1.0, 1e-3] + ([1e-3] if servo_lag else []) + ([scale] if fit_offset else []),
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    theta = fit.x
    res = _model_output(theta, u, fs, servo_lag, fit_offset) - y
    rms = float(np.sqrt(np.mean(res**2)))
    gain, delay = float(theta[0]), float(theta[1])
    i = 2
    time_constant = None
    if servo_lag:
        time_constant = float(theta[i])
        i += 1
    offset = float(theta[i]) if fit_offset else 0.0
    resolution = _detect_resolution(y)
    # the twin adds noise then quantises: leave the quantisation's q²/12 out of the noise
    noise = float(math.sqrt(max(float(np.var(res)) - resolution**2 / 12.0, 0.0)))
    effects: list[EffectSpec] = []
    if fit_offset and abs(offset) > max(1e-6, 5 * rms / math.sqrt(len(y))):
        effects.append(EffectSpec(Offset.kind, {"offset": offset}))
    actuator = ActuatorSpec(
        delay=delay,
        gain=gain,
        model="servo_lag" if servo_lag else "delay_gain",
        params={"time_constant": time_constant} if servo_lag else {},
        effects=effects,
    )
    sensor = Sensor(displacement_noise=noise, displacement_resolution=resolution)
    spec = ModelSpec(actuator=actuator, specimen=None, sensor=sensor, source="calibration")
    info = CalibrationInfo(
        fs=fs,
        gain=gain,
        delay=delay,
        time_constant=time_constant,
        offset=offset,
        residual_rms=rms,
        nrmse=rms / float(np.sqrt(np.mean(y**2))) if np.any(y) else math.inf,
        resolution=resolution,
        initial_delay=tau0,
    )
    log.info("calibrated: %s", info)
    if return_info:
        return spec, info
    return spec

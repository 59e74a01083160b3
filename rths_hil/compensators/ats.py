"""Adaptive time series (ATS) compensator of Chae, Kazemibidokhti & Ricles (2013).

Chae, Kazemibidokhti & Ricles, "Adaptive time series compensator for delay compensation of
servo-hydraulic actuator systems for real-time hybrid simulation", *Earthquake Engineering and
Structural Dynamics* 42(11), 1697–1715, 2013. The actuator is described by its inverse: the
command that produced the measured displacement ``x_m`` is, to second order in the frequency,

    x_c(t) = a0·x_m(t) + a1·ẋ_m(t) + a2·ẍ_m(t)                                  (ATS model)

(``a0`` undoes an amplitude error, ``a1`` ≈ the delay, ``a2`` ≈ a1²/2 for a pure delay). The
compensator sends, for the target ``x_t``,

    x_c[k] = a0·x_t[k] + a1·ẋ_t[k] + a2·ẍ_t[k]                                  (ATS law)

with the target's velocity and acceleration from second-order backward differences. The
coefficients ``A = [a0, a1, a2]ᵀ`` are identified online by least squares over a moving window of
the last ``q`` (command, measured) samples, ``A = (X_mᵀ X_m)⁻¹ X_mᵀ x_c`` with the rows of
``X_m`` = ``[x_m, ẋ_m, ẍ_m]``; each new estimate is clipped to a maximum rate of change and to
bounds, and adaptation only runs while the measured motion exceeds a threshold (below it the
fit is noise). Defaults are the authors' published implementation settings: a 1 s window, one
window sample and one update every 16 steps at 1024 Hz (``ats_interval`` = 1/64 s), bounds
``a0 ∈ [0.7, 1.3]``, ``a1 ∈ [0, 0.08] s``, ``a2 ∈ [0, 0.0032] s²``, maximum rates ``[2, 0.05,
0.001]`` per second, a threshold of 0.01 in (0.254 mm), and a 6th-order Butterworth low-pass
at 20 Hz applied alike to the measured displacement (before its finite-difference velocity and
acceleration) and to the command: the same linear filter on both sides leaves the coefficients
unbiased and removes the sensor noise. Initial values: ``a0 = amplitude``, ``a1 = delay``,
``a2 = delay²/2`` (the authors' rule).

What is verified, and against what. The paper itself was not available here, so no equation
numbers of it are cited. The authors' parameter file for their Simulink implementation ("Adaptive
Time Series (ATS) Compensator by Yunbyeong Chae, Old Dominion University", redistributed in
public repositories, e.g. with the openHySim package's ``rthstools/simulink`` examples) confirms
the settings above: a 1 s moving window, a skipping number of 16 samples between updates, a
0.01 in threshold, the bounds ``a0 ∈ [0.7, 1.3]``, ``a1 ∈ [0, 0.08]``, ``a2 ∈ [0, 0.0032]``
(its comment refers them to Table 1 of the paper), the maximum rates of change ``[2, 0.05,
0.001]``, the 6th-order 20 Hz Butterworth, and the initial values ``a0 ≈ 1``, ``a1`` ≈ the
expected delay, ``a2 = a1²/2``; that file also names ``a0`` the amplitude factor and ``a1`` the
delay; it runs at 1024 or 2048 Hz with the same 16 samples, so the default ``ats_interval`` of
1/64 s is its figure at 1024 Hz, kept in time at other rates. Not verified against the paper's
text: the form of the law ``x_c = a0·x_t + a1·ẋ_t + a2·ẍ_t``, its identification from
(command, measured) pairs by least squares over the window, the filtering of both sides and the
finite differences — they are this implementation's reading of the method.

Per step the work is O(1): the filters and the target differences every step; every
``ats_interval`` a new row enters the window and the 3×3 normal equations are rebuilt over the
window's ``q`` rows (64 by default, a fixed cost amortised over the interval) and solved in
closed form after column scaling; an ill-conditioned window (a motion with one frequency gives
``x`` and ``ẍ`` collinear) keeps the previous coefficients. The numerical kernel is a plain
``numba.njit`` loop (:mod:`._ats_kernel`, loaded with the first compensator built).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from ..errors import InputError
from ..keys import Key, seconds
from .base import Compensator

__all__ = ["ATSCompensator"]

# layout of the state vector (float64): scalars, coefficients, bounds, rates, then the filters
_M0, _M1, _M2, _C0, _C1, _COUNT, _HEAD, _ROWS, _PRIMED = range(9)
_A, _LO, _HI, _DMAX = 9, 12, 15, 18
_DT, _SKIP, _THR2 = 21, 22, 23
_Z = 24  # then 2 values per section for the command filter, 2 per section for the measured


#: The method's own keys of the compensation section, each with the constructor argument it
#: gives: :attr:`ATSCompensator.KEYS`, :attr:`ATSCompensator.ARGUMENTS` and the constructor's
#: defaults all come from this one declaration.
_KEYS: dict[str, tuple[str, Key]] = {
    "ats_window": (
        "window",
        seconds(1.0, doc="ats: length of the moving least-squares window", positive=True),
    ),
    "ats_interval": (
        "interval",
        seconds(
            0.015625,
            doc="ats: time between window samples and coefficient updates (16 steps at 1024 Hz)",
            positive=True,
        ),
    ),
    "ats_cutoff": (
        "cutoff",
        Key(
            "float",
            20.0,
            unit="Hz",
            doc="ats: cut-off of the 6th-order Butterworth on command and measured",
            lo=0,
            lo_open=True,
        ),
    ),
    "ats_threshold": (
        "threshold",
        Key(
            "float",
            0.000254,
            unit="m",
            doc="ats: coefficients adapt only while the window's RMS measured displacement "
            "exceeds this",
            lo=0,
        ),
    ),
    "ats_min": (
        "lower",
        Key("array", [0.7, 0.0, 0.0], doc="ats: lower bounds of a0 (-), a1 (s), a2 (s²)"),
    ),
    "ats_max": (
        "upper",
        Key("array", [1.3, 0.08, 0.0032], doc="ats: upper bounds of a0 (-), a1 (s), a2 (s²)"),
    ),
    "ats_rate": (
        "rate",
        Key(
            "array",
            [2.0, 0.05, 0.001],
            doc="ats: maximum rate of change of a0 (1/s), a1 (s/s), a2 (s²/s)",
        ),
    ),
}
#: The constructor's defaults: each key's default (an array's as a tuple), by argument.
_DEFAULTS: dict[str, Any] = {
    argument: tuple(key.default) if key.kind == "array" else key.default
    for argument, key in _KEYS.values()
}


def _triple(values: Sequence[float], name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InputError(f"compensation.{name}: expected 3 finite numbers (a0, a1, a2)")
    return arr


class ATSCompensator(Compensator):
    """The adaptive time series compensator (see the module docstring).

    Parameters
    ----------
    fs : float
        Loop rate (Hz).
    delay : float
        Initial ``a1`` (s); ``a2`` starts at ``delay²/2``.
    amplitude : float
        Initial ``a0``.
    window, interval : float
        Moving-window length and the time between window rows / updates (s).
    cutoff : float
        Corner of the 6th-order Butterworth on command and measured (Hz), below fs/2.
    threshold : float
        Adapt only while the window's RMS filtered measured displacement exceeds this (m).
    lower, upper, rate : sequence of 3 float
        Bounds of ``a0, a1, a2`` and their maximum rates of change (per s).

    Attributes
    ----------
    a : ndarray
        The current ``[a0, a1, a2]``; ``alpha = 1 + a1·fs``.
    """

    #: the method's own keys of the compensation section (:data:`_KEYS`)
    KEYS: ClassVar[Mapping[str, Key]] = {name: key for name, (_, key) in _KEYS.items()}
    #: the ``delay``, ``amplitude`` and ``ats_*`` keys of the compensation section
    ARGUMENTS: ClassVar[Mapping[str, str]] = {
        "delay": "delay",
        "amplitude": "amplitude",
        **{argument: name for name, (argument, _) in _KEYS.items()},
    }

    def __init__(
        self,
        fs: float,
        delay: float,
        amplitude: float = 1.0,
        *,
        window: float = _DEFAULTS["window"],
        interval: float = _DEFAULTS["interval"],
        cutoff: float = _DEFAULTS["cutoff"],
        threshold: float = _DEFAULTS["threshold"],
        lower: Sequence[float] = _DEFAULTS["lower"],
        upper: Sequence[float] = _DEFAULTS["upper"],
        rate: Sequence[float] = _DEFAULTS["rate"],
    ) -> None:
        fs = float(fs)
        if not cutoff < fs / 2:
            raise InputError(
                f"compensation.ats_cutoff: {cutoff:g} Hz is not below fs/2 = {fs / 2:g} Hz"
            )
        skip = max(1, round(interval * fs))
        q = round(window / (skip / fs))
        if q < 8:
            raise InputError(
                f"compensation.ats_window: {window:g} s holds {q} rows of {skip / fs:g} s; "
                "need at least 8"
            )
        self.fs = fs
        self.dt = 1.0 / fs
        lo = _triple(lower, "ats_min")
        hi = _triple(upper, "ats_max")
        rate_arr = _triple(rate, "ats_rate")
        if np.any(lo > hi) or np.any(rate_arr <= 0):
            raise InputError("compensation.ats_min must not exceed ats_max; ats_rate must be > 0")
        from scipy.signal import butter

        from ._ats_kernel import observe  # numba: compiled when the first ATS is built

        self._sos = np.ascontiguousarray(butter(6, cutoff, fs=fs, output="sos"))
        self._st = np.zeros(_Z + 4 * self._sos.shape[0])
        self._params = np.concatenate(
            [lo, hi, rate_arr * (skip / fs), [self.dt, float(skip), float(threshold) ** 2]]
        )
        self._ring = np.zeros((q, 4))
        a0 = np.array([amplitude, delay, 0.5 * delay * delay], dtype=float)
        self.a0_initial = np.clip(a0, lo, hi)
        self.enabled = True
        self._x1 = self._x2 = self._x3 = 0.0
        self._c1 = 0.5 * fs
        self._c2 = fs * fs
        self._observe = observe
        self.updates = 0
        # compile now, not at a deadline
        self.reset(0.0)
        observe(self._st.copy(), self._sos, self._ring.copy(), 0.0, 0.0)

    @property
    def a(self) -> np.ndarray:
        """The current ``[a0, a1, a2]`` (a view into the state: writable)."""
        return self._st[_A : _A + 3]

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds of ``a0, a1, a2``."""
        return self._st[_LO : _LO + 3]

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds of ``a0, a1, a2``."""
        return self._st[_HI : _HI + 3]

    def reset(self, target: float = 0.0) -> None:
        """Back to the initial coefficients; the target and the filters at rest at ``target``."""
        x = float(target)
        self._x1 = self._x2 = self._x3 = x
        self._st[:] = 0.0
        self._st[_LO:_Z] = self._params
        self._st[_A : _A + 3] = self.a0_initial
        self._ring[:] = 0.0
        self._a0, self._a1, self._a2 = self.a0_initial.tolist()
        self.alpha = 1.0 + self._a1 * self.fs
        self.updates = 0

    def step(self, target: float) -> float:
        """``a0·x + a1·ẋ + a2·ẍ`` with second-order backward differences of the target."""
        x1, x2 = self._x1, self._x2
        v = (3.0 * target - 4.0 * x1 + x2) * self._c1
        acc = (2.0 * target - 5.0 * x1 + 4.0 * x2 - self._x3) * self._c2
        self._x3, self._x2, self._x1 = x2, x1, target
        return self._a0 * target + self._a1 * v + self._a2 * acc

    def observe(self, target: float, command: float, measured: float) -> None:
        """Feed the (command, measured) pair of the step to the moving-window fit."""
        if self._observe(self._st, self._sos, self._ring, command, measured):
            self.updates += 1
            self._a0, self._a1, self._a2 = self._st[_A : _A + 3].tolist()
            self.alpha = 1.0 + self._a1 * self.fs

"""The FEI paper's actuator block model (Fig. 4.1): a fractional transport delay followed by a gain.

The delay is not rounded to whole samples. A delay of ``D = delay·fs`` samples is split into an
integer part ``n0`` and a fractional part ``D - n0`` in [1, 2) (or [0, 1) for delays below one
sample), and the fractional part is realised by a causal third-order Lagrange interpolator
(Laakso et al., "Splitting the unit delay", IEEE SP Magazine 1996, Eq. 42):

    h[j] = prod_{k != j} (D' - k) / (j - k),   j = 0 … 3.

:func:`lagrange_weights` is that formula multiplied out; it is the one implementation of the
taps in the package (the effects, the delay estimator and the diagnosis call it, or its numba
compilation :data:`lagrange_weights_jit` inside their kernels).

For D' in [1, 2) the interpolator is centred, and its error on a sinusoid of normalised frequency
ω = 2π f / fs is O(ω⁴): 1e-8 relative at 1 Hz and 1024 Hz. The streaming
:class:`FractionalDelay` and the offline :func:`fractional_delay` compute the same FIR and agree
to round-off.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from .base import ActuatorModel

ORDER = 3


def lagrange_weights(f: Any) -> tuple[Any, Any, Any, Any]:
    """Taps ``h[0..3]`` of the third-order Lagrange interpolator at fractional delay ``f``.

    ``h[j] = prod_{k != j} (f - k) / (j - k)`` (Laakso et al. 1996, Eq. 42), multiplied out.
    ``f`` is a float or an array (the taps are then arrays of its shape); the same arithmetic
    runs compiled as :data:`lagrange_weights_jit`.
    """
    f1, f2, f3 = f - 1.0, f - 2.0, f - 3.0
    f12 = f1 * f2
    f03 = f * f3
    return (-f12 * f3 / 6.0, f03 * f2 / 2.0, -f03 * f1 / 2.0, f * f12 / 6.0)


def lagrange_slopes(f: Any) -> tuple[Any, Any, Any, Any]:
    """Derivatives ``dh[j]/df`` of the taps of :func:`lagrange_weights`."""
    f1, f2, f3 = f - 1.0, f - 2.0, f - 3.0
    return (
        -(f2 * f3 + f1 * f3 + f1 * f2) / 6.0,
        (f2 * f3 + f * f3 + f * f2) / 2.0,
        -(f1 * f3 + f * f3 + f * f1) / 2.0,
        (f1 * f2 + f * f2 + f * f1) / 6.0,
    )


#: :func:`lagrange_weights` compiled with numba, inlined into the njit kernels calling it.
lagrange_weights_jit = numba.njit(cache=True, nogil=True, inline="always")(lagrange_weights)
#: :func:`lagrange_slopes` compiled with numba, inlined into the njit kernels calling it.
lagrange_slopes_jit = numba.njit(cache=True, nogil=True, inline="always")(lagrange_slopes)


def lagrange_split(delay_samples: float) -> tuple[int, float]:
    """``(n0, f)``: whole samples of shift ``n0 = max(floor(D) - 1, 0)`` and ``f = D - n0``."""
    n0 = max(math.floor(delay_samples) - 1, 0)
    return n0, delay_samples - n0


def lagrange_taps(delay_samples: float) -> tuple[int, np.ndarray]:
    """Split a delay (in samples, ≥ 0) into an integer shift and 4 Lagrange FIR taps.

    Parameters
    ----------
    delay_samples : float
        Delay in samples (``delay_s * fs``), non-negative.

    Returns
    -------
    n0 : int
        Whole samples of pure shift applied before the interpolator.
    taps : ndarray, shape (4,)
        FIR taps ``h[j]`` applied to ``x[k - n0 - j]``.
    """
    if not np.isfinite(delay_samples) or delay_samples < 0:
        raise ValueError(
            f"delay must be a finite non-negative number of samples, got {delay_samples}"
        )
    n0, frac = lagrange_split(float(delay_samples))
    return n0, np.array(lagrange_weights(frac))


def fractional_delay(x: np.ndarray, delay_s: float, fs: float) -> np.ndarray:
    """Delay ``x`` by ``delay_s`` seconds (not rounded to samples), from rest (zeros before).

    Parameters
    ----------
    x : array_like
        Signal sampled at ``fs``.
    delay_s : float
        Delay in seconds, ≥ 0.
    fs : float
        Sampling rate in Hz.

    Notes
    -----
    The shift is a slice and the 4 taps are 4 vector operations, summed in the order of
    :meth:`FractionalDelay.step`.
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    n0, taps = lagrange_taps(delay_s * fs)
    out = np.zeros(n)
    for j, h in enumerate(taps.tolist()):
        s = n0 + j
        if s < n and h != 0.0:
            out[s:] += h * x[: n - s]
    return out


class FractionalDelay:
    """Streaming fractional delay line: one :meth:`step` per sample, no allocation per step."""

    def __init__(self, delay_s: float, fs: float) -> None:
        self.fs = float(fs)
        self.set_delay(delay_s)

    def set_delay(self, delay_s: float) -> None:
        """Change the delay (s). The history is kept, so a change takes effect immediately."""
        self.delay_s = float(delay_s)
        n0, taps = lagrange_taps(self.delay_s * self.fs)
        length = n0 + ORDER + 1
        old = getattr(self, "_buf", None)
        if old is None or len(old) < length:
            hist = self.history() if old is not None else []
            self._buf = [0.0] * max(length, 8)
            self._pos = 0
            for v in reversed(hist):
                self._push(v)
        self._n0 = n0
        self._taps = [float(t) for t in taps]

    def history(self) -> list[float]:
        """Past inputs, newest first."""
        n = len(self._buf)
        return [self._buf[(self._pos - 1 - i) % n] for i in range(n)]

    def reset(self) -> None:
        """Clear the history (all zeros)."""
        for i in range(len(self._buf)):
            self._buf[i] = 0.0
        self._pos = 0

    def _push(self, value: float) -> None:
        self._buf[self._pos] = value
        self._pos = (self._pos + 1) % len(self._buf)

    def step(self, value: float) -> float:
        """Push one input sample and return the delayed output for this step."""
        buf = self._buf
        n = len(buf)
        buf[self._pos] = value
        newest = self._pos
        self._pos = (newest + 1) % n
        base = newest - self._n0
        t0, t1, t2, t3 = self._taps
        return (
            t0 * buf[base % n]
            + t1 * buf[(base - 1) % n]
            + t2 * buf[(base - 2) % n]
            + t3 * buf[(base - 3) % n]
        )


class DelayGain(ActuatorModel):
    """The FEI paper's Fig. 4.1: measured = gain · command delayed by ``delay`` s (fractional).

    Parameters
    ----------
    delay : float
        Transport delay in seconds (≥ 0).
    gain : float
        Amplitude gain (1 = perfect amplitude).
    dt : float
        Step in seconds.
    """

    def __init__(self, delay: float, gain: float, dt: float) -> None:
        self.delay = float(delay)
        self.gain = float(gain)
        self.dt = float(dt)
        self._line = FractionalDelay(self.delay, 1.0 / self.dt)

    def reset(self) -> None:
        """Return to rest (zero state, empty delay lines)."""
        self._line.reset()

    def step(self, command: float) -> float:
        """Advance one step: the achieved displacement (m) for ``command`` (m)."""
        return self.gain * self._line.step(command)

    def simulate(self, command: np.ndarray) -> np.ndarray:
        """The achieved displacement (m) for a whole command history (m), from rest."""
        self.reset()
        return self.gain * fractional_delay(command, self.delay, 1.0 / self.dt)

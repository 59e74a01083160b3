"""The plant step's motion and model: a chirp, and the delayed first-order fit to it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["CHIRP_TIME", "PlantFit", "identify_plant", "plant_path"]

#: Length of the identification chirp (s).
CHIRP_TIME = 4.0


@dataclass
class PlantFit:
    """The delayed first-order model ``g·e^(−sτ)/(T s + 1)`` fitted to a motion.

    Attributes
    ----------
    delay : float
        Transport delay τ (s), the link's latency included.
    lag : float
        First-order time constant T (s).
    gain : float
        Static gain g.
    offset : float
        Measured position at rest minus ``g`` × the commanded one (m).
    fit : float
        Share of the measured motion's variance the model explains (1 = all).
    model : ndarray
        The model's response to the command (m), for the plot.
    """

    delay: float
    lag: float
    gain: float
    offset: float
    fit: float
    model: np.ndarray


def plant_path(
    x0: float, amplitude: float, velocity: float, fs: float, duration: float = CHIRP_TIME
) -> np.ndarray:
    """The identification motion: a logarithmic chirp about ``x0``, 0.2 s of hold either side.

    The frequency rises from 0.5 Hz to ``min(20 Hz, fs/16)`` over ``duration``; the amplitude
    at frequency ``f`` is ``min(amplitude/2, 0.8·velocity/(2πf))`` with cosine tapers over the
    first and last 5 %, and the whole path is scaled so that no step moves faster than
    ``velocity``.
    """
    from scipy.signal import chirp

    f0, f1 = 0.5, min(20.0, fs / 16.0)
    n = max(16, round(duration * fs))
    t = np.arange(n) / fs
    f = f0 * (f1 / f0) ** (t / duration)
    env = np.minimum(0.5 * amplitude, 0.8 * velocity / (2 * np.pi * f))
    taper = np.ones(n)
    m = max(1, n // 20)
    taper[:m] = 0.5 - 0.5 * np.cos(np.pi * np.arange(m) / m)
    taper[-m:] = taper[:m][::-1]
    x = env * taper * chirp(t, f0, duration, f1, method="logarithmic", phi=-90.0)
    peak_v = float(np.max(np.abs(np.diff(x)))) * fs if n > 1 else 0.0
    if peak_v > velocity:
        x *= velocity / peak_v
    hold = np.zeros(round(0.2 * fs))
    return x0 + np.concatenate([hold, x, hold])


def _first_order(u: np.ndarray, lag: float, fs: float) -> np.ndarray:
    """``1/(T s + 1)`` by the bilinear transform (as the ``model`` compensator's C)."""
    from scipy.signal import lfilter

    if lag < 0.05 / fs:
        return u
    c = 2.0 * lag * fs
    return lfilter([1.0 / (1.0 + c)] * 2, [1.0, (1.0 - c) / (1.0 + c)], u)


def identify_plant(
    command: np.ndarray,
    measured: np.ndarray,
    fs: float,
    max_time: float = 0.2,
    valid: np.ndarray | None = None,
) -> PlantFit:
    """Fit ``y = offset + g·(1/(T s + 1))·e^(−sτ)·u`` to a command/measured pair (least squares).

    ``g`` and ``offset`` enter linearly and are solved for each ``(τ, T)``; ``(τ, T)`` come
    from a grid of 5 ms over ``[0, max_time]²`` refined by
    :func:`scipy.optimize.least_squares` within ``[0, 2·max_time]``. The delay is fractional
    (linear interpolation of the command), the lag discretised with the bilinear transform.
    NaN samples (missed replies) and those ``valid`` marks False are left out.

    Parameters
    ----------
    command, measured : ndarray
        The commands sent and the positions measured, one per step (m).
    fs : float
        Step rate (Hz).
    max_time : float
        Upper end of the grid for τ and T (s).
    valid : ndarray of bool, optional
        The samples to fit (e.g. not those after a stall of the commanding computer, when
        the controller saw other command times than the model assumes).

    Returns
    -------
    PlantFit
    """
    from scipy.optimize import least_squares

    u = np.asarray(command, dtype=float)
    y = np.asarray(measured, dtype=float)
    ok = np.isfinite(y) & np.isfinite(u)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if u.size < 16 or ok.sum() < 16:
        raise ValueError("too few samples to identify the plant")
    t = np.arange(u.size) / fs
    du = u - u[0]
    yo = y[ok]
    ones = np.ones(yo.size)

    def response(p: np.ndarray) -> np.ndarray:
        tau, lag = float(p[0]), float(p[1])
        return _first_order(np.interp(t - tau, t, du, left=0.0), lag, fs)

    def solve(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = response(p)[ok]
        a = np.column_stack([s, ones])
        coef, *_ = np.linalg.lstsq(a, yo, rcond=None)
        return a @ coef - yo, coef

    grid = np.arange(0.0, max_time + 1e-12, 5e-3)
    best, p0 = math.inf, np.zeros(2)
    for tau in grid:
        for lag in grid:
            r, _ = solve(np.array([tau, lag]))
            cost = float(r @ r)
            if cost < best:
                best, p0 = cost, np.array([tau, lag])
    hi = 2.0 * max_time
    fit = least_squares(
        lambda p: solve(p)[0], p0, bounds=([0.0, 0.0], [hi, hi]), x_scale=[1e-3, 1e-3],
        diff_step=[1e-4, 1e-4],
    )  # fmt: skip
    r, (g, off) = solve(fit.x)
    var = float(np.var(yo))
    explained = 1.0 - float(r @ r) / (yo.size * var) if var > 0 else math.nan
    return PlantFit(
        delay=float(fit.x[0]),
        lag=float(fit.x[1]),
        gain=float(g),
        offset=float(off),
        fit=explained,
        model=off + g * response(fit.x),
    )

"""Tracking metrics of the RTHS benchmark (Silva et al. 2020) and the tracking indicator.

All functions take the target (reference, calculated) displacement and the measured displacement
as equal-length arrays in m. Sign conventions match the FEI (:mod:`rths_hil.fei`): a measured
signal that *lags* the target gives a positive J1 and a positive TI.

* :func:`j1_delay` — J1, time delay by cross-correlation (s).
* :func:`j2_nrms` — J2, normalised RMS tracking error (%).
* :func:`j3_peak` — J3, peak tracking error (%).
* :func:`tracking_indicator` — TI of Mercan & Ricles (2007), cumulative-area hysteresis measure.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import correlate, correlation_lags

from .errors import InputError


def _pair(target: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(target, dtype=float)
    y = np.asarray(measured, dtype=float)
    if x.ndim != 1 or x.shape != y.shape or x.size < 2:
        raise InputError(
            f"target and measured must be 1-D, equal length ≥ 2; got {x.shape} and {y.shape}"
        )
    return x, y


def j1_delay(target: np.ndarray, measured: np.ndarray, fs: float, max_lag_s: float = 0.2) -> float:
    """J1: delay of measured behind target by cross-correlation (Silva et al. 2020, J1).

    The lag ``τ`` maximising ``R(τ) = Σ_t x(t) y(t + τ)`` over ``|τ| ≤ max_lag_s`` (after mean
    removal, each lag normalised by the energies of the overlapping segments), refined to a
    fraction of a sample by a parabola through the peak and its two neighbours. Positive when
    measured lags target.

    Parameters
    ----------
    target, measured : array_like
        Displacements (m).
    fs : float
        Sampling rate (Hz).
    max_lag_s : float
        Largest lag searched, each way (s).

    Returns
    -------
    float
        Delay in s.
    """
    x, y = _pair(target, measured)
    if max_lag_s <= 0:
        raise InputError(f"max_lag_s must be positive, got {max_lag_s}")
    x = x - x.mean()
    y = y - y.mean()
    r = correlate(y, x, mode="full", method="fft")
    lags = correlation_lags(y.size, x.size, mode="full")
    max_lag = min(int(np.floor(max_lag_s * fs + 1e-9)), x.size - 1)
    sel = np.abs(lags) <= max_lag
    r, lags = r[sel], lags[sel]
    # Normalise each lag by the energies of the two overlapping segments (the correlation
    # coefficient of the overlap): a plain or length-normalised sum leans towards the lag that
    # keeps the strongest part of a transient record in the overlap.
    cx = np.concatenate([[0.0], np.cumsum(x * x)])
    cy = np.concatenate([[0.0], np.cumsum(y * y)])
    n = x.size
    ex = np.where(lags >= 0, cx[n - np.maximum(lags, 0)], cx[n] - cx[np.maximum(-lags, 0)])
    ey = np.where(lags >= 0, cy[n] - cy[np.maximum(lags, 0)], cy[n - np.maximum(-lags, 0)])
    with np.errstate(invalid="ignore", divide="ignore"):
        r = r / np.sqrt(ex * ey)
    r = np.nan_to_num(r, nan=-np.inf)
    i = int(np.argmax(r))
    frac = 0.0
    if 0 < i < r.size - 1:
        denom = r[i - 1] - 2 * r[i] + r[i + 1]
        if denom < 0:
            frac = 0.5 * (r[i - 1] - r[i + 1]) / denom
    return float((lags[i] + frac) / fs)


def j2_nrms(target: np.ndarray, measured: np.ndarray) -> float:
    """J2: normalised RMS tracking error, ``100 · RMS(y − x) / RMS(x)`` in % (Silva et al. 2020)."""
    x, y = _pair(target, measured)
    den = np.sqrt(np.mean(x * x))
    if den == 0:
        return float("nan")
    return float(100.0 * np.sqrt(np.mean((y - x) ** 2)) / den)


def j3_peak(target: np.ndarray, measured: np.ndarray) -> float:
    """J3: peak tracking error, ``100 · max|y − x| / max|x|`` in % (Silva et al. 2020)."""
    x, y = _pair(target, measured)
    den = np.max(np.abs(x))
    if den == 0:
        return float("nan")
    return float(100.0 * np.max(np.abs(y - x)) / den)


def tracking_indicator(
    target: np.ndarray, measured: np.ndarray, cumulative: bool = False
) -> float | np.ndarray:
    """Tracking indicator TI (Mercan & Ricles 2007), in m².

    With trapezoidal cumulative areas in the measured-vs-target plane,
    ``A = ∫ x d(y)`` and ``TA = ∫ y d(x)`` (x = target, y = measured), ``TI = ½ (A − TA)``:
    the signed area swept by the synchronised subspace plot. For a sinusoid of amplitude ``a``
    and angular frequency ``ω`` measured with a delay ``τ``, TI grows by ``π a² sin(ωτ)`` per
    cycle: **positive when measured lags target** (energy added to the test), negative when it
    leads, zero for perfect tracking or a pure gain error.

    Parameters
    ----------
    target, measured : array_like
        Displacements (m).
    cumulative : bool
        Return the running TI (one value per sample, starting at 0) instead of the final value.
    """
    x, y = _pair(target, measured)
    dA = 0.5 * (x[1:] + x[:-1]) * np.diff(y)
    dTA = 0.5 * (y[1:] + y[:-1]) * np.diff(x)
    ti = 0.5 * np.concatenate([[0.0], np.cumsum(dA - dTA)])
    return ti if cumulative else float(ti[-1])

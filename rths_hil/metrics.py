"""Tracking metrics of the RTHS benchmark (Silva et al. 2020) and the tracking indicator.

All functions take the target (reference, calculated) displacement and the measured displacement
as equal-length arrays in m. Sign conventions match the FEI (:mod:`rths_hil.fei`): a measured
signal that *lags* the target gives a positive J1 and a positive TI.

* :func:`j1_delay` — J1, time delay by cross-correlation (s, signed, sub-sample).
* :func:`j2_nrms` — J2, normalised RMS tracking error (%), Silva et al. Eq. 13.
* :func:`j3_peak` — J3, peak tracking error (%), Eq. 14.
* :func:`nrms_error`, :func:`peak_error` — the normalised RMS and peak errors of a response
  against a reference response (%), from which J4–J9 (Eqs. 15–20) are built.
* :func:`criteria` — J1–J9 with the paper's numbering and definitions (Eqs. 12–20) and this
  project's J1.
* :func:`benchmark_criteria` — J1–J9 exactly as the benchmark's distributed evaluation script
  computes them (``F4_evaluation.m``: its numbering, its rounding, std instead of RMS).
* :func:`tracking_indicator` — TI of Mercan & Ricles (2007), cumulative-area hysteresis measure.

Paper and distributed code differ (``docs/studies.md`` has the table): the code's J1 is the
integer lag 0…49 samples of the largest Pearson correlation, in ms rounded to 0.1 ms (no lead,
at most 49 samples); its J2, J4, J6, J7 use the standard deviation (mean removed) where the
paper's Eqs. 13, 15–17 use the RMS; and it numbers the floor-1 peak error J5 and the floor-2/3
RMS errors J6/J7 where the paper has J7 and J5/J6.

Reference: C. E. Silva, D. Gomez, A. Maghareh, S. J. Dyke, B. F. Spencer Jr., "Benchmark
control problem for real-time hybrid simulation", Mech. Syst. Signal Process. 135 (2020)
106381; its code package (``RTHS code RT V23``), ``F4_evaluation.m`` lines 11–39.
"""

from __future__ import annotations

import math

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
    return overlap_peak_lag(r, lags, ex, ey, fs)


def overlap_peak_lag(
    r: np.ndarray, lags: np.ndarray, ex: np.ndarray, ey: np.ndarray, fs: float
) -> float:
    """Lag (s) of the largest overlap correlation ``r / √(ex·ey)``, refined to a fraction of a
    sample by the parabola through the peak and its two neighbours.

    ``r`` are the cross-correlation sums at ``lags`` (samples) and ``ex``, ``ey`` the energies
    of the two overlapping segments at each lag (J1 of :func:`j1_delay` and of the chunked
    summary in :mod:`rths_hil.report`).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        r = r / np.sqrt(ex * ey)
    r = np.nan_to_num(r, nan=-np.inf)
    i = int(np.argmax(r))
    frac = 0.0
    if 0 < i < r.size - 1:
        denom = r[i - 1] - 2 * r[i] + r[i + 1]  # parabola y = a·u² + b·u + c, vertex −b/2a
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


# ----------------------------------------------------------------------------------------------
# J4–J9: global errors against the reference structure


def nrms_error(response: np.ndarray, reference: np.ndarray) -> float:
    """Normalised RMS error ``100 · RMS(r − x_r) / RMS(x_r)`` in % (Silva et al. Eqs. 13, 15–17).

    Parameters
    ----------
    response : array_like
        Response of the hybrid test (measured or numerical displacement, m).
    reference : array_like
        The same degree of freedom of the reference structure (m).
    """
    x, y = _pair(reference, response)
    return j2_nrms(x, y)


def peak_error(response: np.ndarray, reference: np.ndarray) -> float:
    """Peak error ``100 · max|r − x_r| / max|x_r|`` in % (Silva et al. Eqs. 14, 18–20)."""
    x, y = _pair(reference, response)
    return j3_peak(x, y)


def _floors(a: np.ndarray | None, n: int, what: str) -> np.ndarray:
    """``a`` as an (n, floors) array (floors ≤ 3); an empty (n, 0) array for None."""
    if a is None:
        return np.zeros((n, 0))
    arr = np.asarray(a, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] != n or arr.shape[1] > 3:
        raise InputError(
            f"{what}: expected {n} samples of 1 to 3 floors (n,) or (n, floors), got {arr.shape}"
        )
    return arr


def criteria(
    target: np.ndarray,
    measured: np.ndarray,
    fs: float,
    reference: np.ndarray | None = None,
    *,
    max_lag_s: float = 0.2,
) -> dict[str, float]:
    """J1–J9 with the paper's numbering and definitions (Silva et al. 2020, Eqs. 12–20).

    J1 is this project's (:func:`j1_delay`: signed, sub-sample, in s), not the paper's integer
    lag; J2–J9 are in % with the RMS of Eqs. 13–20:

    ========  ==========================================  ========
    J2, J3    measured vs target, RMS and peak            Eq. 13, 14
    J4, J7    measured vs reference floor 1, RMS and peak Eq. 15, 18
    J5, J8    numerical vs reference floor 2              Eq. 16, 19
    J6, J9    numerical vs reference floor 3              Eq. 17, 20
    ========  ==========================================  ========

    Parameters
    ----------
    target : array_like, (n,) or (n, floors)
        The numerical substructure's displacements; column 0 is the actuator's target (floor 1).
    measured : array_like, (n,)
        Measured actuator displacement.
    fs : float
        Sampling rate (Hz).
    reference : array_like, (n,) or (n, floors), optional
        The reference structure's displacements (the whole structure with an ideal transfer
        system). Without it J4–J9 are NaN; floors missing from ``target`` or ``reference``
        give NaN (an SDOF structure has J1–J4 and J7 only).
    max_lag_s : float
        Largest |J1| searched (s).

    Returns
    -------
    dict
        ``J1`` … ``J9``.
    """
    y = np.asarray(measured, dtype=float)
    num = _floors(target, y.size, "target")
    if num.shape[1] == 0:
        raise InputError("target: needs at least one floor")
    ref = _floors(reference, y.size, "reference")
    nan = float("nan")
    out = {
        "J1": j1_delay(num[:, 0], y, fs, max_lag_s),
        "J2": j2_nrms(num[:, 0], y),
        "J3": j3_peak(num[:, 0], y),
    }
    out["J4"] = nrms_error(y, ref[:, 0]) if ref.shape[1] >= 1 else nan
    out["J7"] = peak_error(y, ref[:, 0]) if ref.shape[1] >= 1 else nan
    for floor, (j_rms, j_peak) in ((1, ("J5", "J8")), (2, ("J6", "J9"))):
        ok = ref.shape[1] > floor and num.shape[1] > floor
        out[j_rms] = nrms_error(num[:, floor], ref[:, floor]) if ok else nan
        out[j_peak] = peak_error(num[:, floor], ref[:, floor]) if ok else nan
    return {f"J{i}": out[f"J{i}"] for i in range(1, 10)}


def _matlab_round(x: float) -> float:
    """MATLAB's ``round``: to the nearest integer, halves away from zero (numpy rounds to even)."""
    return float(np.sign(x) * np.floor(np.abs(x) + 0.5))


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    """MATLAB ``corr(a, b)`` of two column vectors (Pearson, NaN for a constant vector)."""
    if a.size < 2:
        return float("nan")
    da = a - a.mean()
    db = b - b.mean()
    # elementwise sums, not np.dot: a multi-threaded BLAS dot is ~100× slower on a busy machine
    den = math.sqrt(float(np.sum(da * da)) * float(np.sum(db * db)))
    return float(np.sum(da * db)) / den if den > 0 else float("nan")


#: Lags searched by the benchmark's J1 (``N = 1:50`` in F4_evaluation.m: 0 … 49 samples).
BENCHMARK_J1_LAGS = 50


def benchmark_criteria(
    target: np.ndarray,
    measured: np.ndarray,
    fs: float,
    reference: np.ndarray | None = None,
) -> dict[str, float]:
    """J1–J9 exactly as the RTHS benchmark's ``F4_evaluation.m`` (lines 11–39) computes them.

    Its numbering and rounding, not the paper's (see the module docstring and
    ``docs/studies.md``):

    * J1 (ms, rounded to 0.1 ms): the lag ``k`` = 0 … 49 samples maximising the Pearson
      correlation of ``measured[k:]`` with ``target[:n−k]``, ``round(10000·k·Δt)/10``; a lead
      gives 0 and 49 samples is the largest value (11.96 ms at 4096 Hz).
    * J2 = ``round(10000·std(x_m − y_n)/std(y_n))/100`` (%), J3 the peak tracking error.
    * J4 / J5: std and peak error of measured vs reference floor 1.
    * J6 / J7: std error of numerical floors 2 / 3 vs reference; J8 / J9: their peak errors.

    ``std`` removes the mean (MATLAB's N−1 normalisation cancels in the ratio); ``round`` rounds
    halves away from zero, as MATLAB does. Floors that are missing give NaN.

    Parameters
    ----------
    target : array_like, (n,) or (n, floors)
        Numerical substructure displacements ``Num_resp`` (column 0: the actuator's target).
    measured : array_like, (n,)
        Measured actuator displacement ``X_m``.
    fs : float
        Sampling rate (Hz); the benchmark runs at 4096 Hz.
    reference : array_like, (n,) or (n, floors), optional
        Reference structure response ``Ref_Resp``.

    Returns
    -------
    dict
        ``J1`` (ms) … ``J9`` (%), with the script's numbering.
    """
    xm = np.asarray(measured, dtype=float)
    if xm.ndim != 1 or xm.size < 2:
        raise InputError(f"measured: expected a 1-D record of ≥ 2 samples, got {xm.shape}")
    if not (np.isfinite(fs) and fs > 0):
        raise InputError(f"fs must be > 0 Hz, got {fs!r}")
    num = _floors(target, xm.size, "target")
    if num.shape[1] == 0:
        raise InputError("target: needs at least one floor")
    ref = _floors(reference, xm.size, "reference")
    n = xm.size
    dt = 1.0 / fs
    r1 = np.array([_pearson(xm[k:], num[: n - k, 0]) for k in range(BENCHMARK_J1_LAGS)])
    # MATLAB's max skips NaN and returns the first maximum (index 1 when all are NaN)
    i = int(np.nanargmax(r1)) if np.any(~np.isnan(r1)) else 0
    out = {"J1": _matlab_round(10000.0 * (i * dt)) / 10.0}

    def std(v: np.ndarray) -> float:
        return float(np.std(v, ddof=1))

    def peak(v: np.ndarray) -> float:
        return float(np.max(np.abs(v)))

    nan = float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        e = xm - num[:, 0]
        out["J2"] = _matlab_round(np.float64(10000.0 * std(e)) / std(num[:, 0])) / 100.0
        out["J3"] = _matlab_round(np.float64(10000.0 * peak(e)) / peak(num[:, 0])) / 100.0
        if ref.shape[1] >= 1:
            e = xm - ref[:, 0]
            out["J4"] = _matlab_round(10000.0 * (np.float64(std(e)) / std(ref[:, 0]))) / 100.0
            out["J5"] = _matlab_round(np.float64(10000.0 * peak(e)) / peak(ref[:, 0])) / 100.0
        else:
            out["J4"] = out["J5"] = nan
        for floor, (j_std, j_peak) in ((1, ("J6", "J8")), (2, ("J7", "J9"))):
            if ref.shape[1] > floor and num.shape[1] > floor:
                e = num[:, floor] - ref[:, floor]
                r = ref[:, floor]
                out[j_std] = _matlab_round(10000.0 * (np.float64(std(e)) / std(r))) / 100.0
                out[j_peak] = _matlab_round(np.float64(10000.0 * peak(e)) / peak(r)) / 100.0
            else:
                out[j_std] = out[j_peak] = nan
    return {f"J{i}": out[f"J{i}"] for i in range(1, 10)}

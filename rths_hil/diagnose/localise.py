"""Where measurement and model disagree: in time, in frequency and by regime.

All three look at the residual ``r = measured − predicted`` of the current model.

**Noise level.** The sensor noise σ is estimated from the residual itself, robustly, from its
third difference: for white noise ``Δ³r`` has variance ``20σ²`` while a smooth structural
response (a few Hz at ~1 kHz) is attenuated by ``(2π f dt)³ ≈ 1e-5``; the median absolute
deviation (×1.4826) ignores the sparse kinks of clamps and limits.

**When.** The mean square of ``r`` over moving windows (length ``window_s``, hop a quarter of
it) is compared with its noise band: for white noise of variance σ², ``M·ms/σ² ~ χ²_M``, so a
window leaves the band when ``ms > σ²(1 + z·√(2/M))`` (z = 5). The moving-window FEI of measured
against predicted (the FEI paper's Eq. 2.1-2.5 on moving windows with overlap, Section 3) gives A(t)
and d(t); their noise band is the linearised FEI error of white noise, ``std ∝ σ/level`` per window
(``level`` = the window's target RMS, see :mod:`rths_hil.fei`), with the constant measured on
one surrogate run of ``predicted + σ·white noise``; a window leaves it at 4 standard deviations.

**Frequency.** Welch/CSD estimates (Hann, 50 % overlap) of the measured and predicted transfer
functions from the command, ``H_m = P_cm/P_cc`` and ``H_p = P_cp/P_cc``, their ratio
``H_m/H_p`` and the coherence ``γ² = |P_cm|²/(P_cc P_mm)``. In the band where the command has
power (≥ 1 % of its peak PSD) and γ² ≥ 0.5, a frequency deviates when ``|ln|H_m/H_p||`` or
the phase difference exceeds 3 standard errors ``√((1 − γ²)/(2 n_d γ²))`` (Bendat & Piersol,
*Random Data*, 4th ed., Table 9.6; ``n_d`` averaged segments) and 0.5 % / 0.005 rad.

**Regime.** Share of the residual's energy (R² of one regressor, no intercept) explained by:
a constant (``mean``: an offset), time since the start (``time``: a drift; 3/4 for a constant,
so a constant still reads ``mean``), the predicted displacement (``amplitude``: a gain), its
velocity (``velocity``: a delay or lag), its direction ``sign(v)`` (``direction``: play,
friction), the measured force (``force``: compliance under load); plus the residual RMS by
quintile of |displacement| and |velocity|, near direction reversals (±50 ms) and elsewhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import signal

from ..errors import InputError
from ..fei import MovingFEIResult, fei, moving_fei

__all__ = ["Localisation", "localise", "moving_ms", "noise_level"]

_Z_WHEN = 5.0
_Z_FEI = 4.0
_Z_FREQ = 3.0
_REVERSAL_S = 0.05


def noise_level(residual: np.ndarray) -> float:
    """Robust white-noise standard deviation of ``residual`` from its third difference (m)."""
    d3 = np.diff(np.asarray(residual, dtype=float), 3)
    if d3.size < 8:
        return float(np.std(residual))
    mad = float(np.median(np.abs(d3 - np.median(d3))))
    return 1.4826 * mad / math.sqrt(20.0)


def moving_ms(x: np.ndarray, m: int, hop: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean square of ``x`` over windows of ``m`` samples every ``hop``: (end indices, values)."""
    c = np.concatenate([[0.0], np.cumsum(np.asarray(x, dtype=float) ** 2)])
    ends = np.arange(m, len(x) + 1, hop)
    return ends - 1, (c[ends] - c[ends - m]) / m


def _intervals(t0: np.ndarray, t1: np.ndarray, flag: np.ndarray) -> list[list[float]]:
    """Merge flagged windows [t0, t1] into disjoint intervals."""
    out: list[list[float]] = []
    for a, b, f in zip(t0.tolist(), t1.tolist(), flag.tolist(), strict=True):
        if not f:
            continue
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [[round(a, 4), round(b, 4)] for a, b in out]


def _freq_intervals(f: np.ndarray, flag: np.ndarray, df: float) -> list[list[float]]:
    return _intervals(f - df / 2, f + df / 2, flag)


@dataclass
class Localisation:
    """Localisation of one residual (JSON-ready summaries plus arrays for the plots)."""

    noise: float
    when: dict[str, Any]
    frequency: dict[str, Any]
    regime: dict[str, Any]
    fei: dict[str, float]
    arrays: dict[str, Any] = field(default_factory=dict, repr=False)
    moving: MovingFEIResult | None = field(default=None, repr=False)

    def to_json(self) -> dict[str, Any]:
        """The summaries (no arrays)."""
        return {
            "noise_m": self.noise,
            "when": self.when,
            "frequency": self.frequency,
            "regime": self.regime,
        }


def _r2(x: np.ndarray, r: np.ndarray, rr: float) -> float:
    xx = float(x @ x)
    if xx == 0 or rr == 0:
        return 0.0
    return float((x @ r) ** 2 / (xx * rr))


def _binned_rms(key: np.ndarray, r: np.ndarray, nbins: int = 5) -> dict[str, list[float]]:
    edges = np.quantile(key, np.linspace(0, 1, nbins + 1))
    idx = np.clip(np.searchsorted(edges, key, side="right") - 1, 0, nbins - 1)
    rms = [
        float(np.sqrt(np.mean(r[idx == i] ** 2))) if np.any(idx == i) else 0.0 for i in range(nbins)
    ]
    return {"edges": [float(e) for e in edges], "rms": rms}


def _regime(
    r: np.ndarray, pred: np.ndarray, t: np.ndarray, fs: float, force: np.ndarray | None
) -> dict[str, Any]:
    rr = float(r @ r)
    v = np.gradient(pred) * fs
    direction = np.sign(v)
    r2 = {
        "mean": _r2(np.ones_like(r), r, rr),
        "time": _r2(t, r, rr),
        "amplitude": _r2(pred - pred.mean(), r, rr),
        "velocity": _r2(v, r, rr),
        "direction": _r2(direction, r, rr),
    }
    if force is not None:
        r2["force"] = _r2(force - force.mean(), r, rr)
    rev = np.flatnonzero(np.diff(direction) != 0)
    near = np.zeros(len(r), dtype=bool)
    if rev.size:
        w = max(int(_REVERSAL_S * fs), 1)
        marks = np.zeros(len(r) + 1)
        np.add.at(marks, np.clip(rev - w, 0, len(r)), 1)
        np.add.at(marks, np.clip(rev + w + 1, 0, len(r)), -1)
        near = np.cumsum(marks)[:-1] > 0
    near_rms = float(np.sqrt(np.mean(r[near] ** 2))) if near.any() else 0.0
    far_rms = float(np.sqrt(np.mean(r[~near] ** 2))) if (~near).any() else 0.0
    dominant = max(r2, key=lambda k: r2[k])
    return {
        "r2": {k: round(v, 4) for k, v in r2.items()},
        "dominant": dominant,
        "by_amplitude": _binned_rms(np.abs(pred - np.median(pred)), r),
        "by_velocity": _binned_rms(np.abs(v), r),
        "reversals": {
            "count": int(rev.size),
            "rms_near": near_rms,
            "rms_elsewhere": far_rms,
            "window_s": _REVERSAL_S,
        },
    }


def _frequency(
    command: np.ndarray, measured: np.ndarray, pred: np.ndarray, fs: float
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    n = len(command)
    nper = int(2 ** round(math.log2(max(min(8.0 * fs, n / 4), 64))))
    kw = {"fs": fs, "nperseg": nper, "noverlap": nper // 2, "window": "hann", "detrend": "constant"}
    f, pcc = signal.welch(command, **kw)
    _, pmm = signal.welch(measured, **kw)
    _, pcm = signal.csd(command, measured, **kw)
    _, pcp = signal.csd(command, pred, **kw)
    n_d = max((n - nper) // (nper // 2) + 1, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        coh = np.abs(pcm) ** 2 / (pcc * pmm)
        ratio = pcm / pcp
        hm = pcm / pcc
        hp = pcp / pcc
    coh = np.nan_to_num(coh)
    band = (pcc >= 0.01 * np.max(pcc)) & (f > 0)
    use = band & (coh >= 0.5) & np.isfinite(ratio) & (np.abs(ratio) > 0)
    df = float(f[1] - f[0])
    arrays = {"f": f, "hm": hm, "hp": hp, "coherence": coh, "ratio": ratio, "use": use}
    out: dict[str, Any] = {"resolution_hz": df, "segments": n_d}
    if not use.any():
        out.update(band_hz=None, deviating_hz=[], note="no coherent band")
        return out, arrays
    la = np.log(np.abs(ratio[use]))
    ph = np.angle(ratio[use])
    g = np.clip(coh[use], 1e-12, 1.0)
    se = np.sqrt((1.0 - g) / (2.0 * n_d * g))
    dev = ((np.abs(la) > _Z_FREQ * se) & (np.abs(la) > 0.005)) | (
        (np.abs(ph) > _Z_FREQ * se) & (np.abs(ph) > 0.005)
    )
    fu = f[use]
    flag = np.zeros_like(use)
    flag[np.flatnonzero(use)[dev]] = True
    w = pcc[use] / np.sum(pcc[use])
    feq = float(np.sum(w * fu))
    amp_ratio = float(np.exp(np.sum(w * la)))
    # command-power-weighted phase delay of measured relative to the model
    delay = float(-np.sum(w * ph) / (2 * np.pi * feq)) if feq > 0 else float("nan")
    worst = int(np.argmax(np.abs(la) + np.abs(ph)))
    out.update(
        band_hz=[float(fu.min()), float(fu.max())],
        f_eq_hz=feq,
        amplitude_ratio=amp_ratio,
        delay_s=delay,
        coherence_min=float(coh[use].min()),
        deviating_hz=_freq_intervals(f, flag, df),
        deviating_fraction=float(dev.mean()),
        worst={
            "f_hz": float(fu[worst]),
            "amplitude_ratio": float(np.exp(la[worst])),
            "phase_deg": float(np.degrees(ph[worst])),
        },
    )
    return out, arrays


def localise(
    command: np.ndarray,
    measured: np.ndarray,
    pred: np.ndarray,
    fs: float,
    force: np.ndarray | None = None,
    window_s: float | None = None,
    noise: float | None = None,
) -> Localisation:
    """Localise the residual ``measured − pred`` in time, frequency and regime.

    Parameters
    ----------
    command, measured, pred : ndarray
        Command, measured and predicted displacement (m).
    fs : float
        Sampling rate (Hz).
    force : ndarray, optional
        Measured force (N), for the force regime.
    window_s : float, optional
        Moving-window length (s); default three periods of the command's equivalent frequency
        (the FEI paper's Eq. 2.4; the FEI paper's 2-3 T_n), within [1 s, duration/4].
    noise : float, optional
        Noise standard deviation (m); estimated from the residual when omitted.

    Returns
    -------
    Localisation
    """
    r = measured - pred
    n = len(r)
    t = np.arange(n) / fs
    sigma = noise_level(r) if noise is None else float(noise)
    sigma = max(sigma, 1e-12)
    whole = fei(command, measured, fs)
    if window_s is None:
        feq = whole.f_eq if whole.valid and whole.f_eq > 0 else 1.0
        window_s = 3.0 / feq
    window_s = float(min(max(window_s, 1.0), n / fs / 4))
    m = max(round(window_s * fs), 8)
    hop = max(m // 4, 1)
    ends, ms = moving_ms(r, m, hop)
    thr = sigma**2 * (1.0 + _Z_WHEN * math.sqrt(2.0 / m))
    flag = ms > thr
    t_end = t[ends]
    t_start = t_end - (m - 1) / fs
    when: dict[str, Any] = {
        "window_s": window_s,
        "noise_band_rms_m": math.sqrt(thr),
        "intervals_s": _intervals(t_start, t_end, flag),
        "fraction": float(flag.mean()) if flag.size else 0.0,
        "peak_s": float(t[int(np.argmax(np.abs(r)))]),
        "peak_m": float(np.max(np.abs(r))),
        "rms_m": float(np.sqrt(np.mean(r * r))),
    }
    arrays: dict[str, Any] = {"t_ms": t_end - 0.5 * (m - 1) / fs, "rms": np.sqrt(ms)}
    arrays["rms_band"] = math.sqrt(thr)
    # moving-window FEI of measured against predicted, with its noise band
    fei_hop = max(int(fs / 16), 1)
    moving = None
    try:
        moving = moving_fei(pred, measured, fs, window_s, hop=fei_hop)
        rng = np.random.default_rng(0)
        sur = moving_fei(pred, pred + sigma * rng.standard_normal(n), fs, window_s, hop=fei_hop)
        ok = sur.valid & np.isfinite(sur.amplitude)
        if ok.any():
            c_a = float(np.sqrt(np.mean(((sur.amplitude[ok] - 1) * sur.level[ok]) ** 2)))
            c_d = float(np.sqrt(np.mean((sur.delay[ok] * sur.level[ok] * sur.f_eq[ok]) ** 2)))
        else:
            c_a = c_d = float("nan")
        with np.errstate(invalid="ignore", divide="ignore"):
            band_a = _Z_FEI * c_a / moving.level
            band_d = _Z_FEI * c_d / (moving.level * moving.f_eq)
        v = moving.valid
        out_a = v & (np.abs(moving.amplitude - 1) > band_a)
        out_d = v & (np.abs(moving.delay) > band_d)
        w0 = np.maximum(moving.t_end - (round(window_s * fs) - 1) / fs, 0.0)
        when["fei"] = {
            "window_s": window_s,
            "amplitude_outside_s": _intervals(w0, moving.t_end, out_a),
            "delay_outside_s": _intervals(w0, moving.t_end, out_d),
            "fraction_outside": float((out_a | out_d)[v].mean()) if v.any() else 0.0,
            "amplitude_range": [
                float(np.nanmin(moving.amplitude)),
                float(np.nanmax(moving.amplitude)),
            ]
            if v.any()
            else None,
            "delay_range_s": [float(np.nanmin(moving.delay)), float(np.nanmax(moving.delay))]
            if v.any()
            else None,
        }
        arrays.update(band_a=band_a, band_d=band_d)
    except InputError as exc:  # e.g. no valid window: report it, keep diagnosing
        when["fei"] = {"error": str(exc)}
    freq, farr = _frequency(command, measured, pred, fs)
    arrays.update(farr)
    regime = _regime(r, pred, t, fs, force)
    whole_res = fei(pred, measured, fs)
    return Localisation(
        noise=sigma,
        when=when,
        frequency=freq,
        regime=regime,
        fei={"amplitude": whole_res.amplitude, "delay_s": whole_res.delay},
        arrays=arrays,
        moving=moving,
    )

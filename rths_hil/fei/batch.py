"""Whole-record and moving-window FEI: direct FFT, batched and exact recursive evaluation.

Conventions, validity rules and algorithms: :mod:`rths_hil.fei`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from ..errors import InputError

log = logging.getLogger(__name__)

#: Default absolute validity floor on a window's target level (m): 1 µm, below the resolution
#: of laboratory displacement transducers.
ABS_FLOOR = 1e-6
#: Default relative validity floor: fraction of the running peak window level.
REL_FLOOR = 0.05
#: A target whose level is below this fraction of its largest absolute value is treated as
#: constant (zero variance), whatever its unit.
ZERO_VARIANCE_RTOL = 1e-9
#: Largest hop for which the online exact evaluator slides DFTs sample by sample
#: (:mod:`rths_hil.fei.sliding`, O(M) per sample) instead of one FFT pair per window
#: (O(M log M) per window): on the development machine the sliding update costs about a tenth
#: of an FFT pair at N = 2048 … 8192.
SLIDING_MAX_HOP = 8
#: Memory budget (bytes) for one batch of the batched/recursive evaluations.
BATCH_BYTES = 64 * 2**20


@dataclass(frozen=True)
class FEIResult:
    """FEI of one window (the FEI paper's Eq. 2.1–2.5).

    Attributes
    ----------
    amplitude : float
        Generalised amplitude A (1 = perfect amplitude tracking).
    phase : float
        Phase φ in rad, in (−π, π].
    f_eq : float
        Equivalent frequency in Hz.
    delay : float
        Equivalent delay d in s (> 0: measured lags target).
    valid : bool
        False when the target has (near) zero variance; the values are then NaN.
    level : float
        Hann-weighted RMS of the mean-free target (m).
    """

    amplitude: float
    phase: float
    f_eq: float
    delay: float
    valid: bool
    level: float


@dataclass
class MovingFEIResult:
    """Moving-window FEI: one entry per evaluated window.

    Attributes
    ----------
    t_end : ndarray
        Time of each window's last sample (s, with sample 0 at t = 0).
    amplitude, phase, f_eq, delay : ndarray
        Per-window A, φ (rad), f_eq (Hz), d (s); NaN where invalid.
    valid : ndarray of bool
        Window validity (see module docstring).
    level : ndarray
        Per-window target level (m).
    """

    t_end: np.ndarray
    amplitude: np.ndarray
    phase: np.ndarray
    f_eq: np.ndarray
    delay: np.ndarray
    valid: np.ndarray
    level: np.ndarray

    def __len__(self) -> int:
        return len(self.t_end)

    @classmethod
    def empty(cls) -> MovingFEIResult:
        """A result with no windows."""
        z = np.empty(0)
        return cls(z, z, z, z, z, np.empty(0, dtype=bool), z)

    @classmethod
    def concatenate(cls, parts: list[MovingFEIResult]) -> MovingFEIResult:
        """Join results of consecutive blocks."""
        if not parts:
            return cls.empty()
        return cls(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("t_end", "amplitude", "phase", "f_eq", "delay", "valid", "level")
            )
        )


def fft_length(n: int) -> int:
    """``M`` = the smallest power of two ≥ ``n`` (the FEI paper's Section 2: ``2p``)."""
    if n < 1:
        raise ValueError("window length must be ≥ 1")
    return 1 << (int(n) - 1).bit_length()


def window_samples(window_s: float, fs: float) -> int:
    """``N = round(window_s · fs)``, checked to be at least 8 samples."""
    if not (math.isfinite(window_s) and window_s > 0):
        raise InputError(f"window must be a positive duration, got {window_s!r} s")
    if not (math.isfinite(fs) and fs > 0):
        raise InputError(f"sampling rate must be positive, got {fs!r} Hz")
    n = round(window_s * fs)
    if n < 8:
        raise InputError(f"window of {window_s:g} s at {fs:g} Hz is {n} samples; need at least 8")
    return n


def _finish(
    E: np.ndarray,
    F: np.ndarray,
    S: np.ndarray,
    fs: float,
    M: int,
    wsq: float,
    abs_floor: float,
    rel_floor: float,
    peak0: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Turn the spectral sums into (A, φ, f_eq, d, valid, level, running peak).

    ``E = Σ|X|²``, ``F = Σ k |X|²``, ``S = Σ Y conj(X)`` over bins 1 … p−1.
    """
    E = np.asarray(E, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.sqrt(np.maximum(2.0 * E / (M * wsq), 0.0))
        peak = np.maximum.accumulate(np.concatenate([[peak0], level]))[1:]
        fei = S / E
        amp = np.abs(fei)
        phase = np.arctan2(fei.imag, fei.real)
        f_eq = (fs / M) * F / E
        delay = -phase / (2.0 * np.pi * f_eq)
    valid = (
        (level > abs_floor)
        & (level >= rel_floor * peak)
        & np.isfinite(f_eq)
        & (f_eq > 0)
        & np.isfinite(amp)
    )
    inv = ~valid
    for arr in (amp, phase, f_eq, delay):
        arr[inv] = np.nan
    last_peak = float(peak[-1]) if peak.size else peak0
    return amp, phase, f_eq, delay, valid, level, last_peak


def _spectral_sums(xw: np.ndarray, yw: np.ndarray, M: int) -> tuple[np.ndarray, ...]:
    """E, F, S over bins 1 … p−1 of windowed, mean-free rows ``xw`` (target), ``yw``."""
    p = M // 2
    X = sfft.rfft(xw, n=M, axis=-1)[..., 1:p]
    Y = sfft.rfft(yw, n=M, axis=-1)[..., 1:p]
    P = X.real * X.real + X.imag * X.imag
    k = np.arange(1, p, dtype=float)
    E = P.sum(axis=-1)
    F = P @ k
    S = np.einsum("...k,...k->...", Y, X.conj())
    return E, F, S


def fei(
    target: np.ndarray,
    measured: np.ndarray,
    fs: float,
    abs_floor: float = ABS_FLOOR,
) -> FEIResult:
    """FEI of a whole target/measured pair (the FEI paper's Eq. 2.1–2.5; conventions in module doc).

    Parameters
    ----------
    target : array_like
        Target (calculated) displacement y_I (m).
    measured : array_like
        Measured displacement y_o (m), same length.
    fs : float
        Sampling rate (Hz).
    abs_floor : float
        Target level (m) at or below which the result is invalid.

    Returns
    -------
    FEIResult
        ``valid`` is False (and the values NaN) for a target of (near) zero variance.
    """
    x = np.asarray(target, dtype=float)
    y = np.asarray(measured, dtype=float)
    if x.ndim != 1 or x.shape != y.shape:
        raise InputError(
            f"target and measured must be 1-D of equal length, got {x.shape}, {y.shape}"
        )
    n = x.size
    if n < 8:
        raise InputError(f"need at least 8 samples for an FEI, got {n}")
    M = fft_length(n)
    w = np.hanning(n)
    xw = w * (x - x.mean())
    yw = w * (y - y.mean())
    E, F, S = _spectral_sums(xw, yw, M)
    floor = max(abs_floor, ZERO_VARIANCE_RTOL * float(np.max(np.abs(x))))
    amp, phase, f_eq, delay, valid, level, _ = _finish(
        np.atleast_1d(E),
        np.atleast_1d(F),
        np.atleast_1d(S),
        fs,
        M,
        float(w @ w),
        floor,
        0.0,
    )
    return FEIResult(
        float(amp[0]),
        float(phase[0]),
        float(f_eq[0]),
        float(delay[0]),
        bool(valid[0]),
        float(level[0]),
    )


# --------------------------------------------------------------------------------------------
# Batched direct evaluation
# --------------------------------------------------------------------------------------------


def _direct_sums(x: np.ndarray, y: np.ndarray, ends: np.ndarray, N: int) -> tuple[np.ndarray, ...]:
    """Spectral sums of the windows ending at indices ``ends``, in memory-bounded batches."""
    M = fft_length(N)
    w = np.hanning(N)
    batch = max(1, BATCH_BYTES // (M * 16 * 4))
    xs = np.lib.stride_tricks.sliding_window_view(x, N)
    ys = np.lib.stride_tricks.sliding_window_view(y, N)
    E = np.empty(ends.size)
    F = np.empty(ends.size)
    S = np.empty(ends.size, dtype=complex)
    for b0 in range(0, ends.size, batch):
        idx = ends[b0 : b0 + batch] - (N - 1)
        xb = xs[idx]
        yb = ys[idx]
        xb = (xb - xb.mean(axis=1, keepdims=True)) * w
        yb = (yb - yb.mean(axis=1, keepdims=True)) * w
        E[b0 : b0 + batch], F[b0 : b0 + batch], S[b0 : b0 + batch] = _spectral_sums(xb, yb, M)
    return E, F, S


# --------------------------------------------------------------------------------------------
# Exact recursive evaluation for every window end (hop = 1)
# --------------------------------------------------------------------------------------------
#
# For a window starting at s = i − N + 1, with Hann weights w_n = Σ_a c_a e^{j a Ω n}
# (a ∈ {−1, 0, 1}, c = (−¼, ½, −¼), Ω = 2π/(N−1)), the spectral sums over bins 1 … p−1 are
#
#     Σ_k g_k U_k conj(V_k) = Σ_{n,m} w_n w_m (u_{s+n} − μ_u)(v_{s+m} − μ_v) K_g(n − m),
#     K_g(l) = Σ_{k=1}^{p−1} g_k e^{−j2πkl/M}   (g_k = 1 for E and S, g_k = k for F).
#
# The raw part Σ_{n,m} w_n w_m u v K splits into nine forms
# e^{−j(a+b)Ωs} Q_ab(i),  Q_ab(i) = Σ_{t,t' ∈ window} U_t V_t' K(t − t'),
# U_t = u_t e^{jaΩt}, V_t = v_t e^{jbΩt}. Moving the window by one sample changes Q_ab by
#
#     Δ(i) = U_i R1(i) + V_i R2(i) + U_i V_i K(0)
#            − U_{i−N} R3(i) − V_{i−N} R4(i) − U_{i−N} V_{i−N} K(0)
#
# with causal convolutions R1 = Σ_{l=1}^{N−1} V_{i−l} K(l), R2 = Σ U_{i−l} K(−l),
# R3 = Σ V_{i−l} K(l − N), R4 = Σ U_{i−l} K(N − l), all computed with FFTs over the record
# (overlap-save in chunks). The mean terms are sliding correlations with fixed vectors.


def _kernel(M: int, N: int, weights: np.ndarray) -> np.ndarray:
    """K_g(l) for l = −(N−1) … N−1, returned as array indexed by l + (N − 1)."""
    G = np.zeros(M, dtype=complex)
    G[1 : M // 2] = weights
    K = np.fft.fft(G)  # K[l mod M] = Σ_k G_k e^{−j2πkl/M}
    lags = np.arange(-(N - 1), N)
    return K[lags % M]


class _Conv:
    """Causal FFT convolution of real sequences with a fixed bank of complex kernels."""

    def __init__(self, kernels: np.ndarray, chunk: int) -> None:
        self.nk, self.klen = kernels.shape
        self.chunk = chunk
        self.P = sfft.next_fast_len(chunk + self.klen - 1)
        self.Kf = sfft.fft(kernels, n=self.P, axis=1)

    def apply(self, seq: np.ndarray, c0: int, c1: int) -> np.ndarray:
        """Outputs y[i] = Σ_l h[l] seq[i − l] for i in [c0, c1) (seq zero before index 0)."""
        lo = c0 - (self.klen - 1)
        if lo < 0:
            seg = np.concatenate([np.zeros(-lo), seq[:c1]])
        else:
            seg = seq[lo:c1]
        Sf = sfft.fft(seg, n=self.P)
        out = sfft.ifft(self.Kf * Sf, axis=1)
        return out[:, self.klen - 1 : self.klen - 1 + (c1 - c0)]


def _recursive_sums(
    x: np.ndarray, y: np.ndarray, N: int, out_ends: np.ndarray
) -> tuple[np.ndarray, ...]:
    """E, F, S for windows ending at ``out_ends`` via the exact recursion (all ends visited)."""
    L = x.size
    M = fft_length(N)
    p = M // 2
    Omega = 2.0 * np.pi / (N - 1)
    coef = {-1: -0.25, 0: 0.5, 1: -0.25}
    mods = (-1, 0, 1)
    n = np.arange(N)
    w = np.hanning(N)
    lags_pos = np.arange(1, N)  # l = 1 … N−1

    K1 = _kernel(M, N, np.ones(p - 1))
    Kk = _kernel(M, N, np.arange(1, p, dtype=float))

    def K_at(K: np.ndarray, lag: np.ndarray) -> np.ndarray:
        return K[lag + (N - 1)]

    # Kernel banks (index l = 0 … N−1, tap at l = 0 is zero for R1..R4).
    def bank(K: np.ndarray) -> np.ndarray:
        rows = []
        lag = lags_pos
        for lags in (lag, -lag, lag - N, N - lag):  # R1, R2, R3, R4
            base = np.zeros(N, dtype=complex)
            base[1:] = K_at(K, lags)
            for b in mods:
                rows.append(base * np.exp(-1j * b * Omega * n))
        return np.array(rows)  # shape (12, N): [R-kind][mod]

    # Mean-term vectors: h1_n = w_n Σ_m w_m K(n−m), h2_m = w_m Σ_n w_n K(n−m).
    def mean_vectors(K: np.ndarray) -> tuple[np.ndarray, np.ndarray, complex]:
        h1 = w * _toeplitz_apply(K, w, N, left=True)
        h2 = w * _toeplitz_apply(K, w, N, left=False)
        return h1, h2, complex(h1.sum())

    chunk = max(8 * N, 2**15)
    chunk = min(chunk, max(N, BATCH_BYTES // (16 * 40)))
    conv1 = _Conv(np.vstack([bank(K1), bank(Kk)]), chunk)  # 24 kernels
    h1_1, h2_1, C1 = mean_vectors(K1)
    h1_k, h2_k, Ck = mean_vectors(Kk)
    # Sliding correlations Σ_n h_n u_{s+n} = Σ_l h_{N−1−l} u_{i−l}.
    corr = _Conv(
        np.vstack([h1_1[::-1], h2_1[::-1], h1_k[::-1], h2_k[::-1], np.full(N, 1.0 / N)]).astype(
            complex
        ),
        chunk,
    )

    # Phasor tables e^{j a Ω t} with exact periodic indexing (period N − 1).
    def phasor(a: int, t: np.ndarray) -> np.ndarray:
        return np.exp(1j * Omega * ((a * t) % (N - 1)))

    Q = {key: np.zeros(9, dtype=complex) for key in ("S", "E", "F")}
    want = np.zeros(L, dtype=bool)
    want[out_ends] = True
    E_out = np.empty(out_ends.size)
    F_out = np.empty(out_ends.size)
    S_out = np.empty(out_ends.size, dtype=complex)
    pos = 0
    K01, K0k = K_at(K1, np.array([0]))[0], K_at(Kk, np.array([0]))[0]
    xpad = np.concatenate([np.zeros(N), x])  # index shift N so that t − N ≥ 0 always
    ypad = np.concatenate([np.zeros(N), y])
    for c0 in range(0, L, chunk):
        c1 = min(L, c0 + chunk)
        t = np.arange(c0, c1)
        rx = conv1.apply(x, c0, c1)  # (24, len)
        ry = conv1.apply(y, c0, c1)
        cx = corr.apply(x, c0, c1)
        cy = corr.apply(y, c0, c1)
        x_now, y_now = x[c0:c1], y[c0:c1]
        x_old, y_old = xpad[c0:c1], ypad[c0:c1]  # samples at t − N (zero before start)
        ph = {a: phasor(a, t) for a in mods}
        ph_old = {a: phasor(a, t - N) for a in mods}
        # For each form (u, v, K-bank offset, K0): accumulate Δ for the nine (a, b) pairs.
        forms = (
            ("S", y_now, x_now, y_old, x_old, ry, rx, 0, K01),
            ("E", x_now, x_now, x_old, x_old, rx, rx, 0, K01),
            ("F", x_now, x_now, x_old, x_old, rx, rx, 12, K0k),
        )
        sums = {}
        for key, u, v, u_o, v_o, ru, rv, off, K0 in forms:
            raw = np.zeros(c1 - c0, dtype=complex)
            acc = Q[key]
            j = 0
            for a in mods:
                U = u * ph[a]
                U_o = u_o * ph_old[a]
                R2 = ru[off + 3 + (a + 1)] * ph[a]
                R4 = ru[off + 9 + (a + 1)] * ph[a]
                for b in mods:
                    V = v * ph[b]
                    V_o = v_o * ph_old[b]
                    R1 = rv[off + 0 + (b + 1)] * ph[b]
                    R3 = rv[off + 6 + (b + 1)] * ph[b]
                    delta = U * R1 + V * R2 + U * V * K0 - U_o * R3 - V_o * R4 - U_o * V_o * K0
                    q = np.cumsum(delta) + acc[j]
                    acc[j] = q[-1]
                    s_ph = phasor(-(a + b), t - (N - 1))
                    raw += coef[a] * coef[b] * s_ph * q
                    j += 1
            sums[key] = raw
        mu_x = cx[4].real
        mu_y = cy[4].real
        # Mean corrections: form(u, v) = raw − μ_v Σ h1 u − μ_u Σ h2 v + μ_u μ_v C.
        S = sums["S"] - mu_x * cy[0] - mu_y * cx[1] + mu_y * mu_x * C1
        E = sums["E"] - mu_x * cx[0] - mu_x * cx[1] + mu_x * mu_x * C1
        F = sums["F"] - mu_x * cx[2] - mu_x * cx[3] + mu_x * mu_x * Ck
        sel = want[c0:c1]
        k = int(sel.sum())
        E_out[pos : pos + k] = E[sel].real
        F_out[pos : pos + k] = F[sel].real
        S_out[pos : pos + k] = S[sel]
        pos += k
    return E_out, F_out, S_out


def _toeplitz_apply(K: np.ndarray, w: np.ndarray, N: int, left: bool) -> np.ndarray:
    """Σ_m K(n−m) w_m (left=True, indexed by n) or Σ_n w_n K(n−m) (indexed by m)."""
    # K is indexed by lag + N − 1 for lags −(N−1) … N−1.
    P = sfft.next_fast_len(3 * N)
    if left:
        full = sfft.ifft(sfft.fft(K, P) * sfft.fft(w, P))
        # (K * w)[n + N − 1] = Σ_m K[n − m + N − 1] w_m
        return full[N - 1 : 2 * N - 1]
    full = sfft.ifft(sfft.fft(K, P) * sfft.fft(w[::-1], P))
    # Σ_n w_n K[n − m + N − 1] = Σ_r w_{N−1−r} K[(N−1−r) − m + N − 1]; index (2N−2−m)
    return full[N - 1 : 2 * N - 1][::-1]


# --------------------------------------------------------------------------------------------
# Moving windows
# --------------------------------------------------------------------------------------------


def _check_pair(target: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(target, dtype=float)
    y = np.asarray(measured, dtype=float)
    if x.ndim != 1 or x.shape != y.shape:
        raise InputError(
            f"target and measured must be 1-D of equal length, got {x.shape}, {y.shape}"
        )
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise InputError("target and measured must be finite (found NaN or inf)")
    return x, y


def moving_fei(
    target: np.ndarray,
    measured: np.ndarray,
    fs: float,
    window_s: float,
    hop: int = 1,
    method: str = "exact",
    decimate: int = 1,
    abs_floor: float = ABS_FLOOR,
    rel_floor: float = REL_FLOOR,
    algorithm: str = "auto",
) -> MovingFEIResult:
    """FEI on moving windows (the FEI paper's Section 3–4): MW for ``hop = N``, MWO with OL = N − 1
    for 1.

    Parameters
    ----------
    target, measured : array_like
        Target y_I and measured y_o displacement (m), equal length, finite.
    fs : float
        Sampling rate (Hz).
    window_s : float
        Window length t_w (s); ``N = round(window_s · fs)`` samples (after decimation:
        ``round(window_s · fs / decimate)``).
    hop : int
        Samples (of the decimated signal) between consecutive window ends. ``hop = 1`` is
        the FEI paper's MWO with ``OL = N − 1`` (the FEI paper's Eq. 7); ``hop = N`` gives MW
        without overlap.
    method : {"exact", "streaming"}
        ``exact`` evaluates Eq. 2.1–2.5 on every window; ``streaming`` runs the O(1)-per-sample
        estimator of :class:`OnlineFEI` over the record (an approximation, see docs/fei.md).
    decimate : int
        Low-pass filter (order-8 Chebyshev I, zero phase, ``scipy.signal.decimate``) and keep
        every ``decimate``-th sample of both signals before windowing (after Guo et al., the FEI
        paper's ref. [7]). The same filter is applied to both signals, so their relative phase is
        kept.
    abs_floor, rel_floor : float
        Validity floors (see module docstring).
    algorithm : {"auto", "direct", "recursive"}
        For ``exact``: batched FFT per window, the exact recursion, or the cheaper of the two.

    Returns
    -------
    MovingFEIResult
        The first window ends at sample ``N − 1``; then every ``hop`` samples.
    """
    x, y = _check_pair(target, measured)
    if int(decimate) != decimate or decimate < 1:
        raise InputError(f"decimate must be a positive integer, got {decimate!r}")
    if int(hop) != hop or hop < 1:
        raise InputError(f"hop must be a positive integer, got {hop!r}")
    decimate, hop = int(decimate), int(hop)
    fs_eff = fs / decimate
    if decimate > 1:
        if x.size < 27 * decimate:
            raise InputError(f"record too short to decimate by {decimate}")
        # imported here: scipy.signal takes 1–2 s to import (scipy 1.17), and the paced
        # loop's exact-FEI worker process, which needs only OnlineFEI, waits for its imports
        from scipy.signal import decimate as _decimate

        x = _decimate(x, decimate, zero_phase=True)
        y = _decimate(y, decimate, zero_phase=True)
    N = window_samples(window_s, fs_eff)
    if N > x.size:
        raise InputError(
            f"window of {window_s:g} s ({N} samples) is longer than the record ({x.size} samples)"
        )
    if method == "streaming":
        from .online import OnlineFEI  # online.py builds on this module

        online = OnlineFEI(
            fs_eff, window_s, hop=hop, method="streaming", abs_floor=abs_floor, rel_floor=rel_floor
        )
        return online.update(x, y)
    if method != "exact":
        raise InputError(f"unknown FEI method {method!r} (use 'exact' or 'streaming')")
    # Global mean removal changes no window (each window removes its own mean) and keeps the
    # recursion well conditioned for signals riding on a large offset.
    x = x - x.mean()
    y = y - y.mean()
    ends = np.arange(N - 1, x.size, hop)
    M = fft_length(N)
    if algorithm == "auto":
        # Cost model (measured): direct ≈ 2 real FFTs of M per window; recursion ≈ 50
        # complex FFT passes over the record, independent of N.
        direct_cost = ends.size * M * math.log2(M) * 1.0
        recursive_cost = x.size * 60.0 * math.log2(max(x.size, 2)) * 2.0
        algorithm = "recursive" if recursive_cost < direct_cost else "direct"
    if algorithm == "recursive":
        E, F, S = _recursive_sums(x, y, N, ends)
    elif algorithm == "direct":
        E, F, S = _direct_sums(x, y, ends, N)
    else:
        raise InputError(f"unknown FEI algorithm {algorithm!r}")
    w = np.hanning(N)
    amp, phase, f_eq, delay, valid, level, _ = _finish(
        E, F, S, fs_eff, M, float(w @ w), abs_floor, rel_floor
    )
    t_end = ends / fs_eff
    return MovingFEIResult(t_end, amp, phase, f_eq, delay, valid, level)

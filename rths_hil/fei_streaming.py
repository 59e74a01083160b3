"""Streaming moving-window FEI: O(1) work per sample, independent of the window length.

The exact windowed FEI needs, per window, ``E = Σ|X|²``, ``F = Σ k|X|²`` and ``S = Σ Y conj(X)``
over the one-sided bins (seed Eq. 2.1, 2.4). With analytic signals ``z = u + jH[u]`` of the
mean-free target and measured signals, Parseval gives, for a Hann window ``w`` slowly varying
against the signal (Bedrosian's theorem),

    S ≈ (M/4) Σ_n w_n² z_o[n] conj(z_I[n]),     E ≈ (M/4) Σ_n w_n² |z_I[n]|²,
    F ≈ (M/4)(M/2π) Σ_n w_n² Im(conj(z_I[n−1]) z_I[n])

(the last because ``Im(conj(z[n−1]) z[n]) = |z|² sin(2π f/fs)`` for a tone). The ratios give
``A``, ``φ``, ``f_eq`` and ``d`` exactly as in Eq. 2.2–2.5; the factors ``M/4`` cancel.

* Mean removal: a first-order DC blocker (corner ``0.1/t_w``) on both signals.
* Analytic signals: a pair of all-pass chains of real first-order sections whose phase
  difference is 90° within ``max_phase_error`` over ``[0.25/t_w, 0.45 fs]``. Poles from the
  closed-form elliptic design of Orchard (1950) for wide-band 90° phase-difference networks,
  ``p_r = sqrt(ω₁ω₂ k') · sn(u_r, k)/cn(u_r, k)``, ``u_r = (2r − 1) K(k)/(4 n)``, ``k' = ω₁/ω₂``,
  mapped to the digital domain with the bilinear transform (band edges pre-warped).
* Hann²-weighted sliding sums: ``w_n² = 3/8 − ½ cos Ωn + ⅛ cos 2Ωn`` (``Ω = 2π/(N−1)``), so each
  weighted sum is a combination of rectangular sliding sums of ``q[t] e^{jmΩt}`` (m = 0, ±1, ±2),
  updated by one addition and one subtraction per sample, with phasors from an exact table of
  period ``N − 1``. Against round-off drift the sums are resynchronised every ``N`` samples by
  swapping in a second set of sums that was built by additions only over exactly the current
  window (no O(N) step, no spikes).

Both signals pass through identical filters, so their relative phase is untouched; the common
group delay of the all-pass chains shifts the window's effective position slightly into the past
(documented in ``docs/fei.md``).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numba
import numpy as np
from scipy.special import ellipj, ellipk

#: Target worst-case phase-difference error of the Hilbert pair (degrees).
MAX_PHASE_ERROR_DEG = 0.01


@lru_cache(maxsize=64)
def hilbert_pair(f_lo: float, f_hi: float, fs: float, max_error_deg: float = MAX_PHASE_ERROR_DEG):
    """Design a digital 90° phase-difference all-pass pair (Orchard 1950, bilinear transform).

    Parameters
    ----------
    f_lo, f_hi : float
        Band edges (Hz), ``0 < f_lo < f_hi < fs/2``.
    fs : float
        Sampling rate (Hz).
    max_error_deg : float
        Worst-case deviation from 90° in the band; the number of sections grows until met.

    Returns
    -------
    a_i, a_q : ndarray
        Coefficients of the first-order sections ``(a + z⁻¹)/(1 + a z⁻¹)`` of the in-phase and
        quadrature chains; the quadrature output lags the in-phase output by 90°.
    error_deg : float
        Achieved worst-case phase error in the band (degrees).
    """
    if not 0 < f_lo < f_hi < fs / 2:
        raise ValueError(f"bad Hilbert band {f_lo}–{f_hi} Hz at fs = {fs} Hz")
    w1 = 2 * fs * math.tan(math.pi * f_lo / fs)
    w2 = 2 * fs * math.tan(math.pi * f_hi / fs)
    kp = w1 / w2
    m = 1.0 - kp * kp
    K = ellipk(m)
    grid = np.geomspace(f_lo, f_hi, 512) * 2 * np.pi / fs
    for n in range(2, 24):
        r = np.arange(1, 2 * n + 1)
        sn, cn, _, _ = ellipj((2 * r - 1) * K / (4 * n), m)
        p = np.sort(math.sqrt(w1 * w2 * kp) * sn / cn)
        a = (p - 2 * fs) / (p + 2 * fs)
        a_i, a_q = a[1::2].copy(), a[0::2].copy()
        err = np.degrees(np.max(np.abs(_phase(a_i, grid) - _phase(a_q, grid) - np.pi / 2)))
        if err <= max_error_deg:
            break
    return a_i, a_q, float(err)


def _phase(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Unwrapped phase of a chain of first-order all-pass sections at normalised ω."""
    z1 = np.exp(-1j * w)
    h = np.ones_like(z1)
    for ai in a:
        h *= (ai + z1) / (1 + ai * z1)
    return np.unwrap(np.angle(h))


# State layout (float64 array ``st``):
_DC_R = 0  # DC blocker pole
_DCX_IN, _DCX_OUT, _DCY_IN, _DCY_OUT = 1, 2, 3, 4
_ZPREV_RE, _ZPREV_IM = 5, 6  # previous analytic target sample
_PEAK = 7  # running peak level
_ABS, _REL = 8, 9
_FS = 10
_WSQ = 11  # Σ w_n²
_NST = 12
# Integer state (int64 array ``ist``):
_T = 0  # samples seen
_NEXT_END = 1  # sample index of the next window end to report
_HOP = 2
_FRESH_START = 3  # sample index at which the fresh sums started
_NIST = 4


@numba.njit(cache=True, nogil=True, fastmath=False)
def _allpass_chain(v: float, a: np.ndarray, s: np.ndarray) -> float:
    """Run one sample through first-order all-pass sections; s[j] holds (x_prev, y_prev)."""
    for j in range(a.shape[0]):
        xp = s[j, 0]
        yp = s[j, 1]
        out = a[j] * (v - yp) + xp
        s[j, 0] = v
        s[j, 1] = out
        v = out
    return v


@numba.njit(cache=True, nogil=True, fastmath=False)
def _stream_kernel(
    xs, ys, st, ist, a_i, a_q, sxi, sxq, syi, syq, ring, ph, acc, fresh, out, out_t
):  # pragma: no cover - compiled
    """Process a block; write completed windows to ``out`` (A, φ, f_eq, d, valid, level)."""
    N = ring.shape[0]
    P = ph.shape[0]  # N − 1
    r = st[_DC_R]
    fs = st[_FS]
    wsq = st[_WSQ]
    nout = 0
    for k in range(xs.shape[0]):
        t = ist[_T]
        if t == 0:  # start the DC blockers at the first value: no step transient
            st[_DCX_IN] = xs[k]
            st[_DCY_IN] = ys[k]
        # DC blockers.
        xo = xs[k] - st[_DCX_IN] + r * st[_DCX_OUT]
        st[_DCX_IN] = xs[k]
        st[_DCX_OUT] = xo
        yo = ys[k] - st[_DCY_IN] + r * st[_DCY_OUT]
        st[_DCY_IN] = ys[k]
        st[_DCY_OUT] = yo
        # Analytic signals.
        zx = complex(_allpass_chain(xo, a_i, sxi), _allpass_chain(xo, a_q, sxq))
        zy = complex(_allpass_chain(yo, a_i, syi), _allpass_chain(yo, a_q, syq))
        zp = complex(st[_ZPREV_RE], st[_ZPREV_IM])
        st[_ZPREV_RE] = zx.real
        st[_ZPREV_IM] = zx.imag
        q1 = zy * zx.conjugate()
        q2 = zx.real * zx.real + zx.imag * zx.imag
        q3 = (zp.conjugate() * zx).imag
        slot = t % N
        o1 = ring[slot, 0]
        o2 = ring[slot, 1].real
        o3 = ring[slot, 2].real
        ring[slot, 0] = q1
        ring[slot, 1] = q2
        ring[slot, 2] = q3
        told = t - N
        # Sliding sums acc[m + 2, j]: Σ q_j e^{j m Ω t} for m = −2 … 2 (q1) and m = 0 … 2.
        for m in range(-2, 3):
            pn = ph[(m * t) % P]
            po = ph[(m * told) % P] if told >= 0 else 0j
            acc[m + 2, 0] += q1 * pn - o1 * po
            fresh[m + 2, 0] += q1 * pn
            if m >= 0:
                acc[m + 2, 1] += q2 * pn - o2 * po
                acc[m + 2, 2] += q3 * pn - o3 * po
                fresh[m + 2, 1] += q2 * pn
                fresh[m + 2, 2] += q3 * pn
        ist[_T] = t + 1
        # Resynchronise: the fresh sums hold exactly the current window after N additions.
        if t + 1 - ist[_FRESH_START] == N:
            for i in range(5):
                for j in range(3):
                    acc[i, j] = fresh[i, j]
                    fresh[i, j] = 0j
            ist[_FRESH_START] = t + 1
        if t == ist[_NEXT_END]:
            ist[_NEXT_END] = t + ist[_HOP]
            s0 = t - N + 1
            # Σ w² q = 3/8 Σq − ½ Re-part(cos) + ⅛ (cos 2): cos(mΩn) with n = t' − s0.
            c1 = ph[(-s0) % P]
            c2 = ph[(-2 * s0) % P]
            S = (
                0.375 * acc[2, 0]
                - 0.25 * (c1 * acc[3, 0] + c1.conjugate() * acc[1, 0])
                + 0.0625 * (c2 * acc[4, 0] + c2.conjugate() * acc[0, 0])
            )
            E = 0.375 * acc[2, 1].real - 0.5 * (c1 * acc[3, 1]).real + 0.125 * (c2 * acc[4, 1]).real
            F = 0.375 * acc[2, 2].real - 0.5 * (c1 * acc[3, 2]).real + 0.125 * (c2 * acc[4, 2]).real
            level = math.sqrt(max(E, 0.0) / (2.0 * wsq))
            if level > st[_PEAK]:
                st[_PEAK] = level
            f_eq = fs * F / (2.0 * math.pi * E) if E > 0 else math.nan
            valid = (
                level > st[_ABS]
                and level >= st[_REL] * st[_PEAK]
                and f_eq > 0
                and math.isfinite(f_eq)
            )
            if valid:
                fei = S / E
                amp = abs(fei)
                phase = math.atan2(fei.imag, fei.real)
                delay = -phase / (2.0 * math.pi * f_eq)
            else:
                amp = math.nan
                phase = math.nan
                f_eq = math.nan
                delay = math.nan
            out[nout, 0] = amp
            out[nout, 1] = phase
            out[nout, 2] = f_eq
            out[nout, 3] = delay
            out[nout, 4] = 1.0 if valid else 0.0
            out[nout, 5] = level
            out_t[nout] = t
            nout += 1
    return nout


class StreamingFEI:
    """O(1)-per-sample moving-window FEI estimator (see module docstring).

    Parameters
    ----------
    fs : float
        Sampling rate (Hz).
    N : int
        Window length (samples).
    hop : int
        Samples between reported windows.
    abs_floor, rel_floor : float
        Validity floors as in :mod:`rths_hil.fei`.
    """

    def __init__(self, fs: float, N: int, hop: int, abs_floor: float, rel_floor: float) -> None:
        self.fs = float(fs)
        self.N = int(N)
        self.hop = int(hop)
        window_s = N / fs
        f_lo = min(0.25 / window_s, 0.01 * fs)
        f_hi = 0.45 * fs
        self.a_i, self.a_q, self.phase_error_deg = hilbert_pair(f_lo, f_hi, self.fs)
        self.dc_corner = 0.1 / window_s
        self._init_state(abs_floor, rel_floor)

    def _init_state(self, abs_floor: float, rel_floor: float) -> None:
        N = self.N
        self.st = np.zeros(_NST)
        self.st[_DC_R] = math.exp(-2 * math.pi * self.dc_corner / self.fs)
        self.st[_ABS] = abs_floor
        self.st[_REL] = rel_floor
        self.st[_FS] = self.fs
        w = np.hanning(N)
        self.st[_WSQ] = float(w @ w)
        self.ist = np.zeros(_NIST, dtype=np.int64)
        self.ist[_NEXT_END] = N - 1
        self.ist[_HOP] = self.hop
        ni, nq = self.a_i.size, self.a_q.size
        self.sxi = np.zeros((ni, 2))
        self.sxq = np.zeros((nq, 2))
        self.syi = np.zeros((ni, 2))
        self.syq = np.zeros((nq, 2))
        self.ring = np.zeros((N, 3), dtype=complex)
        self.ph = np.exp(1j * 2 * np.pi * np.arange(N - 1) / (N - 1))
        self.acc = np.zeros((5, 3), dtype=complex)
        self.fresh = np.zeros((5, 3), dtype=complex)
        self._out = np.empty((1, 6))
        self._out_t = np.empty(1, dtype=np.int64)

    def process(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Push blocks; return (rows of A, φ, f_eq, d, valid, level; window-end indices)."""
        nmax = x.shape[0] // self.hop + 1
        if self._out.shape[0] < nmax:
            self._out = np.empty((nmax, 6))
            self._out_t = np.empty(nmax, dtype=np.int64)
        n = _stream_kernel(
            x,
            y,
            self.st,
            self.ist,
            self.a_i,
            self.a_q,
            self.sxi,
            self.sxq,
            self.syi,
            self.syq,
            self.ring,
            self.ph,
            self.acc,
            self.fresh,
            self._out,
            self._out_t,
        )
        return self._out[:n], self._out_t[:n]

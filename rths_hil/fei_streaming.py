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
#: Upper band edge of the Hilbert pair (Hz): displacement responses of structures carry no
#: energy that matters above it. Raised to 40·f_lo for very short windows.
F_HI_MAX = 50.0


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
_M = 12  # FFT length of the exact FEI
_W1 = 13  # Σ w_n
_WP = 14  # Σ (−1)^n w_n
_X0, _Y0 = 15, 16  # first samples (subtracted from the raw signals against round-off)
_NST = 17
# Integer state (int64 array ``ist``):
_T = 0  # samples seen
_NEXT_END = 1  # sample index of the next window end to report
_HOP = 2
_FRESH_START = 3  # sample index at which the fresh sums started
_I1, _I2 = 4, 5  # t mod P and 2t mod P (phasor table indices of the newest sample)
_O1, _O2 = 6, 7  # the same for the sample leaving the window (t − N)
_SLOT = 8  # t mod N (ring slot)
_NIST = 9


@numba.njit(cache=True, nogil=True, inline="always")
def _wrap(i: int, P: int) -> int:
    if i >= P:
        return i - P
    if i < 0:
        return i + P
    return i


@numba.njit(cache=True, nogil=True, inline="always")
def _hann_sums(acc, j, c1, c2):
    """(Σ w_n² q, Σ w_n q) over the window from the sliding sums of column ``j``."""
    a0 = acc[0, 2, j].real
    a1 = (c1 * acc[0, 3, j]).real
    a2 = (c2 * acc[0, 4, j]).real
    return 0.375 * a0 - 0.5 * a1 + 0.125 * a2, 0.5 * a0 - 0.5 * a1


@numba.njit(cache=True, nogil=True, inline="always", fastmath={"contract", "arcp", "reassoc"})
def _sample(x, y, st, ist, coef, cst, ring, ph, acc, out, out_t, nout):  # pragma: no cover
    """Advance the estimator by one sample pair; return the new number of output rows."""
    N = ring.shape[0]
    P = ph.shape[0]  # N − 1
    t = ist[_T]
    if t == 0:  # start the DC blockers at the first value: no step transient
        st[_DCX_IN] = x
        st[_DCY_IN] = y
        st[_X0] = x
        st[_Y0] = y
    r = st[_DC_R]
    xo = x - st[_DCX_IN] + r * st[_DCX_OUT]
    st[_DCX_IN] = x
    st[_DCX_OUT] = xo
    yo = y - st[_DCY_IN] + r * st[_DCY_OUT]
    st[_DCY_IN] = y
    st[_DCY_OUT] = yo
    # Four all-pass chains side by side: (x, I), (x, Q), (y, I), (y, Q).
    v0 = xo
    v1 = xo
    v2 = yo
    v3 = yo
    for j in range(coef.shape[0]):
        ai = coef[j, 0]
        aq = coef[j, 1]
        o0 = ai * (v0 - cst[j, 0, 1]) + cst[j, 0, 0]
        o1 = aq * (v1 - cst[j, 1, 1]) + cst[j, 1, 0]
        o2 = ai * (v2 - cst[j, 2, 1]) + cst[j, 2, 0]
        o3 = aq * (v3 - cst[j, 3, 1]) + cst[j, 3, 0]
        cst[j, 0, 0] = v0
        cst[j, 1, 0] = v1
        cst[j, 2, 0] = v2
        cst[j, 3, 0] = v3
        cst[j, 0, 1] = o0
        cst[j, 1, 1] = o1
        cst[j, 2, 1] = o2
        cst[j, 3, 1] = o3
        v0 = o0
        v1 = o1
        v2 = o2
        v3 = o3
    zx = complex(v0, v1)
    zy = complex(v2, v3)
    zp = complex(st[_ZPREV_RE], st[_ZPREV_IM])
    st[_ZPREV_RE] = v0
    st[_ZPREV_IM] = v1
    q1 = zy * zx.conjugate()
    q2 = v0 * v0 + v1 * v1
    q3 = (zp.conjugate() * zx).imag
    slot = ist[_SLOT]
    ist[_SLOT] = slot + 1 if slot + 1 < N else 0
    o1c = ring[slot, 0]
    o2 = ring[slot, 1].real
    o3 = ring[slot, 2].real
    ring[slot, 0] = q1
    ring[slot, 1] = q2
    ring[slot, 2] = q3
    # Raw (mean-free per window, exactly as the exact FEI) quantities for Re S and E.
    xr = x - st[_X0]
    yr = y - st[_Y0]
    sgn = 1.0 if (t & 1) == 0 else -1.0
    raw_new = (yr * xr, xr * xr, xr, yr, sgn * xr, sgn * yr)
    raw_old = (
        ring[slot, 3].real,
        ring[slot, 4].real,
        ring[slot, 5].real,
        ring[slot, 6].real,
        ring[slot, 7].real,
        ring[slot, 8].real,
    )
    for j in range(6):
        ring[slot, 3 + j] = raw_new[j]
    i1 = ist[_I1]
    i2 = ist[_I2]
    p0 = 1.0 + 0j
    p1 = ph[i1]
    p2 = ph[i2]
    pm1 = p1.conjugate()
    pm2 = p2.conjugate()
    # Sliding sums acc[0, m + 2, j] = Σ q_j e^{j m Ω t}; acc[1] are the fresh sums.
    for b in range(2):  # the running sums and the fresh ones
        acc[b, 0, 0] += q1 * pm2
        acc[b, 1, 0] += q1 * pm1
        acc[b, 2, 0] += q1
        acc[b, 3, 0] += q1 * p1
        acc[b, 4, 0] += q1 * p2
        acc[b, 2, 1] += q2 * p0
        acc[b, 3, 1] += q2 * p1
        acc[b, 4, 1] += q2 * p2
        acc[b, 2, 2] += q3 * p0
        acc[b, 3, 2] += q3 * p1
        acc[b, 4, 2] += q3 * p2
    for j in range(6):
        q = raw_new[j]
        for b in range(2):
            acc[b, 2, 3 + j] += q
            acc[b, 3, 3 + j] += q * p1
            acc[b, 4, 3 + j] += q * p2
    if t >= N:
        r1 = ph[ist[_O1]]
        r2 = ph[ist[_O2]]
        rm1 = r1.conjugate()
        rm2 = r2.conjugate()
        acc[0, 0, 0] -= o1c * rm2
        acc[0, 1, 0] -= o1c * rm1
        acc[0, 2, 0] -= o1c
        acc[0, 3, 0] -= o1c * r1
        acc[0, 4, 0] -= o1c * r2
        acc[0, 2, 1] -= o2
        acc[0, 3, 1] -= o2 * r1
        acc[0, 4, 1] -= o2 * r2
        acc[0, 2, 2] -= o3
        acc[0, 3, 2] -= o3 * r1
        acc[0, 4, 2] -= o3 * r2
        for j in range(6):
            q = raw_old[j]
            acc[0, 2, 3 + j] -= q
            acc[0, 3, 3 + j] -= q * r1
            acc[0, 4, 3 + j] -= q * r2
    ist[_O1] = _wrap(ist[_O1] + 1, P)
    ist[_O2] = _wrap(ist[_O2] + 2, P)
    ist[_I1] = _wrap(i1 + 1, P)
    ist[_I2] = _wrap(i2 + 2, P)
    ist[_T] = t + 1
    # Resynchronise: the fresh sums hold exactly the current window after N additions.
    if t + 1 - ist[_FRESH_START] == N:
        for i in range(5):
            for j in range(acc.shape[2]):
                acc[0, i, j] = acc[1, i, j]
                acc[1, i, j] = 0j
        ist[_FRESH_START] = t + 1
    if t != ist[_NEXT_END]:
        return nout
    ist[_NEXT_END] = t + ist[_HOP]
    # Σ_n w_n² q = 3/8 Σq − ½ Σ q cos(Ωn) + ⅛ Σ q cos(2Ωn), n = t' − s0, s0 = t − N + 1:
    # e^{jmΩn} = e^{jmΩt'} e^{−jmΩ s0}, and e^{−jΩ s0} = e^{jΩ(N−1−t)} = conj(phasor of t).
    c1 = pm1
    c2 = pm2
    S = (
        0.375 * acc[0, 2, 0]
        - 0.25 * (c1 * acc[0, 3, 0] + p1 * acc[0, 1, 0])
        + 0.0625 * (c2 * acc[0, 4, 0] + p2 * acc[0, 0, 0])
    )
    E = (
        0.375 * acc[0, 2, 1].real
        - 0.5 * (c1 * acc[0, 3, 1]).real
        + 0.125 * (c2 * acc[0, 4, 1]).real
    )
    F = (
        0.375 * acc[0, 2, 2].real
        - 0.5 * (c1 * acc[0, 3, 2]).real
        + 0.125 * (c2 * acc[0, 4, 2]).real
    )
    # Exact Re S and E of the windowed, mean-free signals (Parseval, one-sided bins 1 … p−1):
    # Σ_k Y conj(X) over all M bins = M Σ ŷ x̂; remove DC (k = 0) and Nyquist (k = p), halve.
    n_win = float(N)
    mu_x = acc[0, 2, 5].real / n_win
    mu_y = acc[0, 2, 6].real / n_win
    yx2, _ = _hann_sums(acc, 3, c1, c2)
    xx2, _ = _hann_sums(acc, 4, c1, c2)
    x2, x1 = _hann_sums(acc, 5, c1, c2)
    y2, y1 = _hann_sums(acc, 6, c1, c2)
    _, sx1 = _hann_sums(acc, 7, c1, c2)
    _, sy1 = _hann_sums(acc, 8, c1, c2)
    w2 = st[_WSQ]
    sxy = yx2 - mu_x * y2 - mu_y * x2 + mu_x * mu_y * w2
    sxx = xx2 - 2.0 * mu_x * x2 + mu_x * mu_x * w2
    x_dc = x1 - mu_x * st[_W1]
    y_dc = y1 - mu_y * st[_W1]
    s0_sign = 1.0 if ((t - N + 1) & 1) == 0 else -1.0
    x_ny = s0_sign * sx1 - mu_x * st[_WP]
    y_ny = s0_sign * sy1 - mu_y * st[_WP]
    Mf = st[_M]
    re_s = 0.5 * (Mf * sxy - y_dc * x_dc - y_ny * x_ny)
    e_ex = 0.5 * (Mf * sxx - x_dc * x_dc - x_ny * x_ny)
    level = math.sqrt(max(2.0 * e_ex / (Mf * w2), 0.0))
    if level > st[_PEAK]:
        st[_PEAK] = level
    f_eq = st[_FS] * F / (2.0 * math.pi * E) if E > 0 else math.nan
    valid = (
        level > st[_ABS]
        and level >= st[_REL] * st[_PEAK]
        and f_eq > 0
        and math.isfinite(f_eq)
        and e_ex > 0
    )
    if valid:
        # Amplitude: real part exact, quadrature part from the analytic signals (ratio to
        # their E). Phase: wholly from the analytic signals (both parts in the same window).
        ratio = S / E
        amp = math.hypot(re_s / e_ex, ratio.imag)
        phase = math.atan2(ratio.imag, ratio.real)
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
    return nout + 1


@numba.njit(cache=True, nogil=True)
def _stream_block(xs, ys, st, ist, coef, cst, ring, ph, acc, out, out_t):  # pragma: no cover
    """Process a block; completed windows go to ``out`` (A, φ, f_eq, d, valid, level)."""
    nout = 0
    for k in range(xs.shape[0]):
        nout = _sample(xs[k], ys[k], st, ist, coef, cst, ring, ph, acc, out, out_t, nout)
    return nout


@numba.njit(cache=True, nogil=True)
def _stream_one(x, y, st, ist, coef, cst, ring, ph, acc, out, out_t):  # pragma: no cover
    """Process one sample pair; return 1 when a window completed (row 0 of ``out``)."""
    return _sample(x, y, st, ist, coef, cst, ring, ph, acc, out, out_t, 0)


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
        f_hi = min(0.45 * fs, max(F_HI_MAX, 40.0 * f_lo))
        self.a_i, self.a_q, self.phase_error_deg = hilbert_pair(f_lo, f_hi, self.fs)
        self.band = (f_lo, f_hi)
        self.dc_corner = 0.1 / window_s
        N = self.N
        self.st = np.zeros(_NST)
        self.st[_DC_R] = math.exp(-2 * math.pi * self.dc_corner / self.fs)
        self.st[_ABS] = abs_floor
        self.st[_REL] = rel_floor
        self.st[_FS] = self.fs
        w = np.hanning(N)
        self.st[_WSQ] = float(w @ w)
        self.st[_W1] = float(w.sum())
        self.st[_WP] = float(w @ ((-1.0) ** np.arange(N)))
        M = 1 << (N - 1).bit_length()
        self.st[_M] = float(M)
        self.ist = np.zeros(_NIST, dtype=np.int64)
        self.ist[_NEXT_END] = N - 1
        self.ist[_HOP] = self.hop
        P = N - 1
        self.ist[_O1] = (-N) % P
        self.ist[_O2] = (-2 * N) % P
        self.coef = np.ascontiguousarray(np.column_stack([self.a_i, self.a_q]))
        self.cst = np.zeros((self.coef.shape[0], 4, 2))
        self.ring = np.zeros((N, 9), dtype=complex)
        self.ph = np.exp(1j * 2 * np.pi * np.arange(P) / P)
        self.acc = np.zeros((2, 5, 9), dtype=complex)
        self._out = np.empty((1, 6))
        self._out_t = np.empty(1, dtype=np.int64)
        self._one = np.empty((1, 6))
        self._one_t = np.empty(1, dtype=np.int64)
        self._args = (
            self.st,
            self.ist,
            self.coef,
            self.cst,
            self.ring,
            self.ph,
            self.acc,
            self._one,
            self._one_t,
        )

    def process(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Push blocks; return (rows of A, φ, f_eq, d, valid, level; window-end indices)."""
        nmax = x.shape[0] // self.hop + 1
        if self._out.shape[0] < nmax:
            self._out = np.empty((nmax, 6))
            self._out_t = np.empty(nmax, dtype=np.int64)
        n = _stream_block(
            x,
            y,
            self.st,
            self.ist,
            self.coef,
            self.cst,
            self.ring,
            self.ph,
            self.acc,
            self._out,
            self._out_t,
        )
        return self._out[:n], self._out_t[:n]

    def push(self, x: float, y: float) -> bool:
        """Push one sample pair; True when a window completed (its row: :attr:`last`)."""
        return _stream_one(x, y, *self._args) > 0

    @property
    def last(self) -> np.ndarray:
        """Row (A, φ, f_eq, d, valid, level) of the window completed by the last :meth:`push`."""
        return self._one[0]

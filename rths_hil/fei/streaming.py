"""Streaming moving-window FEI: O(1) work per sample, independent of the window length.

The exact windowed FEI needs, per window, ``E = Σ|X|²``, ``F = Σ k|X|²`` and ``S = Σ Y conj(X)``
over the one-sided bins (the FEI paper, Eq. 2.1, 2.4). With analytic signals ``z = u + jH[u]``
of the mean-free target and measured signals, Parseval gives, for a Hann window ``w`` slowly
varying against the signal (Bedrosian's theorem),

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
  period ``N − 1``. Against round-off drift the sums are resynchronised once every
  ``LB_RESYNC_WINDOWS`` windows (at stream positions) by swapping in a second set of sums that
  was built by additions only over exactly the current window (no O(N) step, no spikes).
* Exact parts: ``Re S`` and ``E`` over all bins by Parseval from Hann- and Hann²-weighted
  sliding sums of the raw samples, and ``E, F, S`` over the bins below ``exact_band`` cycles
  per window by sliding DFTs (:mod:`rths_hil.fei.sliding`, low band); the analytic signals
  supply only the rest of ``Im S`` and ``F`` (``docs/fei.md``).

Both signals pass through identical filters, so their relative phase is untouched; the common
group delay of the all-pass chains shifts the window's effective position slightly into the past
(documented in ``docs/fei.md``).

Implementation: plain ``numba.njit`` loops, one sample at a time through all stages (filters,
sliding sums, low band; at each window end its sums), then a second pass turning the sums of
all windows of a block into A, f_eq, validity and level. The arithmetic of each quantity is
fixed by the source order and the stream position, so results do not depend on how the stream
is cut into blocks. ``fastmath`` is limited to ``contract`` (fused multiply-adds; one rounding
less, never a value that is not a rounding of the exact result); flags that assume finite
values are not used (the validity test relies on ``isfinite``). All state lives in one float
and one integer array (views at fixed offsets), so a pushed sample costs one short call. The
phase ``atan2`` of a block is taken by numpy; a single pushed sample takes it from libm (the
two agree to an ulp).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numba
import numpy as np
from scipy.signal import butter
from scipy.special import ellipj, ellipk

from .sliding import (
    LB_CONST_ROWS,
    LB_RESYNC_WINDOWS,
    JitOptions,
    lowband_constants,
    lowband_step,
    lowband_swap,
    lowband_window,
)

#: Target worst-case phase-difference error of the Hilbert pair (degrees).
MAX_PHASE_ERROR_DEG = 0.01
#: Width of the exact low band in cycles per window: bins below ``EXACT_BAND / t_w`` are
#: evaluated exactly by sliding DFTs (:mod:`rths_hil.fei.sliding`); only the rest of the
#: quadrature part comes from the analytic signals. Where the window's spectrum sits near DC
#: (windows of 2–3 natural periods) the analytic signal of the windowed signal differs from the
#: windowed analytic signal (Bedrosian), and that low band decides the delay; docs/fei.md.
EXACT_BAND = 20.0
#: Upper band edge of the Hilbert pair (Hz): displacement responses of structures carry no
#: energy that matters above it. Raised to 40·f_lo for very short windows.
F_HI_MAX = 50.0


@lru_cache(maxsize=64)
def hilbert_pair(f_lo: float, f_hi: float, fs: float, max_error_deg: float = MAX_PHASE_ERROR_DEG):
    """Design a digital 90° phase-difference all-pass pair (Orchard 1950, bilinear transform).

    Orchard, H. J., "Synthesis of wideband two-phase networks", Wireless Engineer 27 (1950):
    the analogue poles ``p_r = sqrt(ω₁ω₂ k') · sn(u_r, k)/cn(u_r, k)`` alternate between the
    two chains; the bilinear transform ``a = (p − 2fs)/(p + 2fs)`` with pre-warped band edges
    gives the digital sections ``(a + z⁻¹)/(1 + a z⁻¹)``.

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


# Integer state (int64 array ``ib``):
_T = 0  # samples seen
_NEXT_END = 1  # sample index of the next window end to report
_HOP = 2
_RPOS = 3  # position of the newest sample in the resync period (t mod LB_RESYNC_WINDOWS·N)
_I1, _I2 = 4, 5  # t mod P and 2t mod P (phasor table indices of the newest sample)
_O1, _O2 = 6, 7  # the same for the sample leaving the window (t − N)
_SLOT = 8  # t mod N (ring slot)
_N = 9  # window length
_NSEC = 10  # first-order sections per chain
_OFF_COEF, _OFF_CST, _OFF_RING, _OFF_PH, _OFF_ACC, _OFF_ONE, _OFF_WORK = 11, 12, 13, 14, 15, 16, 17
_K0, _OFF_LB, _OFF_LBC = 18, 19, 20  # exact low band: bins, states, constants
_NIB = 21  # then: one window end (a pushed sample's)
# Float state (float64 array ``fb``), scalars first:
_DC_R = 0  # DC blocker pole
_DCX_IN, _DCX_OUT, _DCY_IN, _DCY_OUT = 1, 2, 3, 4  # previous input and output per signal
_ZPREV_RE, _ZPREV_IM = 5, 6  # previous analytic target sample
_PEAK = 7  # running peak level
_ABS, _REL = 8, 9
_FS = 10
_WSQ = 11  # Σ w_n²
_M = 12  # FFT length of the exact FEI
_W1 = 13  # Σ w_n
_WP = 14  # Σ (−1)^n w_n
_X0, _Y0 = 15, 16  # first samples (subtracted from the raw signals against round-off)
_HP = 17  # high-pass before the Hilbert pair: 2 biquads (b0 b1 b2 a1 a2) × 2, then states
_HPS = _HP + 10  # transposed direct-form II states: section j, signal s → _HPS + 4 j + 2 s
_NST = _HPS + 8
# then: section coefficients (nsec, 4) and states (nsec, 2, 4: previous input, previous
# output) of the four chains (x I, x Q, y I, y Q); the ring (N, _NRING) of per-sample
# quantities; the phasor table (P, 2); the sliding sums (_NACC); the row of the last pushed
# window (6) and its work column (_NWORK + 2); the low band's states (4, 6, K0) and constants
# (LB_CONST_ROWS, K0) (:mod:`rths_hil.fei.sliding`).
#
# Sliding sums: each real quantity q has Σ q and Σ q e^{jΩt'}, Σ q e^{j2Ωt'} over the window,
# stored (5, 8): component c (Σq, Re/Im m = 1, Re/Im m = 2) of quantity i at 8c + i; running
# sums at 0, fresh sums at 40. The complex q₁ = z_o conj(z_I) has m = −2 … 2 (re/im):
# running at 80, fresh at 90.
_Q2, _Q3 = 0, 1  # |z_I|², Im(conj(z_I[n−1]) z_I[n])
_YX, _XX, _XR, _YR = 2, 3, 4, 5  # raw (mean-free by first sample) ŷx̂, x̂², x̂, ŷ
_SX, _SY = 6, 7  # (−1)^t x̂, (−1)^t ŷ (m = 0, 1 used)
_NREAL = 8
_Q1 = 80  # q₁: re/im for m = −2, −1, 0, 1, 2 (fresh: + 10)
_NACC = 100
_NRING = 10  # ring slot: the eight real quantities, then q₁ (re, im)
# Per-window work rows (pass 1 → pass 2): Re S, Im S, E, F (analytic), exact Re S, exact E,
# the exact low band's E, F, Re S, Im S (bins 1 … K0), and the window means of the raw
# target and measured samples.
_NWORK = 12

# fastmath "contract" only (fused multiply-adds); error_model "numpy": 1/0 gives inf, no raise.
_JIT: JitOptions = {"cache": True, "nogil": True, "error_model": "numpy", "fastmath": {"contract"}}


@numba.njit(inline="always", **_JIT)
def _wrap(i: int, P: int) -> int:
    if i >= P:
        return i - P
    return i


@numba.njit(inline="always", **_JIT)
def _dc_highpass(fb, s, u):
    """DC blocker and Butterworth high-pass of signal ``s`` (0 target, 1 measured), one sample."""
    i_in = _DCX_IN + 2 * s
    i_out = _DCX_OUT + 2 * s
    # DC blocker (first-order high-pass): o[n] = u[n] − u[n−1] + r o[n−1]
    o = (u - fb[i_in]) + fb[_DC_R] * fb[i_out]
    fb[i_in] = u
    fb[i_out] = o
    # Butterworth high-pass, two second-order sections in transposed direct form II
    # (as scipy.signal.sosfilt)
    for j in range(2):
        c = _HP + 5 * j
        z = _HPS + 4 * j + 2 * s
        h = fb[c] * o + fb[z]  # y[n] = b0 u[n] + z1
        fb[z] = (fb[c + 1] * o - fb[c + 3] * h) + fb[z + 1]  # z1 ← b1 u[n] − a1 y[n] + z2
        fb[z + 1] = fb[c + 2] * o - fb[c + 4] * h  # z2 ← b2 u[n] − a2 y[n]
        o = h
    return o


@numba.njit(inline="always", **_JIT)
def _allpass_chain(coef, cst, c, v):
    """Chain ``c`` of first-order all-pass sections H(z) = (a + z⁻¹)/(1 + a z⁻¹), one sample."""
    for j in range(coef.shape[0]):
        out = coef[j, c] * (v - cst[j, 1, c]) + cst[j, 0, c]  # y[n] = a (u[n] − y[n−1]) + u[n−1]
        cst[j, 0, c] = v
        cst[j, 1, c] = out
        v = out
    return v


@numba.njit(inline="always", **_JIT)
def _slide_real(run, fresh, ring, slot, q, fn, fo, fresh_on, resync):
    """Slide the sums of the eight real quantities by one sample.

    ``q``: the new sample's quantities (8-tuple); the leaving sample's are ``ring[slot, 0:8]``
    (replaced by ``q``). ``fn``, ``fo``: the factors (1, cos Ωt', sin Ωt', cos 2Ωt', sin 2Ωt')
    of the new and the leaving sample. ``fresh_on``: the last window of a resync period (the
    fresh sums add too); ``resync``: its last sample (the running sums become the fresh ones,
    which restart at 0).
    """
    for i in range(_NREAL):
        qo = ring[slot, i]
        qn = q[i]
        ring[slot, i] = qn
        for c in range(5):
            u = qn * fn[c]
            s = (run[c, i] + u) - qo * fo[c]  # Σ q f ← Σ q f + q[t] f(t) − q[t−N] f(t−N)
            if fresh_on:
                f = fresh[c, i] + u  # fresh: additions only over the last window
                if resync:
                    s = f
                    f = 0.0
                fresh[c, i] = f
            run[c, i] = s


@numba.njit(inline="always", **_JIT)
def _cplx_sum(a0, a1, b, qr, qi, pr, pi, orr, oi, rr, ri, fr):
    """Add q·p to the running sums at offset ``b`` and remove o·r (complex products); with
    ``fr`` add q·p to the fresh sums too."""
    ur = qr * pr - qi * pi
    ui = qr * pi + qi * pr
    a0[b] = a0[b] + ur - (orr * rr - oi * ri)  # Σ q₁ e^{jmΩt'} ← … + q₁[t] p − q₁[t−N] r
    a0[b + 1] = a0[b + 1] + ui - (orr * ri + oi * rr)
    if fr:
        a1[b] += ur
        a1[b + 1] += ui


@numba.njit(inline="always", **_JIT)
def _hann2(run, i, c1r, c1i, c2r, c2i):
    """Σ_n w_n² q_i over the window: ⅜ Σq − ½ Re(c₁ Σ q e^{jΩt'}) + ⅛ Re(c₂ Σ q e^{j2Ωt'})."""
    return (0.375 * run[0, i] - 0.5 * (c1r * run[1, i] - c1i * run[2, i])) + 0.125 * (
        c2r * run[3, i] - c2i * run[4, i]
    )


@numba.njit(inline="always", **_JIT)
def _hann1(run, i, c1r, c1i):
    """Σ_n w_n q_i over the window: ½ Σq − ½ Re(c₁ Σ q e^{jΩt'})."""
    return 0.5 * run[0, i] - 0.5 * (c1r * run[1, i] - c1i * run[2, i])


@numba.njit(inline="always", **_JIT)
def _window_sums(t, N, run, a, p1r, p1i, p2r, p2i, w2, sum_w, alt_w, Mf):
    """(Re S, Im S, E, F, exact Re S, exact E, means) of the window ending at sample ``t``.

    ``run``: the sliding sums of the real quantities (5 × 8); ``a``: those of q₁.
    """
    # n = t' − s0 (s0 = t − N + 1): e^{jmΩn} = e^{jmΩt'} e^{−jmΩ s0}, and
    # e^{−jΩ s0} = e^{jΩ(N−1−t)} = conj(phasor of t) = c₁ (Ω(N − 1) = 2π).
    c1r = p1r
    c1i = -p1i
    c2r = p2r
    c2i = -p2i
    # S_a = Σ w² q₁, w² = ⅜ − ¼(e^{jΩn} + e^{−jΩn}) + 1/16 (e^{j2Ωn} + e^{−j2Ωn})
    s_re = (
        0.375 * a[4]
        - 0.25 * ((c1r * a[6] - c1i * a[7]) + (p1r * a[2] - p1i * a[3]))
        + 0.0625 * ((c2r * a[8] - c2i * a[9]) + (p2r * a[0] - p2i * a[1]))
    )
    s_im = (
        0.375 * a[5]
        - 0.25 * ((c1r * a[7] + c1i * a[6]) + (p1r * a[3] + p1i * a[2]))
        + 0.0625 * ((c2r * a[9] + c2i * a[8]) + (p2r * a[1] + p2i * a[0]))
    )
    E = _hann2(run, _Q2, c1r, c1i, c2r, c2i)  # E_a = Σ w² |z_I|²
    F = _hann2(run, _Q3, c1r, c1i, c2r, c2i)  # F_a = Σ w² Im(conj(z_I[n−1]) z_I[n])
    # Exact Re S and E of the windowed, mean-free signals (Parseval, one-sided bins 1 … p−1):
    # Σ_k Y conj(X) over all M bins = M Σ ŷ x̂; remove DC (k = 0) and Nyquist (k = p), halve.
    inv_n = 1.0 / N
    mu_x = run[0, _XR] * inv_n  # window means (of the samples less the first sample)
    mu_y = run[0, _YR] * inv_n
    yx2 = _hann2(run, _YX, c1r, c1i, c2r, c2i)  # Σ w² ŷ x̂
    xx2 = _hann2(run, _XX, c1r, c1i, c2r, c2i)  # Σ w² x̂²
    x2 = _hann2(run, _XR, c1r, c1i, c2r, c2i)  # Σ w² x̂
    y2 = _hann2(run, _YR, c1r, c1i, c2r, c2i)  # Σ w² ŷ
    x1 = _hann1(run, _XR, c1r, c1i)  # Σ w x̂
    y1 = _hann1(run, _YR, c1r, c1i)
    sx1 = _hann1(run, _SX, c1r, c1i)  # Σ w (−1)^t' x̂
    sy1 = _hann1(run, _SY, c1r, c1i)
    sxy = yx2 - mu_x * y2 - mu_y * x2 + mu_x * mu_y * w2  # Σ w² (ŷ − μ_y)(x̂ − μ_x)
    sxx = xx2 - 2.0 * mu_x * x2 + mu_x * mu_x * w2  # Σ w² (x̂ − μ_x)²
    x_dc = x1 - mu_x * sum_w  # X at k = 0
    y_dc = y1 - mu_y * sum_w
    s0_sign = 1.0 if ((t - N + 1) & 1) == 0 else -1.0  # (−1)^n = (−1)^t' (−1)^s0
    x_ny = s0_sign * sx1 - mu_x * alt_w  # X at k = p (Nyquist)
    y_ny = s0_sign * sy1 - mu_y * alt_w
    re_s = 0.5 * (Mf * sxy - y_dc * x_dc - y_ny * x_ny)
    e_ex = 0.5 * (Mf * sxx - x_dc * x_dc - x_ny * x_ny)
    return s_re, s_im, E, F, re_s, e_ex, mu_x, mu_y


@numba.njit(**_JIT)
def _pass1(xs, ys, fb, ib, work, out_t):
    """Filters, sliding sums and the exact low band for a block, one sample at a time.

    Each completed window: its end index into ``out_t``, its sums and means into the columns
    of ``work``. All state is in ``fb`` and ``ib`` (views below; each array argument costs a
    pushed sample ~0.2 µs). Returns the number of completed windows.
    """
    N = ib[_N]
    ns = ib[_NSEC]
    P = N - 1
    K0 = ib[_K0]
    coef = fb[ib[_OFF_COEF] : ib[_OFF_COEF] + 4 * ns].reshape((ns, 4))
    cst = fb[ib[_OFF_CST] : ib[_OFF_CST] + 8 * ns].reshape((ns, 2, 4))
    ring = fb[ib[_OFF_RING] : ib[_OFF_RING] + _NRING * N].reshape((N, _NRING))
    ph = fb[ib[_OFF_PH] : ib[_OFF_PH] + 2 * P].reshape((P, 2))
    acc = fb[ib[_OFF_ACC] : ib[_OFF_ACC] + _NACC]
    run = acc[0:40].reshape((5, _NREAL))  # real quantities: running sums
    fresh = acc[40:80].reshape((5, _NREAL))  # real quantities: fresh sums
    a0 = acc[_Q1 : _Q1 + 10]  # q₁: running sums
    a1 = acc[_Q1 + 10 : _Q1 + 20]  # q₁: fresh sums
    lb = fb[ib[_OFF_LB] : ib[_OFF_LB] + 24 * K0].reshape((4, 6, K0))
    lbc = fb[ib[_OFF_LBC] : ib[_OFF_LBC] + LB_CONST_ROWS * K0].reshape((LB_CONST_ROWS, K0))
    n = xs.shape[0]
    t = ib[_T]
    if n > 0 and t == 0:  # start the DC blockers at the first value: no step transient
        fb[_DCX_IN] = xs[0]
        fb[_DCY_IN] = ys[0]
        fb[_X0] = xs[0]
        fb[_Y0] = ys[0]
    next_end = ib[_NEXT_END]
    hop = ib[_HOP]
    rpos = ib[_RPOS]  # t mod the resync period
    period = LB_RESYNC_WINDOWS * N
    fresh_from = period - N
    i1 = ib[_I1]
    i2 = ib[_I2]
    # phasors e^{jΩt'}, e^{j2Ωt'} of the sample leaving the window (t' = t − N ≡ t − 1 mod P)
    o1i = ib[_O1]
    o2i = ib[_O2]
    q1r_prev, q1i_prev = ph[o1i, 0], ph[o1i, 1]
    q2r_prev, q2i_prev = ph[o2i, 0], ph[o2i, 1]
    slot = ib[_SLOT]
    zpr = fb[_ZPREV_RE]
    zpi = fb[_ZPREV_IM]
    x0 = fb[_X0]
    y0 = fb[_Y0]
    w2 = fb[_WSQ]
    sum_w = fb[_W1]
    alt_w = fb[_WP]
    Mf = fb[_M]
    nout = 0
    for k in range(n):
        x = xs[k]
        y = ys[k]
        # Analytic signals z = I + jQ: DC blocker, high-pass, then the all-pass pair.
        ux = _dc_highpass(fb, 0, x)
        uy = _dc_highpass(fb, 1, y)
        v0 = _allpass_chain(coef, cst, 0, ux)  # x, in-phase
        v1 = _allpass_chain(coef, cst, 1, ux)  # x, quadrature (90° behind)
        v2 = _allpass_chain(coef, cst, 2, uy)  # y, in-phase
        v3 = _allpass_chain(coef, cst, 3, uy)  # y, quadrature
        # q₁ = z_y conj(z_x), q₂ = |z_x|², q₃ = Im(conj(z_x[t−1]) z_x[t])
        q1r = v2 * v0 + v3 * v1
        q1i = v3 * v0 - v2 * v1
        q2 = v0 * v0 + v1 * v1
        q3 = zpr * v1 - zpi * v0
        zpr = v0
        zpi = v1
        # Raw (mean-free per window, exactly as the exact FEI) quantities for Re S and E.
        xr = x - x0
        yr = y - y0
        sgn = 1.0 if (t & 1) == 0 else -1.0
        # The sample leaving the window (zeros in the ring before the first N samples).
        xo = ring[slot, _XR]
        yo = ring[slot, _YR]
        o_q1r = ring[slot, 8]
        o_q1i = ring[slot, 9]
        ring[slot, 8] = q1r
        ring[slot, 9] = q1i
        p1r = ph[i1, 0]  # e^{jΩt}
        p1i = ph[i1, 1]
        p2r = ph[i2, 0]  # e^{j2Ωt}
        p2i = ph[i2, 1]
        # the leaving sample's phasors are the previous sample's: Ω(N − 1) = 2π
        r1r, r1i, r2r, r2i = q1r_prev, q1i_prev, q2r_prev, q2i_prev
        q1r_prev, q1i_prev, q2r_prev, q2i_prev = p1r, p1i, p2r, p2i
        # Sliding sums Σ q e^{jmΩt'} over the window, and the fresh sums.
        fr = rpos >= fresh_from
        resync = rpos == period - 1
        _slide_real(
            run,
            fresh,
            ring,
            slot,
            (q2, q3, yr * xr, xr * xr, xr, yr, sgn * xr, sgn * yr),
            (1.0, p1r, p1i, p2r, p2i),
            (1.0, r1r, r1i, r2r, r2i),
            fr,
            resync,
        )
        _cplx_sum(a0, a1, 0, q1r, q1i, p2r, -p2i, o_q1r, o_q1i, r2r, -r2i, fr)  # m = −2
        _cplx_sum(a0, a1, 2, q1r, q1i, p1r, -p1i, o_q1r, o_q1i, r1r, -r1i, fr)  # m = −1
        a0[4] = a0[4] + q1r - o_q1r  # m = 0
        a0[5] = a0[5] + q1i - o_q1i
        if fr:
            a1[4] += q1r
            a1[5] += q1i
        _cplx_sum(a0, a1, 6, q1r, q1i, p1r, p1i, o_q1r, o_q1i, r1r, r1i, fr)  # m = 1
        _cplx_sum(a0, a1, 8, q1r, q1i, p2r, p2i, o_q1r, o_q1i, r2r, r2i, fr)  # m = 2
        # Resynchronise: the fresh sums hold exactly the current window after N additions.
        if resync:
            for i in range(10):
                a0[i] = a1[i]
                a1[i] = 0.0
        if K0 > 0:  # exact low band: sliding DFTs of the raw samples
            lowband_step(lb, lbc, xr, yr, xo, yo, fr)
        if t == next_end:
            next_end += hop
            s_re, s_im, E, F, re_s, e_ex, mu_x, mu_y = _window_sums(
                t, N, run, a0, p1r, p1i, p2r, p2i, w2, sum_w, alt_w, Mf
            )
            work[0, nout] = s_re
            work[1, nout] = s_im
            work[2, nout] = E
            work[3, nout] = F
            work[4, nout] = re_s
            work[5, nout] = e_ex
            lo_e, lo_f, lo_sr, lo_si = 0.0, 0.0, 0.0, 0.0
            if K0 > 0:
                lo_e, lo_f, lo_sr, lo_si = lowband_window(lb, lbc, mu_x, mu_y)
            work[6, nout] = lo_e  # the low band's E, F, Re S, Im S
            work[7, nout] = lo_f
            work[8, nout] = lo_sr
            work[9, nout] = lo_si
            work[10, nout] = mu_x  # window means of the raw samples
            work[11, nout] = mu_y
            out_t[nout] = t
            nout += 1
        if resync and K0 > 0:
            lowband_swap(lb)
        slot += 1
        if slot == N:
            slot = 0
        i1 = _wrap(i1 + 1, P)
        i2 = _wrap(i2 + 2, P)
        t += 1
        rpos += 1
        if rpos == period:
            rpos = 0
    ib[_T] = t
    ib[_NEXT_END] = next_end
    ib[_RPOS] = rpos
    ib[_I1] = i1
    ib[_I2] = i2
    ib[_O1] = _wrap(i1 + P - 1, P)
    ib[_O2] = _wrap(i2 + P - 2, P)
    ib[_SLOT] = slot
    fb[_ZPREV_RE] = zpr
    fb[_ZPREV_IM] = zpi
    return nout


@numba.njit(**_JIT)
def _pass2(fb, work, out, n, angles):
    """Estimates of ``n`` windows from their sums in ``work`` → columns of ``out``.

    Rows of ``out``: A, φ, f_eq, d, valid, level. With ``angles`` false, rows 1 and 3 receive
    Re S/E and Im S/E instead of φ and d (the caller takes a vectorised atan2).
    """
    Mw2 = fb[_M] * fb[_WSQ]
    fs = fb[_FS]
    bin_hz = fs / fb[_M]
    two_pi = 2.0 * math.pi
    # Independent per window (no branches: the divisions and roots of many windows overlap).
    # S = exact Re S + j(exact low-band Im S + E_high · Im(S_a/E_a)), E exact,
    # F = exact low-band F + E_high · (F_a/E_a), E_high = E − E_low.
    f_hz = fs / two_pi
    inv_mw2 = 2.0 / Mw2
    for i in range(n):
        inv_e = 1.0 / work[2, i]  # analytic E
        e_ex = work[5, i]
        inv_ex = 1.0 / e_ex
        e_hi = max(e_ex - work[6, i], 0.0)
        im_s = work[9, i] + e_hi * (work[1, i] * inv_e)
        a_re = work[4, i] * inv_ex
        a_im = im_s * inv_ex
        out[0, i] = math.sqrt(a_re * a_re + a_im * a_im)
        out[1, i] = a_re
        out[2, i] = (bin_hz * work[7, i] + e_hi * f_hz * work[3, i] * inv_e) * inv_ex
        out[3, i] = a_im
        out[5, i] = math.sqrt(max(e_ex * inv_mw2, 0.0))
    # Running peak and validity (sequential, cheap).
    peak = fb[_PEAK]
    abs_floor = fb[_ABS]
    rel_floor = fb[_REL]
    for i in range(n):
        level = out[5, i]
        if level > peak:
            peak = level
        f_eq = out[2, i]
        valid = (
            level > abs_floor
            and level >= rel_floor * peak
            and work[2, i] > 0
            and f_eq > 0
            and math.isfinite(f_eq)
            and work[5, i] > 0
        )
        if valid:
            out[4, i] = 1.0
            amp = out[0, i]
            if not 1e-150 < amp < 1e150:  # |·| by hypot where the squares could over/underflow
                amp = math.hypot(out[1, i], out[3, i])
                out[0, i] = amp
            if angles:
                phase = math.atan2(out[3, i], out[1, i])
                out[1, i] = phase
                out[3, i] = -phase / (two_pi * f_eq)
        else:
            out[0, i] = math.nan
            out[1, i] = math.nan
            out[2, i] = math.nan
            out[3, i] = math.nan
            out[4, i] = 0.0
    fb[_PEAK] = peak


@numba.njit(**_JIT)
def _stream_block(xs, ys, fb, ib, work, out, out_t):
    """Process a block; completed windows → columns of ``out`` (φ, d: see :func:`_pass2`)."""
    n = _pass1(xs, ys, fb, ib, work, out_t)
    _pass2(fb, work, out, n, False)
    return n


@numba.njit(**_JIT)
def _stream_one(x, y, fb, ib):
    """Process one sample pair; return 1 when a window completed (its row: ``fb`` at _OFF_ONE)."""
    w = ib[_OFF_WORK]
    o = ib[_OFF_ONE]
    xy = fb[w + _NWORK : w + _NWORK + 2]
    xy[0] = x
    xy[1] = y
    work = fb[w : w + _NWORK].reshape((_NWORK, 1))
    n = _pass1(xy[0:1], xy[1:2], fb, ib, work, ib[_NIB : _NIB + 1])
    _pass2(fb, work, fb[o : o + 6].reshape((6, 1)), n, True)
    return n


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
    exact_band : float, optional
        Bins below ``exact_band`` cycles per window are evaluated exactly by sliding DFTs
        (default :data:`EXACT_BAND`); 0 takes the whole quadrature part from the analytic
        signals.

    References
    ----------
    The FEI paper, Eq. 2.1–2.5; E. Jacobsen and R. Lyons, "The sliding DFT", IEEE Signal
    Processing Magazine 20(2), 2003; H. J. Orchard, "Synthesis of wideband two-phase networks",
    Wireless Engineer 27, 1950; E. Bedrosian, "A product theorem for Hilbert transforms",
    Proc. IEEE 51(5), 1963.
    """

    def __init__(
        self,
        fs: float,
        N: int,
        hop: int,
        abs_floor: float,
        rel_floor: float,
        exact_band: float = EXACT_BAND,
    ) -> None:
        self.fs = float(fs)
        self.N = int(N)
        self.hop = int(hop)
        M = 1 << (self.N - 1).bit_length()
        if not (math.isfinite(exact_band) and exact_band >= 0):
            raise ValueError(f"exact_band must be ≥ 0, got {exact_band!r}")
        #: bins 1 … K0 (below ``exact_band`` cycles per window, rounded up to a multiple of 8
        #: bins: 24–40 bins at the default band whatever N) are evaluated exactly
        k0 = 8 * math.ceil(math.ceil(exact_band * M / self.N) / 8)
        self.K0 = min(M // 2 - 1, k0) if exact_band > 0 else 0
        #: the exact band actually used (cycles per window)
        self.exact_band = self.K0 * self.N / M
        window_s = N / fs
        # With an exact low band the analytic signals only need the band above it.
        f_lo = min(max(0.25, 0.5 * self.exact_band) / window_s, 0.01 * fs)
        f_hi = min(0.45 * fs, max(F_HI_MAX, 40.0 * f_lo))
        self.a_i, self.a_q, self.phase_error_deg = hilbert_pair(f_lo, f_hi, self.fs)
        self.band = (f_lo, f_hi)
        self.dc_corner = 0.1 / window_s
        N = self.N
        P = N - 1
        ns = self.a_i.size
        sizes = {
            "st": _NST,
            "coef": 4 * ns,
            "cst": 8 * ns,
            "ring": _NRING * N,
            "ph": 2 * P,
            "acc": _NACC,
            "one": 6,
            "work": _NWORK + 2,
            "lb": 24 * self.K0,
            "lbc": LB_CONST_ROWS * self.K0,
        }
        off = np.cumsum([0, *sizes.values()])
        self._fb = fb = np.zeros(int(off[-1]))
        self._ib = ib = np.zeros(_NIB + 1, dtype=np.int64)
        views = {name: fb[off[i] : off[i + 1]] for i, name in enumerate(sizes)}
        for slot, name in (
            (_OFF_COEF, "coef"),
            (_OFF_CST, "cst"),
            (_OFF_RING, "ring"),
            (_OFF_PH, "ph"),
            (_OFF_ACC, "acc"),
            (_OFF_ONE, "one"),
            (_OFF_WORK, "work"),
            (_OFF_LB, "lb"),
            (_OFF_LBC, "lbc"),
        ):
            ib[slot] = off[list(sizes).index(name)]
        ib[_N] = N
        ib[_NSEC] = ns
        ib[_K0] = self.K0
        if self.K0:
            views["lbc"][:] = lowband_constants(N, self.K0).ravel()
        ib[_NEXT_END] = N - 1
        ib[_HOP] = self.hop
        ib[_O1] = (-N) % P
        ib[_O2] = (-2 * N) % P
        st = views["st"]
        st[_DC_R] = math.exp(-2 * math.pi * self.dc_corner / self.fs)
        #: corner of the high-pass before the Hilbert pair (Hz), 0.8 × the exact band's edge
        self.hp_corner = min(0.8 * self.exact_band / window_s, 0.2 * self.fs) if self.K0 else 0.0
        if self.K0:
            sos = butter(4, self.hp_corner, "highpass", fs=self.fs, output="sos")
            st[_HP : _HP + 10] = np.column_stack([sos[:, :3], sos[:, 4:]]).ravel()
        else:  # no exact band: the two sections pass the signal unchanged
            st[_HP : _HP + 10] = [1.0, 0.0, 0.0, 0.0, 0.0] * 2
        st[_ABS] = abs_floor
        st[_REL] = rel_floor
        st[_FS] = self.fs
        w = np.hanning(N)
        st[_WSQ] = float(w @ w)
        st[_W1] = float(w.sum())
        st[_WP] = float(w @ ((-1.0) ** np.arange(N)))
        st[_M] = float(1 << (N - 1).bit_length())
        views["coef"][:] = np.column_stack([self.a_i, self.a_q, self.a_i, self.a_q]).ravel()
        phasor = np.exp(1j * 2 * np.pi * np.arange(P) / P)
        views["ph"][:] = np.column_stack([phasor.real, phasor.imag]).ravel()
        self._one = views["one"]
        self._work = np.empty((_NWORK, 1))
        self._out = np.empty((6, 1))
        self._out_t = np.empty(1, dtype=np.int64)

    def process(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Push blocks; return (rows of A, φ, f_eq, d, valid, level; window-end indices).

        The rows are a view (each column contiguous) that the next call overwrites.
        """
        nmax = x.shape[0] // self.hop + 1
        if self._out.shape[1] < nmax:
            self._work = np.empty((_NWORK, nmax))
            self._out = np.empty((6, nmax))
            self._out_t = np.empty(nmax, dtype=np.int64)
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        n = _stream_block(x, y, self._fb, self._ib, self._work, self._out, self._out_t)
        out = self._out[:, :n]
        np.arctan2(out[3], out[1], out=out[1])  # φ (the kernel left Re, Im of S/E)
        np.divide(out[1], out[2] * (-2.0 * math.pi), out=out[3])  # d = −φ/(2π f_eq)
        return out.T, self._out_t[:n]

    def push(self, x: float, y: float) -> bool:
        """Push one sample pair; True when a window completed (its row: :attr:`last`)."""
        return _stream_one(x, y, self._fb, self._ib) > 0

    @property
    def last(self) -> np.ndarray:
        """Row (A, φ, f_eq, d, valid, level) of the window completed by the last :meth:`push`."""
        return self._one

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
  period ``N − 1``. Against round-off drift the sums are resynchronised once every
  ``LB_RESYNC_WINDOWS`` windows (at stream positions) by swapping in a second set of sums that
  was built by additions only over exactly the current window (no O(N) step, no spikes).

Both signals pass through identical filters, so their relative phase is untouched; the common
group delay of the all-pass chains shifts the window's effective position slightly into the past
(documented in ``docs/fei.md``).

Implementation (for speed; the arithmetic of each quantity is fixed by the source order and
the stream position, no re-association, so results do not depend on how the stream is cut into
blocks): a block is processed in sub-blocks of ``LB_SUB`` samples. Per sub-block, the recursive
filters (DC blockers, high-pass, all-pass chains) run first with their states in vector
registers (:func:`_filter_block`, generated per section count); then the sliding sums run
sample by sample and, at each window end, reduce to the window's sums (S, E, F, the exact Re S
and E, the means); then the exact low band runs over the sub-block bin chunk by bin chunk
(:func:`rths_hil.fei_sliding.lowband_block`). A second pass turns the sums into A, f_eq,
validity and level for all windows of the block at once (independent iterations, so divisions
and square roots overlap). The phase ``atan2`` of a block is taken by numpy (vectorised); a
single pushed sample takes it from libm (the two agree to an ulp). All state lives in one float
and one integer array, so a pushed sample costs one short call.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from scipy.signal import butter
from scipy.special import ellipj, ellipk

from .fei_sliding import (
    LB_CONST_ROWS,
    LB_RESYNC_WINDOWS,
    LB_STATE_ROWS,
    LB_SUB,
    _vec_tools,
    lowband_block,
    lowband_constants,
    lowband_padded,
)

#: Target worst-case phase-difference error of the Hilbert pair (degrees).
MAX_PHASE_ERROR_DEG = 0.01
#: Width of the exact low band in cycles per window: bins below ``EXACT_BAND / t_w`` are
#: evaluated exactly by sliding DFTs (:mod:`rths_hil.fei_sliding`); only the rest of the
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
_K0, _OFF_LB, _OFF_LBC = 18, 19, 20  # exact low band: K0p (K0 padded to 8), states, constants
_OFF_SV, _OFF_ACCS = 21, 22  # sub-block scratch: per-sample values, low-band window partials
_NIB = 23  # then: one window end (a pushed sample's), LB_SUB window indices (low-band scratch)
# Float state (float64 array ``fb``), scalars first:
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
_HP = 17  # high-pass before the Hilbert pair: 2 biquads (b0 b1 b2 a1 a2) × 2, then states
_HPS = _HP + 10  # transposed direct-form II states: section j, signal s → _HPS + 4 j + 2 s
_NST = _HPS + 8
# then: section coefficients (nsec, 4) and states (nsec, 2, 4) of the four chains (x I, x Q,
# y I, y Q); the ring (N, _NRING) of per-sample quantities; the phasor table (P, 2); the
# sliding sums (2, _NACC) (running, fresh); the row of the last pushed window (6) and its work
# column (_NWORK).
#
# Sliding sums: each quantity q has Σ q (one real) and Σ q e^{jΩt}, Σ q e^{j2Ωt} (two complex).
# The eight real quantities (_Q2 … _SY) are stored component-major, (5, 8): component c
# (Σq, Re/Im m = 1, Re/Im m = 2) of quantity i at 8c + i, so that one component of all eight
# is one 8-wide vector; running sums at 0, fresh sums at 40. The complex q₁ = z_o conj(z_I) has
# m = −2 … 2 (ten reals, re/im): running at 80, fresh at 90.
_Q2, _Q3 = 0, 1  # |z_I|², Im(conj(z_I[n−1]) z_I[n])
_YX, _XX, _XR, _YR = 2, 3, 4, 5  # raw (mean-free by first sample) ŷx̂, x̂², x̂, ŷ
_SX, _SY = 6, 7  # (−1)^t x̂, (−1)^t ŷ (m = 0, 1 used)
_NREAL = 8
_Q1 = 80  # q₁: re/im for m = −2, −1, 0, 1, 2 (fresh: + 10)
_NACC = 100
_NRING = 10  # ring slot: the eight real quantities, then q₁ (re, im)
# Per-window work rows (pass 1 → pass 2): Re S, Im S, E, F (analytic), exact Re S, exact E,
# the exact low band's E, F, Re S, Im S (bins 1 … K0), and the window means of the raw
# target and measured samples (read by the low band).
_NWORK = 12

_JIT = {"cache": True, "nogil": True, "error_model": "numpy", "fastmath": {"contract"}}


@numba.njit(inline="always", **_JIT)
def _wrap(i: int, P: int) -> int:
    if i >= P:
        return i - P
    return i


@intrinsic
def _real_sums(typingctx, fb, a0, ring, q, p, r, fresh_on, resync):  # pragma: no cover
    """Sliding sums of the eight real quantities (one 8-wide vector per component) and their
    Hann-weighted window sums.

    ``q``: the new sample's quantities (8-tuple); ``p``, ``r``: (Re, Im) of the phasors e^{jΩt},
    e^{j2Ωt} of the new sample and of the one leaving the window (4-tuples). The old quantities
    are read from ``fb[ring:ring + 8]`` and replaced by ``q``. For each component c with phasor
    factor p_c (1 for Σq): running ``s = (s + q_i p_c) − o_i r_c`` (the product o_i r_c fused),
    with ``fresh_on`` (the last window of a resync period) fresh ``f += q_i p_c``, and with
    ``resync`` (its last sample) the running sums become the fresh ones, which restart at 0.
    Returns Σ w² q for quantities 0 … 5, Σ w q for 4 … 7 and Σ q for 4, 5 over the window
    ending at the new sample:
    Σ w² q = ⅜ Σq − ½ Re(c₁ Σ q e^{jΩt}) + ⅛ Re(c₂ Σ q e^{j2Ωt}), Σ w q = ½ Σq − ½ Re(c₁ …).
    """
    ret = types.UniTuple(types.float64, 12)
    sig = ret(fb, a0, ring, q, p, r, fresh_on, resync)

    def codegen(context, builder, signature, args):
        fbv, a0o, ro, qt, pt, rt, fr, rs = args
        base = context.make_array(signature.args[0])(context, builder, fbv).data
        vty, splat, _load, _store, fmadd = _vec_tools(context, builder)
        i32 = ir.IntType(32)
        i64 = ir.IntType(64)

        def vptr(off):
            return builder.bitcast(builder.gep(base, [off]), vty.as_pointer())

        qv = ir.Constant(vty, ir.Undefined)
        for i in range(8):
            qv = builder.insert_element(qv, builder.extract_value(qt, i), ir.Constant(i32, i))
        rp = vptr(ro)
        ov = builder.load(rp, align=8)
        builder.store(qv, rp, align=8)
        neg_ov = builder.fneg(ov)
        zero = ir.Constant(vty, [0.0] * 8)
        slots, us = [], []
        for c in range(5):
            if c == 0:
                u = qv
            else:
                u = builder.fmul(qv, splat(builder.extract_value(pt, c - 1)))
            p0 = vptr(builder.add(a0o, ir.Constant(i64, 8 * c)))
            run = builder.fadd(builder.load(p0, align=8), u)
            if c == 0:
                run = builder.fsub(run, ov)
            else:
                run = fmadd(neg_ov, splat(builder.extract_value(rt, c - 1)), run)
            builder.store(run, p0, align=8)
            slots.append(cgutils.alloca_once_value(builder, run))
            us.append(u)
        with builder.if_then(fr, likely=False):  # the last window of a resync period
            for c in range(5):
                p0 = vptr(builder.add(a0o, ir.Constant(i64, 8 * c)))
                p1 = vptr(builder.add(a0o, ir.Constant(i64, 40 + 8 * c)))
                fresh = builder.fadd(builder.load(p1, align=8), us[c])
                run = builder.select(rs, fresh, builder.load(slots[c]))
                builder.store(run, p0, align=8)
                builder.store(run, slots[c])
                builder.store(builder.select(rs, zero, fresh), p1, align=8)
        A = [builder.load(sl) for sl in slots]
        # Window sums with the conjugate phasors c₁ = conj(p₁), c₂ = conj(p₂) (as _hann2/1).
        c1r = splat(builder.extract_value(pt, 0))
        c1i = splat(builder.fneg(builder.extract_value(pt, 1)))
        c2r = splat(builder.extract_value(pt, 2))
        c2i = splat(builder.fneg(builder.extract_value(pt, 3)))
        re1 = builder.fsub(builder.fmul(c1r, A[1]), builder.fmul(c1i, A[2]))
        re2 = builder.fsub(builder.fmul(c2r, A[3]), builder.fmul(c2i, A[4]))
        h2 = builder.fadd(
            builder.fsub(builder.fmul(splat(0.375), A[0]), builder.fmul(splat(0.5), re1)),
            builder.fmul(splat(0.125), re2),
        )
        h1 = builder.fsub(builder.fmul(splat(0.5), A[0]), builder.fmul(splat(0.5), re1))
        vals = [builder.extract_element(h2, ir.Constant(i32, i)) for i in range(6)]
        vals += [builder.extract_element(h1, ir.Constant(i32, i)) for i in range(4, 8)]
        vals += [builder.extract_element(A[0], ir.Constant(i32, i)) for i in (4, 5)]
        return cgutils.pack_array(builder, vals)

    return sig, codegen


#: Most first-order sections per all-pass chain the filter kernel is generated for.
NS_MAX = 24


@intrinsic
def _filter_block(typingctx, fb, coef, cst, xs, ys, b0, n, sv):  # pragma: no cover
    """DC blockers, high-pass and the four all-pass chains for samples ``b0 … b0+n−1``.

    Writes the chain outputs (x I, x Q, y I, y Q) of sample ``b0 + k`` to ``sv[k, 0:4]``. The
    scalar states live in ``fb`` (offsets _DC_R … _HPS + 7), the chains' coefficients in ``coef``
    (ns × 4) and states in ``cst`` (ns × 2 × 4). The code is generated for each section count
    (1 … NS_MAX, a switch) so that all states stay in registers across the samples: the target
    and measured signals share 2-wide vectors, the four chains one 4-wide vector.
    """
    for a, nd in ((fb, 1), (coef, 2), (cst, 3), (sv, 2)):
        if not (isinstance(a, types.Array) and a.ndim == nd and a.layout == "C"):
            return None
    if not all(isinstance(a, types.Array) and a.ndim == 1 for a in (xs, ys)):
        return None
    sig = types.none(fb, coef, cst, xs, ys, b0, n, sv)

    def codegen(context, builder, signature, args):
        fbv, coefv, cstv, xsv, ysv, _b0, _n, svv = args
        sa = signature.args
        b0v = context.cast(builder, args[5], sa[5], types.intp)
        nv = context.cast(builder, args[6], sa[6], types.intp)
        F = context.make_array(sa[0])(context, builder, fbv)
        C = context.make_array(sa[1])(context, builder, coefv)
        S = context.make_array(sa[2])(context, builder, cstv)
        X = context.make_array(sa[3])(context, builder, xsv)
        Y = context.make_array(sa[4])(context, builder, ysv)
        V = context.make_array(sa[7])(context, builder, svv)
        i64 = nv.type
        i32 = ir.IntType(32)
        dbl = ir.DoubleType()
        v2, v4 = ir.VectorType(dbl, 2), ir.VectorType(dbl, 4)
        fma2 = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(v2, [v2, v2, v2]), "llvm.fma.v2f64"
        )
        fma4 = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(v4, [v4, v4, v4]), "llvm.fma.v4f64"
        )
        ns = cgutils.unpack_tuple(builder, C.shape)[0]
        vcol = cgutils.unpack_tuple(builder, V.shape)[1]

        def c64(v):
            return ir.Constant(i64, v)

        def fptr(i):
            return builder.gep(F.data, [c64(i)])

        def pair(i, j):  # <fb[i], fb[j]>
            v = builder.insert_element(
                ir.Constant(v2, ir.Undefined), builder.load(fptr(i)), ir.Constant(i32, 0)
            )
            return builder.insert_element(v, builder.load(fptr(j)), ir.Constant(i32, 1))

        def store_pair(v, i, j):
            builder.store(builder.extract_element(v, ir.Constant(i32, 0)), fptr(i))
            builder.store(builder.extract_element(v, ir.Constant(i32, 1)), fptr(j))

        def splat2(i):
            return pair(i, i)

        def v4ptr(base, off):
            return builder.bitcast(builder.gep(base, [off]), v4.as_pointer())

        r = splat2(_DC_R)
        dc_in = cgutils.alloca_once_value(builder, pair(_DCX_IN, _DCY_IN))
        dc_out = cgutils.alloca_once_value(builder, pair(_DCX_OUT, _DCY_OUT))
        hp = [[splat2(_HP + 5 * j + i) for i in range(5)] for j in range(2)]
        z1 = [
            cgutils.alloca_once_value(builder, pair(_HPS + 4 * j, _HPS + 4 * j + 2)) for j in (0, 1)
        ]
        z2 = [
            cgutils.alloca_once_value(builder, pair(_HPS + 4 * j + 1, _HPS + 4 * j + 3))
            for j in (0, 1)
        ]
        done = builder.append_basic_block("filters.done")
        default = builder.append_basic_block("filters.default")
        sw = builder.switch(ns, default)
        with builder.goto_block(default):
            builder.branch(done)
        for m in range(1, NS_MAX + 1):
            blk = builder.append_basic_block(f"filters.ns{m}")
            sw.add_case(ir.Constant(ns.type, m), blk)
            with builder.goto_block(blk):
                a = [builder.load(v4ptr(C.data, c64(4 * j)), align=8) for j in range(m)]
                vp = [
                    cgutils.alloca_once_value(
                        builder, builder.load(v4ptr(S.data, c64(8 * j)), align=8)
                    )
                    for j in range(m)
                ]
                op = [
                    cgutils.alloca_once_value(
                        builder, builder.load(v4ptr(S.data, c64(8 * j + 4)), align=8)
                    )
                    for j in range(m)
                ]
                with cgutils.for_range(builder, nv) as loop:
                    k = builder.add(b0v, loop.index)
                    xk = builder.load(cgutils.get_item_pointer(context, builder, sa[3], X, [k]))
                    yk = builder.load(cgutils.get_item_pointer(context, builder, sa[4], Y, [k]))
                    xy = builder.insert_element(
                        ir.Constant(v2, ir.Undefined), xk, ir.Constant(i32, 0)
                    )
                    xy = builder.insert_element(xy, yk, ir.Constant(i32, 1))
                    # DC blocker: o = x − x_prev + r o_prev
                    o = builder.call(
                        fma2, [r, builder.load(dc_out), builder.fsub(xy, builder.load(dc_in))]
                    )
                    builder.store(xy, dc_in)
                    builder.store(o, dc_out)
                    u = o
                    for j in range(2):  # Butterworth high-pass, transposed direct form II
                        b_0, b_1, b_2, a_1, a_2 = hp[j]
                        h = builder.call(fma2, [b_0, u, builder.load(z1[j])])
                        t1 = builder.fsub(builder.fmul(b_1, u), builder.fmul(a_1, h))
                        builder.store(builder.fadd(t1, builder.load(z2[j])), z1[j])
                        builder.store(
                            builder.fsub(builder.fmul(b_2, u), builder.fmul(a_2, h)), z2[j]
                        )
                        u = h
                    mask = ir.Constant(ir.VectorType(i32, 4), [0, 0, 1, 1])
                    v = builder.shuffle_vector(u, ir.Constant(v2, ir.Undefined), mask)
                    for j in range(m):  # o = a (v − o_prev) + v_prev
                        oj = builder.call(
                            fma4,
                            [a[j], builder.fsub(v, builder.load(op[j])), builder.load(vp[j])],
                        )
                        builder.store(v, vp[j])
                        builder.store(oj, op[j])
                        v = oj
                    row = builder.mul(loop.index, vcol)
                    builder.store(v, v4ptr(V.data, row), align=8)
                for j in range(m):
                    builder.store(builder.load(vp[j]), v4ptr(S.data, c64(8 * j)), align=8)
                    builder.store(builder.load(op[j]), v4ptr(S.data, c64(8 * j + 4)), align=8)
                builder.branch(done)
        builder.position_at_end(done)
        store_pair(builder.load(dc_in), _DCX_IN, _DCY_IN)
        store_pair(builder.load(dc_out), _DCX_OUT, _DCY_OUT)
        for j in range(2):
            store_pair(builder.load(z1[j]), _HPS + 4 * j, _HPS + 4 * j + 2)
            store_pair(builder.load(z2[j]), _HPS + 4 * j + 1, _HPS + 4 * j + 3)
        return context.get_dummy_value()

    return sig, codegen


@numba.njit(inline="always", **_JIT)
def _cplx_sum(a0, a1, b, qr, qi, pr, pi, orr, oi, rr, ri, fr):  # pragma: no cover
    """Add q·p to the running sums at offset ``b`` and remove o·r (complex products); with
    ``fr`` add q·p to the fresh sums too."""
    ur = qr * pr - qi * pi
    ui = qr * pi + qi * pr
    a0[b] = a0[b] + ur - (orr * rr - oi * ri)
    a0[b + 1] = a0[b + 1] + ui - (orr * ri + oi * rr)
    if fr:
        a1[b] += ur
        a1[b + 1] += ui


@numba.njit(inline="always", **_JIT)
def _window_sums(t, N, a, h, p1r, p1i, p2r, p2i, w2, sum_w, alt_w, Mf):  # pragma: no cover
    """(Re S, Im S, E, F, exact Re S, exact E, means) of the window ending at sample ``t``.

    ``a``: the sums (q₁ at _Q1); ``h``: the window sums of the real quantities from
    :func:`_real_sums`.
    """
    # Σ_n w_n² q = 3/8 Σq − ½ Σ q cos(Ωn) + ⅛ Σ q cos(2Ωn), n = t' − s0, s0 = t − N + 1:
    # e^{jmΩn} = e^{jmΩt'} e^{−jmΩ s0}, and e^{−jΩ s0} = e^{jΩ(N−1−t)} = conj(phasor of t).
    c1r = p1r
    c1i = -p1i
    c2r = p2r
    c2i = -p2i
    b = 0
    s_re = (
        0.375 * a[b + 4]
        - 0.25 * ((c1r * a[b + 6] - c1i * a[b + 7]) + (p1r * a[b + 2] - p1i * a[b + 3]))
        + 0.0625 * ((c2r * a[b + 8] - c2i * a[b + 9]) + (p2r * a[b] - p2i * a[b + 1]))
    )
    s_im = (
        0.375 * a[b + 5]
        - 0.25 * ((c1r * a[b + 7] + c1i * a[b + 6]) + (p1r * a[b + 3] + p1i * a[b + 2]))
        + 0.0625 * ((c2r * a[b + 9] + c2i * a[b + 8]) + (p2r * a[b + 1] + p2i * a[b]))
    )
    E = h[_Q2]
    F = h[_Q3]
    # Exact Re S and E of the windowed, mean-free signals (Parseval, one-sided bins 1 … p−1):
    # Σ_k Y conj(X) over all M bins = M Σ ŷ x̂; remove DC (k = 0) and Nyquist (k = p), halve.
    inv_n = 1.0 / N  # (a constant: the compiler hoists it out of the sample loop)
    mu_x = h[10] * inv_n
    mu_y = h[11] * inv_n
    yx2 = h[_YX]
    xx2 = h[_XX]
    x2 = h[_XR]
    y2 = h[_YR]
    x1 = h[6]
    y1 = h[7]
    sx1 = h[8]
    sy1 = h[9]
    sxy = yx2 - mu_x * y2 - mu_y * x2 + mu_x * mu_y * w2
    sxx = xx2 - 2.0 * mu_x * x2 + mu_x * mu_x * w2
    x_dc = x1 - mu_x * sum_w
    y_dc = y1 - mu_y * sum_w
    s0_sign = 1.0 if ((t - N + 1) & 1) == 0 else -1.0
    x_ny = s0_sign * sx1 - mu_x * alt_w
    y_ny = s0_sign * sy1 - mu_y * alt_w
    re_s = 0.5 * (Mf * sxy - y_dc * x_dc - y_ny * x_ny)
    e_ex = 0.5 * (Mf * sxx - x_dc * x_dc - x_ny * x_ny)
    return s_re, s_im, E, F, re_s, e_ex, mu_x, mu_y


@numba.njit(**_JIT)
def _pass1(xs, ys, fb, ib, work, out_t):  # pragma: no cover
    """Filters, sliding sums and the exact low band for a block, in sub-blocks of LB_SUB.

    Per sub-block: :func:`_filter_block` (the recursive filters, states in registers), then the
    sliding sums sample by sample (each completed window: its end index into ``out_t``, its sums
    and means into the columns of ``work``), then the low band over the sub-block
    (:func:`rths_hil.fei_sliding.lowband_block`); its scratch lives in ``fb`` and ``ib`` (no
    extra arguments: each array argument costs a pushed sample ~0.2 µs). Returns the number of
    completed windows.
    """
    N = ib[_N]
    ns = ib[_NSEC]
    P = N - 1
    coef = fb[ib[_OFF_COEF] : ib[_OFF_COEF] + 4 * ns].reshape((ns, 4))
    cst = fb[ib[_OFF_CST] : ib[_OFF_CST] + 8 * ns].reshape((ns, 2, 4))
    ring = fb[ib[_OFF_RING] : ib[_OFF_RING] + _NRING * N].reshape((N, _NRING))
    ph = fb[ib[_OFF_PH] : ib[_OFF_PH] + 2 * P].reshape((P, 2))
    off_acc = ib[_OFF_ACC]
    off_ring = ib[_OFF_RING]
    acc = fb[off_acc : off_acc + _NACC]
    a0 = acc[_Q1 : _Q1 + 10]  # q₁: running sums
    a1 = acc[_Q1 + 10 : _Q1 + 20]  # q₁: fresh sums
    K0 = ib[_K0]  # padded to a multiple of 8: K0 // 8 chunks of 8 bins (fei_sliding's layout)
    lb = fb[ib[_OFF_LB] : ib[_OFF_LB] + LB_STATE_ROWS * K0].reshape((K0 // 8, LB_STATE_ROWS, 8))
    lbc = fb[ib[_OFF_LBC] : ib[_OFF_LBC] + LB_CONST_ROWS * K0].reshape((K0 // 8, LB_CONST_ROWS, 8))
    sv = fb[ib[_OFF_SV] : ib[_OFF_SV] + 8 * LB_SUB].reshape((LB_SUB, 8))
    accs = fb[ib[_OFF_ACCS] : ib[_OFF_ACCS] + 32 * LB_SUB].reshape((LB_SUB, 4, 8))
    iscr = ib[_NIB + 1 : _NIB + 1 + LB_SUB]
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
    for b0 in range(0, n, LB_SUB):
        m = min(n - b0, LB_SUB)
        _filter_block(fb, coef, cst, xs, ys, b0, m, sv)
        t_sub = t
        w_sub = nout
        for k in range(m):
            x = xs[b0 + k]
            y = ys[b0 + k]
            # Four all-pass chain outputs: (x, I), (x, Q), (y, I), (y, Q).
            v0 = sv[k, 0]
            v1 = sv[k, 1]
            v2 = sv[k, 2]
            v3 = sv[k, 3]
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
            q_yx = yr * xr
            q_xx = xr * xr
            q_sx = sgn * xr
            q_sy = sgn * yr
            # The sample leaving the window (zeros in the ring before the first N samples).
            row = ring[slot]
            row_off = off_ring + _NRING * slot
            o_q1r = row[8]
            o_q1i = row[9]
            row[8] = q1r
            row[9] = q1i
            sv[k, 4] = xr  # for the low band: new and leaving samples
            sv[k, 5] = yr
            sv[k, 6] = row[4]
            sv[k, 7] = row[5]
            slot += 1
            if slot == N:
                slot = 0
            p1r = ph[i1, 0]
            p1i = ph[i1, 1]
            p2r = ph[i2, 0]
            p2i = ph[i2, 1]
            # the leaving sample's phasors are the previous sample's: Ω(N − 1) = 2π
            r1r, r1i, r2r, r2i = q1r_prev, q1i_prev, q2r_prev, q2i_prev
            q1r_prev, q1i_prev, q2r_prev, q2i_prev = p1r, p1i, p2r, p2i
            # Sliding sums Σ q e^{jmΩt'} over the window, and the fresh sums.
            fr = rpos >= fresh_from
            resync = rpos == period - 1
            h = _real_sums(
                fb,
                off_acc,
                row_off,
                (q2, q3, q_yx, q_xx, xr, yr, q_sx, q_sy),
                (p1r, p1i, p2r, p2i),
                (r1r, r1i, r2r, r2i),
                fr,
                resync,
            )
            _cplx_sum(a0, a1, 0, q1r, q1i, p2r, -p2i, o_q1r, o_q1i, r2r, -r2i, fr)
            _cplx_sum(a0, a1, 2, q1r, q1i, p1r, -p1i, o_q1r, o_q1i, r1r, -r1i, fr)
            a0[4] = a0[4] + q1r - o_q1r
            a0[5] = a0[5] + q1i - o_q1i
            if fr:
                a1[4] += q1r
                a1[5] += q1i
            _cplx_sum(a0, a1, 6, q1r, q1i, p1r, p1i, o_q1r, o_q1i, r1r, r1i, fr)
            _cplx_sum(a0, a1, 8, q1r, q1i, p2r, p2i, o_q1r, o_q1i, r2r, r2i, fr)
            # Resynchronise: the fresh sums hold exactly the current window after N additions.
            if resync:
                for i in range(10):
                    a0[i] = a1[i]
                    a1[i] = 0.0
            if t == next_end:
                next_end += hop
                s_re, s_im, E, F, re_s, e_ex, mu_x, mu_y = _window_sums(
                    t, N, a0, h, p1r, p1i, p2r, p2i, w2, sum_w, alt_w, Mf
                )
                work[0, nout] = s_re
                work[1, nout] = s_im
                work[2, nout] = E
                work[3, nout] = F
                work[4, nout] = re_s
                work[5, nout] = e_ex
                work[6, nout] = 0.0  # the low band's E, F, Re S, Im S (below, when K0 > 0)
                work[7, nout] = 0.0
                work[8, nout] = 0.0
                work[9, nout] = 0.0
                work[10, nout] = mu_x  # window means of the raw samples
                work[11, nout] = mu_y
                out_t[nout] = t
                nout += 1
            i1 = _wrap(i1 + 1, P)
            i2 = _wrap(i2 + 2, P)
            t += 1
            rpos += 1
            if rpos == period:
                rpos = 0
        if K0 > 0:  # exact low band (sliding DFTs of the raw samples) over the sub-block
            lowband_block(lb, lbc, sv, m, t_sub, N, out_t, w_sub, nout, work, iscr, accs)
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
def _pass2(fb, work, out, n, angles):  # pragma: no cover
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
def _stream_block(xs, ys, fb, ib, work, out, out_t):  # pragma: no cover
    """Process a block; completed windows → columns of ``out`` (φ, d: see :func:`_pass2`)."""
    n = _pass1(xs, ys, fb, ib, work, out_t)
    _pass2(fb, work, out, n, False)
    return n


@numba.njit(**_JIT)
def _stream_one(x, y, fb, ib):  # pragma: no cover
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
        #: bins 1 … K0 (below ``exact_band`` cycles per window) are evaluated exactly
        # rounded up to whole 8-wide vector chunks: the padding lanes are computed anyway
        k0 = 8 * math.ceil(math.ceil(exact_band * M / self.N) / 8)
        self.K0 = min(M // 2 - 1, k0) if exact_band > 0 else 0
        #: the exact band actually used (cycles per window)
        self.exact_band = self.K0 * self.N / M
        window_s = N / fs
        # With an exact low band the analytic signals only need the band above it.
        f_lo = min(max(0.25, 0.5 * self.exact_band) / window_s, 0.01 * fs)
        f_hi = min(0.45 * fs, max(F_HI_MAX, 40.0 * f_lo))
        self.a_i, self.a_q, self.phase_error_deg = hilbert_pair(f_lo, f_hi, self.fs)
        if self.a_i.size > NS_MAX:
            raise ValueError(f"Hilbert pair needs {self.a_i.size} sections (kernel: {NS_MAX})")
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
            "lbpad": 7,  # places "lb" on a 64-byte boundary (8-wide vectors)
            "lb": LB_STATE_ROWS * lowband_padded(self.K0),
            "lbc": LB_CONST_ROWS * lowband_padded(self.K0),
            "sv": 8 * LB_SUB,
            "accs": 32 * LB_SUB,
        }
        off = np.cumsum([0, *sizes.values()])
        buf = np.zeros(int(off[-1]))
        i_lb = list(sizes).index("lb")
        pad_start = int(off[i_lb]) - 7
        shift = (-(buf.ctypes.data // 8 + pad_start)) % 8 if buf.ctypes.data % 8 == 0 else 0
        off[i_lb:] += shift - 7  # the pad shrinks to `shift` doubles
        self._fb = fb = buf[: int(off[-1])]
        self._ib = ib = np.zeros(_NIB + 1 + LB_SUB, dtype=np.int64)
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
            (_OFF_SV, "sv"),
            (_OFF_ACCS, "accs"),
        ):
            ib[slot] = off[list(sizes).index(name)]
        ib[_N] = N
        ib[_NSEC] = ns
        ib[_K0] = lowband_padded(self.K0)
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

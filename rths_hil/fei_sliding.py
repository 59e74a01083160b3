"""Exact moving-window FEI at every sample by sliding DFTs (the online exact evaluator's engine).

The exact FEI of the window ``x[s … s+N−1]`` (seed Eq. 2.1–2.5, conventions in
:mod:`rths_hil.fei`) needs the zero-padded ``M``-point DFT of the Hann-windowed, mean-free
window at the one-sided bins ``k = 1 … p−1``,

    X_k = Σ_i w_i (x[s+i] − μ) e^{−jθ_k i},      θ_k = 2πk/M,  μ = (1/N) Σ_i x[s+i].

The symmetric Hann window (``numpy.hanning``) is three complex exponentials,
``w_i = ½ − ¼e^{jΩi} − ¼e^{−jΩi}`` with ``Ω = 2π/(N−1)``, so with the modulated inputs
``u_g[n] = x[n] e^{jgΩn}`` (g = 0, +1, −1) and their rectangular sliding DFTs at the bins,

    D_g,k(s) = Σ_{i=0}^{N−1} u_g[s+i] e^{−jθ_k i},
    X_k = ½ D_0,k − ¼ e^{−jΩs} D_+1,k − ¼ e^{jΩs} D_−1,k − μ W_k,   W_k = Σ_i w_i e^{−jθ_k i}.

Moving the window by one sample is the sliding-DFT recursion (Jacobsen & Lyons, "The sliding
DFT", IEEE Signal Processing Magazine 20(2), 2003, Eq. 1, generalised to zero padding M ≥ N):

    D_g,k(s+1) = e^{jθ_k} (D_g,k(s) − u_g[s] + u_g[s+N] e^{−jθ_k N}),

three complex multiply-adds per bin and signal, i.e. O(M) per sample with no FFT. The sums
``E = Σ|X_k|²``, ``F = Σ k|X_k|²``, ``S = Σ conj(X_k) Y_k`` of a window are another O(M) pass.
The recursion is marginally stable, so every ``resync`` samples the states are recomputed from
the window itself with FFTs (one real and one complex FFT per signal), at sample indices fixed
by the stream position: results do not depend on how the stream is cut into blocks, and they
equal the per-window FFT evaluation (:func:`rths_hil.fei.moving_fei`) to round-off.

Cost on the 2-core development VM (AVX-512) at N = M = 8192: see ``docs/fei.md``; it is chosen by
:class:`rths_hil.fei.OnlineFEI` for small hops, where one FFT pair per window costs more.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.fft as sfft
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

# Row indices of the state arrays Dr/Di (6 × K): target g = 0, +1, −1, measured g = 0, +1, −1.
_NSTATE = 6


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def _advance(Dr, Di, c1r, c1i, c2r, c2i, nr, ni, orr, oi):  # pragma: no cover - numba
    """One sliding-DFT step of the six states: D ← c1 · (D − old + new · c2)."""
    K = Dr.shape[1]
    for r in range(_NSTATE):
        a_r, a_i, b_r, b_i = nr[r], ni[r], orr[r], oi[r]
        dr = Dr[r]
        di = Di[r]
        for k in range(K):
            tr = dr[k] - b_r + a_r * c2r[k] - a_i * c2i[k]
            ti = di[k] - b_i + a_r * c2i[k] + a_i * c2r[k]
            dr[k] = c1r[k] * tr - c1i[k] * ti
            di[k] = c1r[k] * ti + c1i[k] * tr


@numba.njit(cache=True, nogil=True, inline="always", fastmath={"contract", "reassoc"})
def _hann_bin(Dr, Di, r, k, pr, pi, mu, wr, wi):  # pragma: no cover - numba
    """X_k = ½D0 − ¼ conj(ϕ) D+ − ¼ ϕ D− − μ W_k from state rows r, r+1, r+2 (ϕ = pr + j·pi)."""
    re = (
        0.5 * Dr[r, k]
        - 0.25 * (pr * Dr[r + 1, k] + pi * Di[r + 1, k])
        - 0.25 * (pr * Dr[r + 2, k] - pi * Di[r + 2, k])
        - mu * wr
    )
    im = (
        0.5 * Di[r, k]
        - 0.25 * (pr * Di[r + 1, k] - pi * Dr[r + 1, k])
        - 0.25 * (pr * Di[r + 2, k] + pi * Dr[r + 2, k])
        - mu * wi
    )
    return re, im


@numba.njit(cache=True, nogil=True, fastmath={"contract", "reassoc"})
def _sums(Dr, Di, Wr, Wi, kk, mx, my, pr, pi):  # pragma: no cover - numba
    """E, F, Re S, Im S of the window whose states are D (ϕ = pr + j·pi = e^{jΩs})."""
    K = Dr.shape[1]
    E = 0.0
    F = 0.0
    Sr = 0.0
    Si = 0.0
    for k in range(K):
        xr, xi = _hann_bin(Dr, Di, 0, k, pr, pi, mx, Wr[k], Wi[k])  # target: rows 0–2
        yr, yi = _hann_bin(Dr, Di, 3, k, pr, pi, my, Wr[k], Wi[k])  # measured: rows 3–5
        P = xr * xr + xi * xi
        E += P
        F += kk[k] * P
        Sr += xr * yr + xi * yi
        Si += xr * yi - xi * yr
    return E, F, Sr, Si


@numba.njit(cache=True, nogil=True)
def _run(
    xs, ys, t0, first_end, hop, N, ring, sums, Dr, Di, c1r, c1i, c2r, c2i, Wr, Wi, kk, ph, out, ends
):  # pragma: no cover - numba
    """Push samples ``xs, ys`` (absolute indices t0, t0+1, …); return the windows completed.

    ``ring`` (2 × N) holds the last N samples (slot t mod N), ``sums`` the running window sums
    of target and measured. ``out`` rows get (E, F, Re S, Im S) of each window ending at an
    index ``≥ first_end`` with ``(end − first_end) % hop == 0``; ``ends`` their indices.
    """
    P = N - 1
    nr = np.empty(_NSTATE)
    ni = np.empty(_NSTATE)
    orr = np.empty(_NSTATE)
    oi = np.empty(_NSTATE)
    n_out = 0
    for j in range(xs.shape[0]):
        t = t0 + j
        slot = t % N
        xo = ring[0, slot]
        yo = ring[1, slot]
        xn = xs[j]
        yn = ys[j]
        ring[0, slot] = xn
        ring[1, slot] = yn
        sums[0] += xn - xo
        sums[1] += yn - yo
        # phasors e^{jΩt} (new sample) and e^{jΩ(t−N)} (the one leaving), period N − 1
        qn = ph[t % P]
        qo = ph[(t - N) % P]
        for s, vn, vo in ((0, xn, xo), (3, yn, yo)):
            nr[s] = vn
            ni[s] = 0.0
            orr[s] = vo
            oi[s] = 0.0
            nr[s + 1] = vn * qn.real
            ni[s + 1] = vn * qn.imag
            orr[s + 1] = vo * qo.real
            oi[s + 1] = vo * qo.imag
            nr[s + 2] = vn * qn.real
            ni[s + 2] = -vn * qn.imag
            orr[s + 2] = vo * qo.real
            oi[s + 2] = -vo * qo.imag
        _advance(Dr, Di, c1r, c1i, c2r, c2i, nr, ni, orr, oi)
        if t >= first_end and (t - first_end) % hop == 0:
            s0 = t - N + 1
            q = ph[s0 % P]
            E, F, Sr, Si = _sums(Dr, Di, Wr, Wi, kk, sums[0] / N, sums[1] / N, q.real, q.imag)
            out[n_out, 0] = E
            out[n_out, 1] = F
            out[n_out, 2] = Sr
            out[n_out, 3] = Si
            ends[n_out] = t
            n_out += 1
    return n_out


class SlidingSums:
    """Spectral sums ``E, F, S`` of every window, updated sample by sample (O(M) per sample).

    Parameters
    ----------
    N : int
        Window length (samples).
    hop : int
        Samples between reported windows (the first ends at sample ``N − 1``).
    resync : int, optional
        Samples between re-computations of the states from the window by FFT (default N).
    """

    def __init__(self, N: int, hop: int = 1, resync: int | None = None) -> None:
        self.N = int(N)
        self.M = 1 << (self.N - 1).bit_length()
        self.hop = int(hop)
        self.resync = int(resync or self.N)
        p = self.M // 2
        K = p - 1
        k = np.arange(1, p, dtype=float)
        theta = 2 * np.pi * k / self.M
        self.c1r, self.c1i = np.cos(theta), np.sin(theta)
        c2 = np.exp(-1j * ((np.arange(1, p) * self.N) % self.M) * 2 * np.pi / self.M)
        self.c2r, self.c2i = np.ascontiguousarray(c2.real), np.ascontiguousarray(c2.imag)
        W = sfft.rfft(np.hanning(self.N), n=self.M)[1:p]
        self.Wr, self.Wi = np.ascontiguousarray(W.real), np.ascontiguousarray(W.imag)
        self.kk = k
        P = self.N - 1
        self.ph = np.exp(1j * 2 * np.pi * np.arange(P) / P)
        self.Dr = np.zeros((_NSTATE, K))
        self.Di = np.zeros((_NSTATE, K))
        self.ring = np.zeros((2, self.N))
        self.sums = np.zeros(2)
        self.t = 0  # samples pushed
        self._out = np.empty((1, 4))
        self._ends = np.empty(1, dtype=np.int64)

    def _resync(self) -> None:
        """Recompute the states and window sums of the window ending at sample ``t − 1``."""
        N, M = self.N, self.M
        p = M // 2
        t = self.t
        s0 = t - N
        idx = (np.arange(s0, t)) % N
        P = N - 1
        mod = self.ph[np.arange(s0, t) % P]  # e^{jΩn}
        for base, row in ((0, 0), (3, 1)):
            v = self.ring[row, idx]
            self.sums[row] = float(v.sum())
            d0 = sfft.rfft(v, n=M)[1:p]
            dp = sfft.fft(v * mod, n=M)
            dm = np.conj(dp[M - np.arange(1, p)])  # DFT of conj(u₊) = u₋ at bin k
            for g, d in ((0, d0), (1, dp[1:p]), (2, dm)):
                self.Dr[base + g] = d.real
                self.Di[base + g] = d.imag

    def process(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Push a block; return rows (E, F, Re S, Im S) and end indices of completed windows."""
        n = x.shape[0]
        cap = n // self.hop + 1
        if self._out.shape[0] < cap:
            self._out = np.empty((cap, 4))
            self._ends = np.empty(cap, dtype=np.int64)
        done = 0
        pos = 0
        while pos < n:
            # run up to the next resync point (a multiple of `resync`, past the first window)
            nxt = (self.t // self.resync + 1) * self.resync
            take = min(n - pos, nxt - self.t)
            got = _run(
                x[pos : pos + take],
                y[pos : pos + take],
                self.t,
                self.N - 1,
                self.hop,
                self.N,
                self.ring,
                self.sums,
                self.Dr,
                self.Di,
                self.c1r,
                self.c1i,
                self.c2r,
                self.c2i,
                self.Wr,
                self.Wi,
                self.kk,
                self.ph,
                self._out[done:],
                self._ends[done:],
            )
            done += got
            pos += take
            self.t += take
            if self.t % self.resync == 0 and self.t >= self.N:
                self._resync()
        return self._out[:done], self._ends[:done]


# ---------------------------------------------------------------------------------------------
# Low band: sliding DFTs for the first K0 bins only, with an O(1), spike-free
# resynchronisation (the streaming evaluator's exact low band, :mod:`rths_hil.fei_streaming`).
#
# The three Hann terms are taken as three frequencies of the *raw* signal rather than as
# modulated signals at one frequency: e^{±jΩi} e^{−jθ_k i} = e^{−j(θ_k ∓ Ω) i}, so with
# D(θ; s) = Σ_i x[s+i] e^{−jθi} (a sliding DFT of the real samples at the frequency θ),
#
#     X_k = ½ D(θ_k) − ¼ D(θ_k − Ω) − ¼ D(θ_k + Ω) − μ W_k,
#     D(θ; s+1) = e^{jθ} (D(θ; s) − x[s] + x[s+N] e^{−jθN})      (Jacobsen & Lyons 2003, Eq. 1).
#
# Inputs are real (half the multiplications of the modulated form) and the window needs no
# phasor. Two sets of states: the *active* set slides (adds the new sample, removes the one
# leaving the window). Against round-off the states are resynchronised once every
# LB_RESYNC_WINDOWS windows: during the last N samples of each such period a *fresh* set starts
# from zero and only adds; after those N samples it holds exactly the current window, without
# any removal round-off, and replaces the active set (no O(N) step, no spikes). The period is
# fixed by the stream position, so results do not depend on how the stream is cut into blocks.
#
# Kernel: a block is processed chunk by chunk (8 bins), all of its samples per chunk, with the
# chunk's states and constants held in vector registers; the window sums of each completed
# window are accumulated per chunk into 8-lane partials and reduced once at the end.
#
# Layout (8-wide vectors, chunk-major): K0 is padded to K0p, a multiple of 8 (padding bins have
# zero constants, so their states stay 0 and add nothing); bins 8c … 8c + 7 form chunk c. ``lb``
# (K0p/8 × 24 × 8): per chunk the rows 6·plane + state, planes active re, active im, fresh re,
# fresh im, states target θ_k, θ_k − Ω, θ_k + Ω, then measured the same. ``lbc``
# (K0p/8 × 15 × 8): per chunk, for the frequency sets g = 0, 1, 2 (θ_k, θ_k − Ω, θ_k + Ω) four
# rows from 4g: e^{jθ} = c1, e^{−jθN} = c2 (re, im each); then W_k (re, im) and k.
# ---------------------------------------------------------------------------------------------


#: Rows per chunk of the low-band state and constant arrays ``lb`` and ``lbc``.
LB_STATE_ROWS = 24
LB_CONST_ROWS = 15
#: Windows per resynchronisation period of the low band (see the comment above).
LB_RESYNC_WINDOWS = 16


def lowband_padded(K0: int) -> int:
    """Number of stored low-band bins: K0 rounded up to a multiple of 8 (vector width)."""
    return -(-int(K0) // 8) * 8


def _c_array(a, ndim):
    """True for a C-contiguous float64 array type of ``ndim`` dimensions (kernel arguments)."""
    return (
        isinstance(a, types.Array)
        and a.ndim == ndim
        and a.layout == "C"
        and a.dtype == types.float64
    )


def _vec_tools(context, builder):  # pragma: no cover - code generation
    """LLVM helpers for the low-band kernels: vector type, splat, fma, loads/stores."""
    dbl = ir.DoubleType()
    vty = ir.VectorType(dbl, 8)
    i32 = ir.IntType(32)
    fma = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(vty, [vty, vty, vty]), "llvm.fma.v8f64"
    )

    def splat(x):
        if isinstance(x, float):
            return ir.Constant(vty, [x] * 8)
        v = builder.insert_element(ir.Constant(vty, ir.Undefined), x, ir.Constant(i32, 0))
        mask = ir.Constant(ir.VectorType(i32, 8), [0] * 8)
        return builder.shuffle_vector(v, ir.Constant(vty, ir.Undefined), mask)

    def vptr(base, off):
        return builder.bitcast(builder.gep(base, [off]), vty.as_pointer())

    def load(base, off):
        return builder.load(vptr(base, off), align=8)

    def store(v, base, off):
        builder.store(v, vptr(base, off), align=8)

    def fmadd(a, b, c):
        return builder.call(fma, [a, b, c])

    return vty, splat, load, store, fmadd


def _chunk_ptr(builder, arr, index, rows):  # pragma: no cover - code generation
    """Pointer to chunk ``index`` (``rows`` × 8 doubles) of a chunk-major array."""
    i64 = index.type
    return builder.gep(arr.data, [builder.mul(index, ir.Constant(i64, 8 * rows))])


_W_ROW = 12  # W re, W im, k
_NACC = 4  # window sums accumulated per chunk: E, F, Re S, Im S


def _hsum(builder, v):  # pragma: no cover - code generation
    """Sum of the 8 lanes of v (pairwise tree)."""
    i32 = ir.IntType(32)
    width = 8
    while width > 1:
        width //= 2
        lo = builder.shuffle_vector(
            v, v, ir.Constant(ir.VectorType(i32, width), list(range(width)))
        )
        hi = builder.shuffle_vector(
            v, v, ir.Constant(ir.VectorType(i32, width), list(range(width, 2 * width)))
        )
        v = builder.fadd(lo, hi)
    return builder.extract_element(v, ir.Constant(i32, 0))


def _transpose_sum8(builder, vs):  # pragma: no cover - code generation
    """Lane sums of eight 8-lane vectors as one vector (lane i: the sum of vs[i])."""
    i32 = ir.IntType(32)

    def shuf(a, b, idx):
        return builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(i32, 8), idx))

    def level(a, b, lo, hi):
        return builder.fadd(shuf(a, b, lo), shuf(a, b, hi))

    # lanes i + 4: [a0..3 | b0..3]
    s = [
        level(vs[i], vs[i + 1], [0, 1, 2, 3, 8, 9, 10, 11], [4, 5, 6, 7, 12, 13, 14, 15])
        for i in (0, 2, 4, 6)
    ]
    # lanes + 2: [a0,1 | c0,1 | b0,1 | d0,1]
    t = [
        level(s[i], s[i + 1], [0, 1, 8, 9, 4, 5, 12, 13], [2, 3, 10, 11, 6, 7, 14, 15])
        for i in (0, 2)
    ]
    # lanes + 1: [0, 4, 2, 6, 1, 5, 3, 7] → reorder
    u = level(t[0], t[1], [0, 8, 2, 10, 4, 12, 6, 14], [1, 9, 3, 11, 5, 13, 7, 15])
    return shuf(u, u, [0, 4, 2, 6, 1, 5, 3, 7])


@intrinsic
def _lowband_piece_vec(
    typingctx, lb, lbc, src, p, n, fresh, ends, nw, work, wcol, accs
):  # pragma: no cover
    """Vector kernel of :func:`lowband_block` for a stretch of samples with one fresh mode.

    Samples ``p … p+n−1`` of ``src`` (rows; columns 4, 5: new target and measured samples,
    6, 7: the ones leaving the window). ``fresh``: the fresh set adds these samples too.
    ``ends[:nw]``: ascending sample indices (relative to ``p``) at which a window completes;
    window ``j`` reads its means from ``work[10, wcol+j]``, ``work[11, wcol+j]`` and receives
    E, F, Re S, Im S in ``work[6 … 9, wcol+j]``. ``accs`` (≥ nw × 4 × 8): scratch partials.
    """
    if not (_c_array(lb, 3) and _c_array(lbc, 3) and _c_array(src, 2)):
        return None
    if not (_c_array(work, 2) and _c_array(accs, 3)):
        return None
    if not (isinstance(ends, types.Array) and ends.layout == "C" and ends.dtype == types.int64):
        return None
    if not all(isinstance(v, types.Integer) for v in (p, n, nw, wcol)):
        return None
    sig = types.none(lb, lbc, src, p, n, fresh, ends, nw, work, wcol, accs)

    def codegen(context, builder, signature, args):  # pragma: no cover - code generation
        lbv, lbcv, srcv, _p, _n, freshv, endsv, _nw, workv, _wc, accsv = args
        sa = signature.args
        pv, nv, nwv, wcv = (context.cast(builder, args[i], sa[i], types.intp) for i in (3, 4, 7, 9))
        freshv = context.cast(builder, freshv, sa[5], types.boolean)
        arr = context.make_array(sa[0])(context, builder, lbv)
        cst = context.make_array(sa[1])(context, builder, lbcv)
        sr = context.make_array(sa[2])(context, builder, srcv)
        en = context.make_array(sa[6])(context, builder, endsv)
        wk = context.make_array(sa[8])(context, builder, workv)
        ac = context.make_array(sa[10])(context, builder, accsv)
        ncol = cgutils.unpack_tuple(builder, sr.shape)[1]
        wstride = cgutils.unpack_tuple(builder, wk.shape)[1]
        nch = cgutils.unpack_tuple(builder, arr.shape)[0]
        i64 = nch.type
        _vty, splat, load, store, fmadd = _vec_tools(context, builder)
        c64 = lambda v: ir.Constant(i64, v)  # noqa: E731

        def at(row):
            return c64(8 * row)

        def scalar(ptr, idx):
            return builder.load(builder.gep(ptr, [idx]))

        def acc_ptr(w, j):
            return builder.add(builder.mul(w, c64(8 * _NACC)), c64(8 * j))

        mhalf = splat(-0.5)

        def chunk(index, first):  # one chunk of 8 bins over all samples of the stretch
            # (the first chunk writes the window partials, the others add to them)
            base = _chunk_ptr(builder, arr, index, LB_STATE_ROWS)
            cbase = _chunk_ptr(builder, cst, index, LB_CONST_ROWS)
            consts = [[load(cbase, at(4 * g + i)) for i in range(4)] for g in range(3)]
            wr, wi, kk = (load(cbase, at(_W_ROW + i)) for i in range(3))
            act = [cgutils.alloca_once_value(builder, load(base, at(r))) for r in range(12)]
            frs = [cgutils.alloca_once_value(builder, load(base, at(12 + r))) for r in range(12)]
            wpos = cgutils.alloca_once_value(builder, c64(0))
            first_end = builder.select(
                builder.icmp_signed(">", nwv, c64(0)), scalar(en.data, c64(0)), c64(-1)
            )
            nxt = cgutils.alloca_once_value(builder, first_end)

            def window(w):  # accumulate this chunk's bins of window w into its partials
                col = builder.add(wcv, w)
                mx = scalar(wk.data, builder.add(builder.mul(c64(10), wstride), col))
                my = scalar(wk.data, builder.add(builder.mul(c64(11), wstride), col))

                # 2 X_k = D(θ) − ½ (D(θ − Ω) + D(θ + Ω)) − 2 μ W (the factor 2 is undone once
                # per window: the sums are quadratic, × ¼ after the reduction)
                def spec(s0, plane, w_, nm):
                    r = 6 * plane + s0
                    pair = builder.fadd(builder.load(act[r + 1]), builder.load(act[r + 2]))
                    return fmadd(nm, w_, fmadd(mhalf, pair, builder.load(act[r])))

                nmx = splat(builder.fmul(mx, ir.Constant(mx.type, -2.0)))
                nmy = splat(builder.fmul(my, ir.Constant(my.type, -2.0)))
                xr = spec(0, 0, wr, nmx)
                xi = spec(0, 1, wi, nmx)
                yr = spec(3, 0, wr, nmy)
                yi = spec(3, 1, wi, nmy)
                pw = fmadd(xi, xi, builder.fmul(xr, xr))
                if first:  # the same roundings as adding to zero partials
                    store(pw, ac.data, acc_ptr(w, 0))
                    store(builder.fmul(kk, pw), ac.data, acc_ptr(w, 1))
                    store(fmadd(xi, yi, builder.fmul(xr, yr)), ac.data, acc_ptr(w, 2))
                    store(fmadd(builder.fneg(xi), yr, builder.fmul(xr, yi)), ac.data, acc_ptr(w, 3))
                    return
                e, f, s_r, s_i = (load(ac.data, acc_ptr(w, j)) for j in range(_NACC))
                store(builder.fadd(e, pw), ac.data, acc_ptr(w, 0))
                store(fmadd(kk, pw, f), ac.data, acc_ptr(w, 1))
                store(fmadd(xi, yi, fmadd(xr, yr, s_r)), ac.data, acc_ptr(w, 2))
                store(fmadd(builder.fneg(xi), yr, fmadd(xr, yi, s_i)), ac.data, acc_ptr(w, 3))

            def run(with_fresh, dense):
                """Sample loop; ``dense``: every sample completes a window (hop 1)."""
                with cgutils.for_range(builder, nv) as sl:
                    row = builder.mul(builder.add(pv, sl.index), ncol)
                    vals = [scalar(sr.data, builder.add(row, c64(c))) for c in (4, 5, 6, 7)]
                    new = (splat(vals[0]), splat(vals[1]))
                    old = (splat(vals[2]), splat(vals[3]))
                    for g in range(3):
                        c1r, c1i, c2r, c2i = consts[g]
                        for sgl in range(2):
                            s = 3 * sgl + g
                            # active: D ← c1 · (D − o + n c2)
                            tr = fmadd(new[sgl], c2r, builder.fsub(builder.load(act[s]), old[sgl]))
                            ti = fmadd(new[sgl], c2i, builder.load(act[6 + s]))
                            builder.store(
                                fmadd(c1r, tr, builder.fneg(builder.fmul(c1i, ti))), act[s]
                            )
                            builder.store(fmadd(c1r, ti, builder.fmul(c1i, tr)), act[6 + s])
                            if with_fresh:  # fresh: F ← c1 · (F + n c2)
                                ur = fmadd(new[sgl], c2r, builder.load(frs[s]))
                                ui = fmadd(new[sgl], c2i, builder.load(frs[6 + s]))
                                builder.store(
                                    fmadd(c1r, ur, builder.fneg(builder.fmul(c1i, ui))), frs[s]
                                )
                                builder.store(fmadd(c1r, ui, builder.fmul(c1i, ur)), frs[6 + s])
                    if dense:
                        window(sl.index)
                    else:
                        is_end = builder.icmp_signed("==", sl.index, builder.load(nxt))
                        with builder.if_then(is_end):
                            w = builder.load(wpos)
                            window(w)
                            w1 = builder.add(w, c64(1))
                            builder.store(w1, wpos)
                            last = builder.icmp_signed(">=", w1, nwv)
                            idx = builder.select(last, c64(0), w1)
                            builder.store(builder.select(last, c64(-1), scalar(en.data, idx)), nxt)

            dense = builder.icmp_signed("==", nwv, nv)  # ends are then 0 … n−1
            with builder.if_else(freshv) as (then, otherwise):
                with then:
                    run(True, False)
                with otherwise:
                    with builder.if_else(dense) as (d_then, d_else):
                        with d_then:
                            run(False, True)
                        with d_else:
                            run(False, False)
            for r in range(12):
                store(builder.load(act[r]), base, at(r))
                store(builder.load(frs[r]), base, at(12 + r))

        with builder.if_then(builder.icmp_signed(">", nch, c64(0))):
            chunk(c64(0), True)
            with cgutils.for_range(builder, builder.sub(nch, c64(1))) as loop:
                chunk(builder.add(loop.index, c64(1)), False)
        # Reduce the partials → work rows 6 … 9 (× ¼): eight windows at a time by a transposing
        # tree (the same pairwise order as _hsum, lanes i + 4, then + 2, then + 1), the rest
        # one by one.
        quarter = ir.Constant(ir.DoubleType(), 0.25)
        n8 = builder.sdiv(nwv, c64(8))
        with cgutils.for_range(builder, n8) as gl:
            w0 = builder.mul(gl.index, c64(8))
            for j in range(_NACC):
                vs = [load(ac.data, acc_ptr(builder.add(w0, c64(i)), j)) for i in range(8)]
                v = _transpose_sum8(builder, vs)
                idx = builder.add(builder.mul(c64(6 + j), wstride), builder.add(wcv, w0))
                store(builder.fmul(v, splat(0.25)), wk.data, idx)
        with cgutils.for_range(builder, builder.sub(nwv, builder.mul(n8, c64(8)))) as wl:
            w = builder.add(builder.mul(n8, c64(8)), wl.index)
            col = builder.add(wcv, w)
            for j in range(_NACC):
                v = builder.fmul(_hsum(builder, load(ac.data, acc_ptr(w, j))), quarter)
                idx = builder.add(builder.mul(c64(6 + j), wstride), col)
                builder.store(v, builder.gep(wk.data, [idx]))
        return context.get_dummy_value()

    return sig, codegen


@numba.njit(cache=True, nogil=True)
def lowband_swap(lb):  # pragma: no cover - numba
    """Resynchronise: the fresh set becomes the active set and restarts from zero."""
    for c in range(lb.shape[0]):
        for r in range(12):
            for j in range(8):
                lb[c, r, j] = lb[c, 12 + r, j]
                lb[c, 12 + r, j] = 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def lowband_block(lb, lbc, src, n, t0, N, ends_t, w0, w1, work, iscr, accs):  # pragma: no cover
    """Advance the low band over ``n`` samples and evaluate the windows completing in them.

    ``src[k, 4 … 7]`` (k < n): new target and measured samples of stream index ``t0 + k`` and
    the ones leaving the window (0 before the first N). Windows ``w0 … w1−1`` end at the stream
    indices ``ends_t[w]`` (ascending, inside the block); each reads its means from ``work[10, w]``,
    ``work[11, w]`` and receives E, F, Re S, Im S over bins 1 … K0 in ``work[6 … 9, w]``.
    ``iscr`` (int64, ≥ n) and ``accs`` (≥ n × 4 × 8) are scratch. The block is split where the
    fresh set starts and where it replaces the active set (stream positions; see above).
    """
    period = LB_RESYNC_WINDOWS * N
    fstart = period - N
    p = 0
    w = w0
    while p < n:
        ph = (t0 + p) % period
        fresh = ph >= fstart
        q = min(n, p + (period - ph if fresh else fstart - ph))
        nw = 0
        while w < w1 and ends_t[w] - t0 < q:
            iscr[nw] = ends_t[w] - t0 - p
            nw += 1
            w += 1
        _lowband_piece_vec(lb, lbc, src, p, q - p, fresh, iscr, nw, work, w - nw, accs)
        if fresh and (t0 + q) % period == 0:
            lowband_swap(lb)
        p = q


def lowband_constants(N: int, K0: int) -> np.ndarray:
    """The constant array ``lbc`` (K0p/8 × 15 × 8) of K0 low bins of an N-sample window."""
    N = int(N)
    M = 1 << (N - 1).bit_length()
    K0p = lowband_padded(K0)
    k = np.arange(1, K0 + 1)
    theta = 2 * np.pi * k / M
    theta_n = 2 * np.pi * ((k * N) % M) / M  # θ_k N mod 2π
    omega = 2 * np.pi / (N - 1)  # Ω N ≡ Ω (mod 2π)
    lbc = np.zeros((LB_CONST_ROWS, K0p))
    for g, sign in enumerate((0.0, -1.0, 1.0)):  # θ_k, θ_k − Ω, θ_k + Ω
        th = theta + sign * omega
        thn = theta_n + sign * omega  # θN mod 2π (up to a multiple of 2π)
        for i, v in enumerate((np.exp(1j * th), np.exp(-1j * thn))):
            lbc[4 * g + 2 * i, :K0] = v.real
            lbc[4 * g + 2 * i + 1, :K0] = v.imag
    W = sfft.rfft(np.hanning(N), n=M)[1 : K0 + 1]
    lbc[_W_ROW, :K0] = W.real
    lbc[_W_ROW + 1, :K0] = W.imag
    lbc[_W_ROW + 2, :K0] = k
    return np.ascontiguousarray(lbc.reshape(LB_CONST_ROWS, K0p // 8, 8).transpose(1, 0, 2))


#: Samples per sub-block of the block kernels (scratch rows; keeps the scratch in L1/L2).
LB_SUB = 128


def lowband_scratch() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scratch arrays (src, iscr, accs) for :func:`lowband_block` with blocks of ≤ LB_SUB."""
    return np.zeros((LB_SUB, 8)), np.zeros(LB_SUB, dtype=np.int64), np.zeros((LB_SUB, _NACC, 8))


@numba.njit(cache=True, nogil=True)
def _lowband_run(xs, ys, t0, hop, N, lb, lbc, ring, sums, src, iscr, accs, work, ends):
    """Standalone driver: ring of raw samples and window sums (means), then the kernel."""
    n_all = xs.shape[0]
    nout = 0
    for b0 in range(0, n_all, LB_SUB):
        b1 = min(n_all, b0 + LB_SUB)
        w0 = nout
        for k in range(b1 - b0):
            t = t0 + b0 + k
            slot = t % N
            xn = xs[b0 + k]
            yn = ys[b0 + k]
            xo = ring[slot, 0]
            yo = ring[slot, 1]
            ring[slot, 0] = xn
            ring[slot, 1] = yn
            src[k, 4] = xn
            src[k, 5] = yn
            src[k, 6] = xo
            src[k, 7] = yo
            sums[0] += xn - xo
            sums[1] += yn - yo
            sums[2] += xn
            sums[3] += yn
            if slot == N - 1:  # plain sums of the window restart every N samples
                sums[0] = sums[2]
                sums[1] = sums[3]
                sums[2] = 0.0
                sums[3] = 0.0
            if t >= N - 1 and (t - N + 1) % hop == 0:
                work[10, nout] = sums[0] / N
                work[11, nout] = sums[1] / N
                ends[nout] = t
                nout += 1
        lowband_block(lb, lbc, src, b1 - b0, t0 + b0, N, ends, w0, nout, work, iscr, accs)
    return nout


class LowBandSums:
    """Exact ``E, F, S`` restricted to bins 1 … K0 of every window, O(K0) per sample.

    The building block of the streaming evaluator's exact low band; standalone for tests.
    """

    def __init__(self, N: int, K0: int, hop: int = 1) -> None:
        self.N, self.K0, self.hop = int(N), int(K0), int(hop)
        self.lb = np.zeros((lowband_padded(K0) // 8, LB_STATE_ROWS, 8))
        self.lbc = lowband_constants(self.N, self.K0)
        self.ring = np.zeros((self.N, 2))
        self.sums = np.zeros(4)
        self.scratch = lowband_scratch()
        self.t = 0

    def process(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Rows (E, F, Re S, Im S, end index) of the windows completed by the block."""
        x = np.ascontiguousarray(x, dtype=float)
        y = np.ascontiguousarray(y, dtype=float)
        nmax = x.shape[0] // self.hop + 1
        work = np.zeros((12, nmax))
        ends = np.zeros(nmax, dtype=np.int64)
        n = _lowband_run(
            x,
            y,
            self.t,
            self.hop,
            self.N,
            self.lb,
            self.lbc,
            self.ring,
            self.sums,
            *self.scratch,
            work,
            ends,
        )
        self.t += x.shape[0]
        return np.column_stack([work[6:10, :n].T, ends[:n]])

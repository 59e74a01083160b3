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
# leaving the window); in every period of N samples a *fresh* set starts from zero at the
# period's first sample and only adds. After N samples it holds exactly the current window,
# without any removal round-off, and replaces the active set. The fresh set is only read then,
# so it adds _GROUP samples at a time, F ← c1^G F + Σ_j x_j c1^{G−j} c2 (one rotation per
# group instead of one per sample).
#
# Layout (8-wide vectors, chunk-major so that one chunk's vectors sit at fixed offsets from one
# pointer): K0 is padded to K0p, a multiple of 8 (padding bins have zero constants, so their
# states stay 0 and add nothing); bins 8c … 8c + 7 form chunk c. ``lb`` (K0p/8 × 24 × 8): per
# chunk the rows 6·plane + state, planes active re, active im, fresh re, fresh im, states target
# θ_k, θ_k − Ω, θ_k + Ω, then measured the same. ``lbc`` (K0p/8 × 45 × 8): per chunk, for the
# frequency sets g = 0, 1, 2 (θ_k, θ_k − Ω, θ_k + Ω) 14 rows from 14g: e^{jθ} = c1, e^{−jθN} =
# c2, c1^G, then c1^{G−j} c2 for j = 0 … G−1 (each re, im); then W_k (re, im) and k.
# Kept 64-byte aligned by the streaming evaluator (unaligned arrays work, slower).
# ---------------------------------------------------------------------------------------------


#: Rows per chunk of the low-band state and constant arrays ``lb`` and ``lbc``.
LB_STATE_ROWS = 24
LB_CONST_ROWS = 45


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


_GROUP = 4  # samples per update of the fresh set
_G_ROWS = 6 + 2 * _GROUP  # constant rows per frequency set
_W_ROW = 3 * _G_ROWS  # W re, W im, k


def _emit_active(builder, tools, arr, cst, nch, new, old):  # pragma: no cover - codegen
    """Active set, one sample: D ← c1 · (D − o + n c2) (``new``, ``old``: splats per signal)."""
    _vty, _splat, load, store, fmadd = tools
    at = _row_offset(nch)
    with cgutils.for_range(builder, nch) as loop:
        base = _chunk_ptr(builder, arr, loop.index, LB_STATE_ROWS)
        cbase = _chunk_ptr(builder, cst, loop.index, LB_CONST_ROWS)
        for g in range(3):
            c = _G_ROWS * g
            c1r, c1i, c2r, c2i = (load(cbase, at(c + i)) for i in range(4))
            for sgl in range(2):
                s = 3 * sgl + g
                n = new[sgl]
                tr = fmadd(n, c2r, builder.fsub(load(base, at(s)), old[sgl]))
                ti = fmadd(n, c2i, load(base, at(6 + s)))
                store(fmadd(c1r, tr, builder.fneg(builder.fmul(c1i, ti))), base, at(s))
                store(fmadd(c1r, ti, builder.fmul(c1i, tr)), base, at(6 + s))


def _emit_fresh(builder, tools, arr, cst, nch, ns):  # pragma: no cover - code generation
    """Fresh set: add 1 or _GROUP samples (``ns``: per signal, splats oldest first).

    One sample: F ← c1 · (F + n c2); _GROUP samples at once:
    F ← c1^G F + Σ_j n_j c1^{G−j} c2 (the same recursion unrolled, one rotation per group).
    """
    _vty, _splat, load, store, fmadd = tools
    at = _row_offset(nch)
    cnt = len(ns[0])
    with cgutils.for_range(builder, nch) as loop:
        base = _chunk_ptr(builder, arr, loop.index, LB_STATE_ROWS)
        cbase = _chunk_ptr(builder, cst, loop.index, LB_CONST_ROWS)
        for g in range(3):
            c = _G_ROWS * g
            if cnt == 1:
                c1r, c1i, c2r, c2i = (load(cbase, at(c + i)) for i in range(4))
                for sgl in range(2):
                    s = 3 * sgl + g
                    n = ns[sgl][0]
                    ur = fmadd(n, c2r, load(base, at(12 + s)))
                    ui = fmadd(n, c2i, load(base, at(18 + s)))
                    store(fmadd(c1r, ur, builder.fneg(builder.fmul(c1i, ui))), base, at(12 + s))
                    store(fmadd(c1r, ui, builder.fmul(c1i, ur)), base, at(18 + s))
                continue
            cgr, cgi = load(cbase, at(c + 4)), load(cbase, at(c + 5))
            kr = [load(cbase, at(c + 6 + 2 * j)) for j in range(cnt)]
            ki = [load(cbase, at(c + 7 + 2 * j)) for j in range(cnt)]
            for sgl in range(2):
                s = 3 * sgl + g
                f_r = load(base, at(12 + s))
                f_i = load(base, at(18 + s))
                vr = fmadd(cgr, f_r, builder.fneg(builder.fmul(cgi, f_i)))
                vi = fmadd(cgr, f_i, builder.fmul(cgi, f_r))
                for j in range(cnt):
                    vr = fmadd(ns[sgl][j], kr[j], vr)
                    vi = fmadd(ns[sgl][j], ki[j], vi)
                store(vr, base, at(12 + s))
                store(vi, base, at(18 + s))


def _emit_swap(builder, tools, arr, nch):  # pragma: no cover - code generation
    """The fresh set becomes the active set and restarts from zero."""
    vty, _splat, load, store, _fmadd = tools
    at = _row_offset(nch)
    zero = ir.Constant(vty, [0.0] * 8)
    with cgutils.for_range(builder, nch) as loop:
        base = _chunk_ptr(builder, arr, loop.index, LB_STATE_ROWS)
        for r in range(12):
            store(load(base, at(12 + r)), base, at(r))
            store(zero, base, at(12 + r))


def _row_offset(nch):  # pragma: no cover - code generation
    def at(row):
        return ir.Constant(nch.type, 8 * row)

    return at


@intrinsic
def _lowband_update_vec(
    typingctx, lb, lbc, ring, cx, cy, st, N, m, xn, yn, xo, yo
):  # pragma: no cover
    """Vector kernel of :func:`lowband_update` (one call, all control flow inside)."""
    if not (_c_array(lb, 3) and _c_array(lbc, 3) and _c_array(ring, 2)):
        return None
    ints = (cx, cy, st, N, m)
    if not all(isinstance(v, types.Integer) for v in ints):
        return None
    sig = types.none(lb, lbc, ring, cx, cy, st, N, m, xn, yn, xo, yo)

    def codegen(context, builder, signature, args):  # pragma: no cover - code generation
        lbv, lbcv, ringv = args[:3]
        cxv, cyv, stv, nv, mv = (
            context.cast(builder, v, ty, types.intp)
            for v, ty in zip(args[3:8], signature.args[3:8], strict=True)
        )
        xnv, ynv, xov, yov = args[8:]
        arr = context.make_array(signature.args[0])(context, builder, lbv)
        cst = context.make_array(signature.args[1])(context, builder, lbcv)
        rg = context.make_array(signature.args[2])(context, builder, ringv)
        ncol = cgutils.unpack_tuple(builder, rg.shape)[1]
        nch = cgutils.unpack_tuple(builder, arr.shape)[0]
        i64 = nch.type
        tools = _vec_tools(context, builder)
        splat = tools[1]
        new = (splat(xnv), splat(ynv))
        _emit_active(builder, tools, arr, cst, nch, new, (splat(xov), splat(yov)))

        def past(j):  # splats of ring samples j rows before st (modulo N), target and measured
            i = builder.sub(stv, ir.Constant(i64, j))
            i = builder.select(
                builder.icmp_signed("<", i, ir.Constant(i64, 0)), builder.add(i, nv), i
            )
            row = builder.mul(i, ncol)
            return [
                splat(builder.load(builder.gep(rg.data, [builder.add(row, col)])))
                for col in (cxv, cyv)
            ]

        grp = ir.Constant(i64, _GROUP)
        zero = ir.Constant(i64, 0)
        in_group = builder.icmp_signed("==", builder.srem(mv, grp), zero)
        with builder.if_then(in_group, likely=False):
            older = [past(j) for j in range(_GROUP - 1, 0, -1)]
            ns = [[o[sgl] for o in older] + [new[sgl]] for sgl in range(2)]
            _emit_fresh(builder, tools, arr, cst, nch, ns)
        with builder.if_then(builder.icmp_signed("==", mv, nv), likely=False):
            r = builder.srem(nv, grp)  # samples after the last full group: t − r + 1 … t
            for j in range(_GROUP - 2, 0, -1):
                with builder.if_then(builder.icmp_signed(">", r, ir.Constant(i64, j))):
                    xj, yj = past(j)
                    _emit_fresh(builder, tools, arr, cst, nch, [[xj], [yj]])
            with builder.if_then(builder.icmp_signed(">", r, zero)):
                _emit_fresh(builder, tools, arr, cst, nch, [[new[0]], [new[1]]])
            _emit_swap(builder, tools, arr, nch)
        return context.get_dummy_value()

    return sig, codegen


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


@intrinsic
def _lowband_window_vec(typingctx, lb, lbc, mx, my):  # pragma: no cover
    """Vector kernel of :func:`lowband_window`: (E, F, Re S, Im S)."""
    if not (_c_array(lb, 3) and _c_array(lbc, 3)):
        return None
    sig = types.UniTuple(types.float64, 4)(lb, lbc, mx, my)

    def codegen(context, builder, signature, args):
        lbv, lbcv, mxv, myv = args
        arr = context.make_array(signature.args[0])(context, builder, lbv)
        cst = context.make_array(signature.args[1])(context, builder, lbcv)
        nch = cgutils.unpack_tuple(builder, arr.shape)[0]
        i64 = nch.type
        vty, splat, load, _store, fmadd = _vec_tools(context, builder)
        zero = ir.Constant(vty, [0.0] * 8)
        accs = [cgutils.alloca_once_value(builder, zero) for _ in range(4)]
        nmx = splat(builder.fneg(mxv))
        nmy = splat(builder.fneg(myv))
        half = splat(0.5)
        mq = splat(-0.25)

        def at(row):
            return ir.Constant(i64, 8 * row)

        with cgutils.for_range(builder, nch) as loop:
            base = _chunk_ptr(builder, arr, loop.index, LB_STATE_ROWS)
            cbase = _chunk_ptr(builder, cst, loop.index, LB_CONST_ROWS)
            wr = load(cbase, at(_W_ROW))
            wi = load(cbase, at(_W_ROW + 1))
            kk = load(cbase, at(_W_ROW + 2))

            def spec(plane, s0, w, nm):  # ½ D(θ) − ¼ D(θ − Ω) − ¼ D(θ + Ω) − μ W
                r = 6 * plane + s0
                v = builder.fmul(half, load(base, at(r)))
                v = fmadd(mq, load(base, at(r + 1)), v)
                v = fmadd(mq, load(base, at(r + 2)), v)
                return fmadd(nm, w, v)

            xr = spec(0, 0, wr, nmx)
            xi = spec(1, 0, wi, nmx)
            yr = spec(0, 3, wr, nmy)
            yi = spec(1, 3, wi, nmy)
            p = fmadd(xi, xi, builder.fmul(xr, xr))
            e, f, sr, si = (builder.load(a) for a in accs)
            builder.store(builder.fadd(e, p), accs[0])
            builder.store(fmadd(kk, p, f), accs[1])
            builder.store(fmadd(xi, yi, fmadd(xr, yr, sr)), accs[2])
            builder.store(fmadd(builder.fneg(xi), yr, fmadd(xr, yi, si)), accs[3])
        vals = [_hsum(builder, builder.load(a)) for a in accs]
        return cgutils.pack_array(builder, vals)

    return sig, codegen


@numba.njit(cache=True, nogil=True, inline="always")
def lowband_update(lb, lbc, ring, cx, cy, st, N, m, xn, yn, xo, yo):  # pragma: no cover - numba
    """Advance the six sliding DFTs of the low band by one sample pair.

    ``lb`` (K0p/8 × 24 × 8), ``lbc`` (K0p/8 × 45 × 8): see the layout above. ``xn, yn``: the new
    samples, ``xo, yo``: the ones leaving the window (0 before the first N). ``m`` (1 … N): the
    new sample's place in the current fresh period; ``ring[·, cx]``, ``ring[·, cy]``: the
    caller's ring of the last N samples (row ``st`` holds the new one, rows modulo N), from
    which the fresh set takes the samples of a group. The fresh set is advanced every
    _GROUP samples (and by the remaining samples at the period's end, ``m = N``), where it
    then replaces the active set.
    """
    _lowband_update_vec(lb, lbc, ring, cx, cy, st, N, m, xn, yn, xo, yo)


@numba.njit(cache=True, nogil=True, inline="always")
def lowband_window(lb, lbc, mx, my):  # pragma: no cover - numba
    """E, F, Re S, Im S over bins 1 … K0 of the current window (exact); ``mx, my``: means."""
    return _lowband_window_vec(lb, lbc, mx, my)


@numba.njit(cache=True, nogil=True, inline="always")
def lowband_step(lb, lbc, lbring, lbs, t, N, xn, yn):  # pragma: no cover - numba
    """Standalone step: ring of raw samples and window sums, then :func:`lowband_update`.

    ``lbring`` (N × 2): the last N raw samples; ``lbs`` (4): running Σx, Σy, fresh Σx, Σy.
    The fresh periods are the stretches ``[qN, (q+1)N)``.
    """
    slot = t % N
    xo = lbring[slot, 0]
    yo = lbring[slot, 1]
    lbring[slot, 0] = xn
    lbring[slot, 1] = yn
    lbs[0] += xn - xo
    lbs[1] += yn - yo
    lowband_update(lb, lbc, lbring, 0, 1, slot, N, slot + 1, xn, yn, xo, yo)
    lbs[2] += xn
    lbs[3] += yn
    if slot == N - 1:
        lbs[0] = lbs[2]
        lbs[1] = lbs[3]
        lbs[2] = 0.0
        lbs[3] = 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def lowband_sums(lb, lbc, lbs, N):  # pragma: no cover - numba
    """E, F, Re S, Im S over bins 1 … K0 of the window ending at the last sample (exact)."""
    return lowband_window(lb, lbc, lbs[0] / N, lbs[1] / N)


def lowband_constants(N: int, K0: int) -> np.ndarray:
    """The constant array ``lbc`` (K0p/8 × 45 × 8) of K0 low bins of an N-sample window."""
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
        rows = [np.exp(1j * th), np.exp(-1j * thn), np.exp(1j * _GROUP * th)]
        rows += [np.exp(1j * ((_GROUP - j) * th - thn)) for j in range(_GROUP)]  # c1^{G−j} c2
        c = _G_ROWS * g
        for i, v in enumerate(rows):
            lbc[c + 2 * i, :K0] = v.real
            lbc[c + 2 * i + 1, :K0] = v.imag
    W = sfft.rfft(np.hanning(N), n=M)[1 : K0 + 1]
    lbc[_W_ROW, :K0] = W.real
    lbc[_W_ROW + 1, :K0] = W.imag
    lbc[_W_ROW + 2, :K0] = k
    return np.ascontiguousarray(lbc.reshape(LB_CONST_ROWS, K0p // 8, 8).transpose(1, 0, 2))


def lowband_arrays(N: int, K0: int) -> tuple[np.ndarray, ...]:
    """Fresh state and constant arrays (lb, lbc, lbring, lbs) for K0 low bins."""
    lb = np.zeros((lowband_padded(K0) // 8, LB_STATE_ROWS, 8))
    return lb, lowband_constants(N, K0), np.zeros((int(N), 2)), np.zeros(4)


@numba.njit(cache=True, nogil=True)
def _lowband_block(xs, ys, t0, hop, N, lb, lbc, lbring, lbs, out):  # pragma: no cover
    n = 0
    for j in range(xs.shape[0]):
        t = t0 + j
        lowband_step(lb, lbc, lbring, lbs, t, N, xs[j], ys[j])
        if t >= N - 1 and (t - N + 1) % hop == 0:
            E, F, Sr, Si = lowband_sums(lb, lbc, lbs, N)
            out[n, 0] = E
            out[n, 1] = F
            out[n, 2] = Sr
            out[n, 3] = Si
            out[n, 4] = t
            n += 1
    return n


class LowBandSums:
    """Exact ``E, F, S`` restricted to bins 1 … K0 of every window, O(K0) per sample.

    The building block of the streaming evaluator's exact low band; standalone for tests.
    """

    def __init__(self, N: int, K0: int, hop: int = 1) -> None:
        self.N, self.K0, self.hop = int(N), int(K0), int(hop)
        self.state = lowband_arrays(self.N, self.K0)
        self.t = 0

    def process(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Rows (E, F, Re S, Im S, end index) of the windows completed by the block."""
        out = np.empty((x.shape[0] // self.hop + 1, 5))
        n = _lowband_block(x, y, self.t, self.hop, self.N, *self.state, out)
        self.t += x.shape[0]
        return out[:n]

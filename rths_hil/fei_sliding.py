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


@numba.njit(cache=True, nogil=True, fastmath={"contract", "reassoc"})
def _sums(Dr, Di, Wr, Wi, kk, mx, my, pr, pi):  # pragma: no cover - numba
    """E, F, Re S, Im S of the window whose states are D (ϕ = pr + j·pi = e^{jΩs})."""
    K = Dr.shape[1]
    E = 0.0
    F = 0.0
    Sr = 0.0
    Si = 0.0
    for k in range(K):
        # X = ½D0 − ¼ conj(ϕ) D+ − ¼ ϕ D− − μ W
        xr = (
            0.5 * Dr[0, k]
            - 0.25 * (pr * Dr[1, k] + pi * Di[1, k])
            - 0.25 * (pr * Dr[2, k] - pi * Di[2, k])
            - mx * Wr[k]
        )
        xi = (
            0.5 * Di[0, k]
            - 0.25 * (pr * Di[1, k] - pi * Dr[1, k])
            - 0.25 * (pr * Di[2, k] + pi * Dr[2, k])
            - mx * Wi[k]
        )
        yr = (
            0.5 * Dr[3, k]
            - 0.25 * (pr * Dr[4, k] + pi * Di[4, k])
            - 0.25 * (pr * Dr[5, k] - pi * Di[5, k])
            - my * Wr[k]
        )
        yi = (
            0.5 * Di[3, k]
            - 0.25 * (pr * Di[4, k] - pi * Dr[4, k])
            - 0.25 * (pr * Di[5, k] + pi * Dr[5, k])
            - my * Wi[k]
        )
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
# Low band: the same sliding DFTs for the first K0 bins only, with an O(1), spike-free
# resynchronisation (the streaming evaluator's exact low band, :mod:`rths_hil.fei_streaming`).
#
# Two sets of states: the *active* set slides (adds the new sample, removes the one leaving
# the window); once every RESYNC_WINDOWS window periods a *fresh* set starts from zero at the
# period's first sample and only adds. After N samples it holds exactly the current window,
# without any removal round-off, and replaces the active set.
# ---------------------------------------------------------------------------------------------


#: Window periods between resynchronisations of the low-band states.
RESYNC_WINDOWS = 1


@numba.njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def lowband_update(lb, lbc, xn, yn, xo, yo, qnr, qni, qor, qoi, fresh, swap):  # pragma: no cover
    """Advance the six modulated sliding DFTs of the low band by one sample pair.

    ``lb`` (4 × 6 × K0): active re/im and fresh re/im (rows 0–2 target g = 0, +1, −1;
    rows 3–5 measured); ``lbc`` (7 × K0): e^{jθ_k} (re, im), e^{−jθ_k N} (re, im), W_k (re, im),
    k. ``xn, yn``: the new samples, ``xo, yo``: the ones leaving the window (0 before the first
    N); ``qn = e^{jΩt}``, ``qo = e^{jΩ(t−N)}``. With ``fresh`` the fresh set is advanced too
    (adds only); with ``swap`` (the last sample of a fresh period) it replaces the active set.
    """
    axr, axi = xn * qnr, xn * qni
    bxr, bxi = xo * qor, xo * qoi
    ayr, ayi = yn * qnr, yn * qni
    byr, byi = yo * qor, yo * qoi
    K = lb.shape[2]
    c1r = lbc[0]
    c1i = lbc[1]
    c2r = lbc[2]
    c2i = lbc[3]
    for s in range(6):
        if s == 0:
            nr, ni, o_r, o_i = xn, 0.0, xo, 0.0
        elif s == 1:
            nr, ni, o_r, o_i = axr, axi, bxr, bxi
        elif s == 2:
            nr, ni, o_r, o_i = axr, -axi, bxr, -bxi
        elif s == 3:
            nr, ni, o_r, o_i = yn, 0.0, yo, 0.0
        elif s == 4:
            nr, ni, o_r, o_i = ayr, ayi, byr, byi
        else:
            nr, ni, o_r, o_i = ayr, -ayi, byr, -byi
        dr = lb[0, s]
        di = lb[1, s]
        for k in range(K):
            a_r = nr * c2r[k] - ni * c2i[k]
            a_i = nr * c2i[k] + ni * c2r[k]
            tr = dr[k] - o_r + a_r
            ti = di[k] - o_i + a_i
            dr[k] = c1r[k] * tr - c1i[k] * ti
            di[k] = c1r[k] * ti + c1i[k] * tr
        if fresh:
            fr_ = lb[2, s]
            fi_ = lb[3, s]
            for k in range(K):
                a_r = nr * c2r[k] - ni * c2i[k]
                a_i = nr * c2i[k] + ni * c2r[k]
                fr = fr_[k] + a_r
                fi = fi_[k] + a_i
                fr_[k] = c1r[k] * fr - c1i[k] * fi
                fi_[k] = c1r[k] * fi + c1i[k] * fr
    if swap:
        for s in range(6):
            for k in range(K):
                lb[0, s, k] = lb[2, s, k]
                lb[1, s, k] = lb[3, s, k]
                lb[2, s, k] = 0.0
                lb[3, s, k] = 0.0


@numba.njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def lowband_window(lb, lbc, mx, my, pr, pi):  # pragma: no cover - numba
    """E, F, Re S, Im S over bins 1 … K0 of the window starting at s (exact).

    ``mx, my``: the window means; ``pr + j·pi = e^{jΩs}``.
    """
    E = 0.0
    F = 0.0
    Sr = 0.0
    Si = 0.0
    for k in range(lb.shape[2]):
        Wr = lbc[4, k]
        Wi = lbc[5, k]
        # X = ½D0 − ¼ conj(ϕ) D+ − ¼ ϕ D− − μ W  (ϕ = e^{jΩs})
        xr = (
            0.5 * lb[0, 0, k]
            - 0.25 * (pr * lb[0, 1, k] + pi * lb[1, 1, k])
            - 0.25 * (pr * lb[0, 2, k] - pi * lb[1, 2, k])
            - mx * Wr
        )
        xi = (
            0.5 * lb[1, 0, k]
            - 0.25 * (pr * lb[1, 1, k] - pi * lb[0, 1, k])
            - 0.25 * (pr * lb[1, 2, k] + pi * lb[0, 2, k])
            - mx * Wi
        )
        yr = (
            0.5 * lb[0, 3, k]
            - 0.25 * (pr * lb[0, 4, k] + pi * lb[1, 4, k])
            - 0.25 * (pr * lb[0, 5, k] - pi * lb[1, 5, k])
            - my * Wr
        )
        yi = (
            0.5 * lb[1, 3, k]
            - 0.25 * (pr * lb[1, 4, k] - pi * lb[0, 4, k])
            - 0.25 * (pr * lb[1, 5, k] + pi * lb[0, 5, k])
            - my * Wi
        )
        Pk = xr * xr + xi * xi
        E += Pk
        F += lbc[6, k] * Pk
        Sr += xr * yr + xi * yi
        Si += xr * yi - xi * yr
    return E, F, Sr, Si


@numba.njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def lowband_step(lb, lbc, lbring, lbs, ph, io, t, N, xn, yn):  # pragma: no cover - numba
    """Standalone step: ring of raw samples, window sums and phasors, then :func:`lowband_update`.

    ``lbring`` (2 × N): the last N raw samples; ``lbs`` (4): running Σx, Σy, fresh Σx, Σy;
    ``ph``: e^{j2πm/(N−1)}, m = 0 … N−2; ``io``: unused scratch.
    """
    P = N - 1
    slot = t % N
    xo = lbring[0, slot]
    yo = lbring[1, slot]
    lbring[0, slot] = xn
    lbring[1, slot] = yn
    lbs[0] += xn - xo
    lbs[1] += yn - yo
    qn = ph[t % P]
    qo = ph[(t - N) % P]
    fresh = (t // N) % RESYNC_WINDOWS == RESYNC_WINDOWS - 1
    swap = fresh and (t + 1) % N == 0
    lowband_update(lb, lbc, xn, yn, xo, yo, qn.real, qn.imag, qo.real, qo.imag, fresh, swap)
    if fresh:
        lbs[2] += xn
        lbs[3] += yn
        if swap:
            lbs[0] = lbs[2]
            lbs[1] = lbs[3]
            lbs[2] = 0.0
            lbs[3] = 0.0


@numba.njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def lowband_sums(lb, lbc, lbs, ph, t, N):  # pragma: no cover - numba
    """E, F, Re S, Im S over bins 1 … K0 of the window ending at sample t (exact)."""
    q = ph[(t - N + 1) % (N - 1)]
    return lowband_window(lb, lbc, lbs[0] / N, lbs[1] / N, q.real, q.imag)


def lowband_arrays(N: int, K0: int) -> tuple[np.ndarray, ...]:
    """Fresh state and constant arrays (lb, lbc, lbring, lbs, ph, io) for K0 low bins."""
    M = 1 << (int(N) - 1).bit_length()
    k = np.arange(1, K0 + 1)
    theta = 2 * np.pi * k / M
    W = sfft.rfft(np.hanning(N), n=M)[1 : K0 + 1]
    c2 = np.exp(-1j * ((k * N) % M) * 2 * np.pi / M)
    lbc = np.ascontiguousarray(
        np.vstack([np.cos(theta), np.sin(theta), c2.real, c2.imag, W.real, W.imag, k])
    )
    P = N - 1
    ph = np.exp(1j * 2 * np.pi * np.arange(P) / P)
    return np.zeros((4, 6, K0)), lbc, np.zeros((2, N)), np.zeros(4), ph, np.zeros((4, 8))


@numba.njit(cache=True, nogil=True)
def _lowband_block(xs, ys, t0, hop, N, lb, lbc, lbring, lbs, ph, io, out):  # pragma: no cover
    n = 0
    for j in range(xs.shape[0]):
        t = t0 + j
        lowband_step(lb, lbc, lbring, lbs, ph, io, t, N, xs[j], ys[j])
        if t >= N - 1 and (t - N + 1) % hop == 0:
            E, F, Sr, Si = lowband_sums(lb, lbc, lbs, ph, t, N)
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

"""Exact moving-window FEI at every sample by sliding DFTs (the online exact evaluator's engine).

The exact FEI of the window ``x[s … s+N−1]`` (the FEI paper, Eq. 2.1–2.5; conventions in
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

:class:`rths_hil.fei.OnlineFEI` uses :class:`SlidingSums` for small hops, where one FFT pair per
window costs more. The second half of the module, the *low band* (:class:`LowBandSums`), is the
streaming evaluator's exact part (:mod:`rths_hil.fei.streaming`).

The kernels are plain ``numba.njit`` loops. ``fastmath`` is limited to ``contract`` (a multiply
and an add may become one fused multiply-add: one rounding less, never a value that is not a
rounding of the exact result) and, in the window sums, ``reassoc`` (the order in which the bins
are summed; changes the last bits only). No flag that assumes finite or non-NaN values is used.
"""

from __future__ import annotations

from typing import Literal, TypedDict

import numba
import numpy as np
import scipy.fft as sfft

# Row indices of the state arrays Dr/Di (6 × K): target g = 0, +1, −1, measured g = 0, +1, −1.
_NSTATE = 6


class JitOptions(TypedDict, total=False):
    """The ``numba.njit`` options the FEI kernels are compiled with."""

    cache: bool
    nogil: bool
    error_model: Literal["python", "numpy"]
    fastmath: set[str]


# fastmath "contract": fused multiply-adds only (see the module docstring).
_JIT: JitOptions = {"cache": True, "nogil": True, "fastmath": {"contract"}}
# ... and "reassoc" for the sums over bins (summation order only).
_JIT_SUM: JitOptions = {"cache": True, "nogil": True, "fastmath": {"contract", "reassoc"}}


@numba.njit(**_JIT)
def _advance(Dr, Di, c1r, c1i, c2r, c2i, nr, ni, orr, oi):
    """One sliding-DFT step of the six states (Jacobsen & Lyons 2003, Eq. 1).

    ``n = nr + j·ni``: the entering input ``u_g[s+N]`` of state row r; ``o``: the leaving
    ``u_g[s]``; ``c1 = e^{jθ_k}``, ``c2 = e^{−jθ_k N}``.
    """
    K = Dr.shape[1]
    for r in range(_NSTATE):
        a_r, a_i, b_r, b_i = nr[r], ni[r], orr[r], oi[r]
        dr = Dr[r]
        di = Di[r]
        for k in range(K):
            # T = D − u[s] + u[s+N] e^{−jθN}
            tr = dr[k] - b_r + a_r * c2r[k] - a_i * c2i[k]
            ti = di[k] - b_i + a_r * c2i[k] + a_i * c2r[k]
            # D ← e^{jθ} T
            dr[k] = c1r[k] * tr - c1i[k] * ti
            di[k] = c1r[k] * ti + c1i[k] * tr


@numba.njit(inline="always", **_JIT_SUM)
def _hann_bin(Dr, Di, r, k, pr, pi, mu, wr, wi):
    """X_k = ½D₀ − ¼ conj(ϕ) D₊ − ¼ ϕ D₋ − μ W_k from state rows r, r+1, r+2 (ϕ = pr + j·pi)."""
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


@numba.njit(**_JIT_SUM)
def _sums(Dr, Di, Wr, Wi, kk, mx, my, pr, pi):
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
        E += P  # E = Σ |X_k|²            (the FEI paper, Eq. 2.1 denominator)
        F += kk[k] * P  # F = Σ k |X_k|²  (Eq. 2.4 numerator, in bins)
        Sr += xr * yr + xi * yi  # S = Σ Y_k conj(X_k)  (Eq. 2.1 numerator)
        Si += xr * yi - xi * yr
    return E, F, Sr, Si


@numba.njit(cache=True, nogil=True)
def _run(
    xs, ys, t0, first_end, hop, N, ring, sums, Dr, Di, c1r, c1i, c2r, c2i, Wr, Wi, kk, ph, out, ends
):
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
        sums[0] += xn - xo  # Σ x over the window (μ = Σ/N)
        sums[1] += yn - yo
        # phasors e^{jΩt} (new sample) and e^{jΩ(t−N)} (the one leaving), period N − 1
        qn = ph[t % P]
        qo = ph[(t - N) % P]
        for s, vn, vo in ((0, xn, xo), (3, yn, yo)):
            # u₀ = v, u₊ = v e^{jΩt}, u₋ = v e^{−jΩt} of the entering and the leaving sample
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
# resynchronisation (the streaming evaluator's exact low band, :mod:`rths_hil.fei.streaming`).
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
# from zero and only adds,
#
#     F(θ) ← e^{jθ} (F(θ) + x[s+N] e^{−jθN}),
#
# so after those N samples it holds exactly the current window, without any removal round-off,
# and replaces the active set (no O(N) step, no spikes). The period is fixed by the stream
# position, so results do not depend on how the stream is cut into blocks.
#
# Layout. States ``lb`` (4 × 6 × K0): planes active re, active im, fresh re, fresh im; rows
# target θ_k, θ_k − Ω, θ_k + Ω, then measured the same. Constants ``lbc`` (15 × K0): for the
# frequency sets g = 0, 1, 2 (θ_k, θ_k − Ω, θ_k + Ω) four rows from 4g: Re, Im e^{jθ} and
# Re, Im e^{−jθN}; then Re W_k, Im W_k and k.
# ---------------------------------------------------------------------------------------------


#: Rows of the low-band constant array ``lbc``.
LB_CONST_ROWS = 15
#: Windows per resynchronisation period of the low band (see the comment above).
LB_RESYNC_WINDOWS = 16
_W_ROW = 12  # rows of Re W_k, Im W_k, k in ``lbc``


@numba.njit(**_JIT)
def lowband_step(lb, lbc, xn, yn, xo, yo, fresh):
    """Slide the low band's states by one sample.

    ``xn, yn``: the entering target and measured samples ``x[s+N]``; ``xo, yo``: the leaving
    ones ``x[s]`` (0 before the first N). ``fresh``: the fresh set adds the sample too.
    """
    K0 = lb.shape[2]
    for sig in range(2):  # target, measured
        vn = xn if sig == 0 else yn
        vo = xo if sig == 0 else yo
        for g in range(3):  # θ_k, θ_k − Ω, θ_k + Ω
            r = 3 * sig + g
            for k in range(K0):
                c1r = lbc[4 * g, k]  # e^{jθ}
                c1i = lbc[4 * g + 1, k]
                c2r = lbc[4 * g + 2, k]  # e^{−jθN}
                c2i = lbc[4 * g + 3, k]
                # active: D ← e^{jθ} (D − x[s] + x[s+N] e^{−jθN})   (Jacobsen & Lyons, Eq. 1)
                tr = lb[0, r, k] - vo + vn * c2r
                ti = lb[1, r, k] + vn * c2i
                lb[0, r, k] = c1r * tr - c1i * ti
                lb[1, r, k] = c1r * ti + c1i * tr
                if fresh:
                    # fresh: F ← e^{jθ} (F + x[s+N] e^{−jθN})   (additions only)
                    ur = lb[2, r, k] + vn * c2r
                    ui = lb[3, r, k] + vn * c2i
                    lb[2, r, k] = c1r * ur - c1i * ui
                    lb[3, r, k] = c1r * ui + c1i * ur


@numba.njit(**_JIT_SUM)
def lowband_window(lb, lbc, mx, my):
    """E, F, Re S, Im S over bins 1 … K0 of the window held by the active states.

    ``mx, my``: the window means of target and measured (the μ W_k term).
    """
    E = 0.0
    F = 0.0
    Sr = 0.0
    Si = 0.0
    for k in range(lb.shape[2]):
        wr = lbc[_W_ROW, k]
        wi = lbc[_W_ROW + 1, k]
        # X_k = ½ D(θ_k) − ¼ D(θ_k − Ω) − ¼ D(θ_k + Ω) − μ W_k   (Hann = three exponentials)
        xr = 0.5 * lb[0, 0, k] - 0.25 * (lb[0, 1, k] + lb[0, 2, k]) - mx * wr
        xi = 0.5 * lb[1, 0, k] - 0.25 * (lb[1, 1, k] + lb[1, 2, k]) - mx * wi
        yr = 0.5 * lb[0, 3, k] - 0.25 * (lb[0, 4, k] + lb[0, 5, k]) - my * wr
        yi = 0.5 * lb[1, 3, k] - 0.25 * (lb[1, 4, k] + lb[1, 5, k]) - my * wi
        P = xr * xr + xi * xi
        E += P  # E = Σ |X_k|²             (the FEI paper, Eq. 2.1 denominator)
        F += lbc[_W_ROW + 2, k] * P  # F = Σ k |X_k|²   (Eq. 2.4 numerator, in bins)
        Sr += xr * yr + xi * yi  # S = Σ Y_k conj(X_k)   (Eq. 2.1 numerator)
        Si += xr * yi - xi * yr
    return E, F, Sr, Si


@numba.njit(**_JIT)
def lowband_swap(lb):
    """Resynchronise: the fresh set becomes the active set and restarts from zero."""
    for r in range(lb.shape[1]):
        for k in range(lb.shape[2]):
            lb[0, r, k] = lb[2, r, k]
            lb[1, r, k] = lb[3, r, k]
            lb[2, r, k] = 0.0
            lb[3, r, k] = 0.0


def lowband_constants(N: int, K0: int) -> np.ndarray:
    """The constant array ``lbc`` (15 × K0) of the K0 lowest bins of an N-sample window."""
    N = int(N)
    M = 1 << (N - 1).bit_length()
    k = np.arange(1, K0 + 1)
    theta = 2 * np.pi * k / M
    theta_n = 2 * np.pi * ((k * N) % M) / M  # θ_k N mod 2π
    omega = 2 * np.pi / (N - 1)  # Ω N ≡ Ω (mod 2π)
    lbc = np.zeros((LB_CONST_ROWS, K0))
    for g, sign in enumerate((0.0, -1.0, 1.0)):  # θ_k, θ_k − Ω, θ_k + Ω
        th = theta + sign * omega
        thn = theta_n + sign * omega  # θN mod 2π (up to a multiple of 2π)
        for i, v in enumerate((np.exp(1j * th), np.exp(-1j * thn))):
            lbc[4 * g + 2 * i] = v.real
            lbc[4 * g + 2 * i + 1] = v.imag
    W = sfft.rfft(np.hanning(N), n=M)[1 : K0 + 1]
    lbc[_W_ROW] = W.real
    lbc[_W_ROW + 1] = W.imag
    lbc[_W_ROW + 2] = k
    return lbc


@numba.njit(**_JIT)
def _lowband_run(xs, ys, t0, hop, N, lb, lbc, ring, sums, out):
    """Standalone driver: ring of raw samples, window means, the low band; rows → ``out``.

    ``sums``: running window sums of target and measured (0, 1) and plain sums since the last
    multiple of N (2, 3), which replace the running ones every N samples (no drift).
    """
    period = LB_RESYNC_WINDOWS * N
    nout = 0
    for j in range(xs.shape[0]):
        t = t0 + j
        slot = t % N
        xn = xs[j]
        yn = ys[j]
        xo = ring[slot, 0]
        yo = ring[slot, 1]
        ring[slot, 0] = xn
        ring[slot, 1] = yn
        sums[0] += xn - xo
        sums[1] += yn - yo
        sums[2] += xn
        sums[3] += yn
        if slot == N - 1:  # plain sums of the window restart every N samples
            sums[0] = sums[2]
            sums[1] = sums[3]
            sums[2] = 0.0
            sums[3] = 0.0
        pos = t % period  # position in the resynchronisation period
        lowband_step(lb, lbc, xn, yn, xo, yo, pos >= period - N)
        if t >= N - 1 and (t - N + 1) % hop == 0:
            E, F, Sr, Si = lowband_window(lb, lbc, sums[0] / N, sums[1] / N)
            out[nout, 0] = E
            out[nout, 1] = F
            out[nout, 2] = Sr
            out[nout, 3] = Si
            out[nout, 4] = t
            nout += 1
        if pos == period - 1:  # the fresh set holds exactly this window
            lowband_swap(lb)
    return nout


class LowBandSums:
    """Exact ``E, F, S`` restricted to bins 1 … K0 of every window, O(K0) per sample.

    The building block of the streaming evaluator's exact low band; standalone for tests.
    """

    def __init__(self, N: int, K0: int, hop: int = 1) -> None:
        self.N, self.K0, self.hop = int(N), int(K0), int(hop)
        self.lb = np.zeros((4, 6, self.K0))
        self.lbc = lowband_constants(self.N, self.K0)
        self.ring = np.zeros((self.N, 2))
        self.sums = np.zeros(4)
        self.t = 0

    def process(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Rows (E, F, Re S, Im S, end index) of the windows completed by the block."""
        x = np.ascontiguousarray(x, dtype=float)
        y = np.ascontiguousarray(y, dtype=float)
        out = np.zeros((x.shape[0] // self.hop + 1, 5))
        n = _lowband_run(
            x, y, self.t, self.hop, self.N, self.lb, self.lbc, self.ring, self.sums, out
        )
        self.t += x.shape[0]
        return out[:n]

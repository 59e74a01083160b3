"""Brute-force references for the FEI's sliding sums: direct DFT sums over a window."""

from __future__ import annotations

import numpy as np

from rths_hil import fei as F


def brute_sums(x: np.ndarray, y: np.ndarray, end: int, N: int) -> tuple[float, float, complex]:
    """E, F, S of the window ending at ``end`` by a direct DFT sum (no FFT, no recursion)."""
    M = F.fft_length(N)
    p = M // 2
    w = np.hanning(N)
    xs = x[end - N + 1 : end + 1]
    ys = y[end - N + 1 : end + 1]
    xw = w * (xs - xs.mean())
    yw = w * (ys - ys.mean())
    k = np.arange(1, p)
    basis = np.exp(-2j * np.pi * np.outer(k, np.arange(N)) / M)
    X = basis @ xw
    Y = basis @ yw
    P = np.abs(X) ** 2
    return float(P.sum()), float(P @ k), complex(np.sum(Y * np.conj(X)))


def random_walk_pair(L: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = 0.05 + 1e-3 * np.cumsum(rng.standard_normal(L))  # large offset, small motion
    y = 1.08 * np.roll(x, 3) + 1e-5 * rng.standard_normal(L)
    return x, y


def brute_lowband(x, y, end, N, K0):
    M = F.fft_length(N)
    w = np.hanning(N)
    xs = x[end - N + 1 : end + 1]
    ys = y[end - N + 1 : end + 1]
    k = np.arange(1, K0 + 1)
    basis = np.exp(-2j * np.pi * np.outer(k, np.arange(N)) / M)
    X = basis @ (w * (xs - xs.mean()))
    Y = basis @ (w * (ys - ys.mean()))
    P = np.abs(X) ** 2
    return float(P.sum()), float(P @ k), complex(np.sum(Y * np.conj(X)))

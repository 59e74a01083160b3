"""Realistic test signals for the twin/estimation tests: SDOF responses to bundled records.

Independent of rths_hil.structures.sdof on purpose: the response is scipy.signal.lsim of the
continuous 1-DOF transfer function ``X/Ag = -1/(s² + 2ζω s + ω²)`` driven by the bundled
accelerogram (g → m/s²) linearly interpolated to ``fs``, then scaled to a chosen peak.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from scipy import signal

FS = 1024.0
G = 9.80665
DATA = Path(__file__).resolve().parents[2] / "rths_hil" / "data" / "ground_motions"


@functools.lru_cache(maxsize=16)
def _response(name: str, fn: float, zeta: float, fs: float, duration: float | None):
    d = np.loadtxt(DATA / f"{name}.csv", delimiter=",", skiprows=1)
    t0, a = d[:, 0], d[:, 1] * G
    if duration is not None:
        keep = t0 <= duration
        t0, a = t0[keep], a[keep]
    t = np.arange(0.0, t0[-1], 1.0 / fs)
    ag = np.interp(t, t0, a)
    w = 2 * np.pi * fn
    _, x, _ = signal.lsim(([-1.0], [1.0, 2 * zeta * w, w * w]), ag, t)
    return t, x


def sdof_response(
    name: str = "el_centro_1940_NS_chopra_0p02",
    fn: float = 1.0,
    zeta: float = 0.02,
    peak: float = 0.02,
    fs: float = FS,
    duration: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Time (s) and relative displacement (m) of an SDOF under a bundled record, |x|max = peak."""
    t, x = _response(name, fn, zeta, fs, duration)
    return t.copy(), x * (peak / np.max(np.abs(x)))

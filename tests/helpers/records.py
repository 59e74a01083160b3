"""Deterministic record rows for the recorder's tests."""

from __future__ import annotations

import numpy as np

from rths_hil.records.recorder import COLUMNS


def row(k: int, fs: float = 1024.0) -> tuple:
    """A deterministic row whose every column depends on k (so misplaced bytes show up)."""
    out = []
    for j, (name, code, _, _) in enumerate(COLUMNS):
        if name == "time":
            out.append(k / fs)
        elif code == "<i8":
            out.append(k * 7 + j)
        elif code == "|b1":
            out.append((k + j) % 3 == 0)
        else:
            out.append(np.sin(0.01 * k + j) * 10.0 ** (-j % 5))
    return tuple(out)

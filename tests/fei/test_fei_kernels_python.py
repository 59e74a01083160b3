"""The compiled FEI kernels' logic, run as plain Python (``NUMBA_DISABLE_JIT=1``, subprocess).

The kernels of :mod:`rths_hil.fei.sliding` and :mod:`rths_hil.fei.streaming` are
``numba.njit`` loops; under the JIT neither coverage nor a debugger sees their lines. Here a
subprocess runs the same functions as Python on small cases and checks them against a direct
DFT (sliding DFTs, low band), against ``moving_fei`` (streaming with every bin in the exact band)
and against the compiled kernels of this process (streaming with a partial exact band and
without one: the analytic-signal filters, sliding sums and resynchronisations).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np

from rths_hil import fei as F
from rths_hil.fei.sliding import LB_RESYNC_WINDOWS, LowBandSums, SlidingSums
from rths_hil.fei.streaming import StreamingFEI
from tests.helpers.fei_refs import brute_lowband, brute_sums, random_walk_pair

FS = 64.0
# streaming cases: (N, exact_band, samples) — all bins exact; a partial band; no exact band.
# Each runs past at least one resynchronisation of the sliding sums (LB_RESYNC_WINDOWS · N).
STREAM_CASES = [(32, 20.0, 1200), (128, 20.0, 16 * 128 + 300), (256, 0.0, 16 * 256 + 200)]


def stream_signals(L: int) -> tuple[np.ndarray, np.ndarray]:
    """Two tones and noise; measured = 1.05 × target delayed by 20 ms (exactly, per tone)."""
    t = np.arange(L) / FS

    def tones(t):
        return 0.01 * np.sin(2 * np.pi * 1.7 * t) + 0.004 * np.sin(2 * np.pi * 5.3 * t + 0.3)

    noise = 1e-4 * np.random.default_rng(7).standard_normal((2, L))
    return tones(t) + noise[0], 1.05 * tones(t - 0.02) + noise[1]


CHILD = textwrap.dedent(
    """
    import sys

    import numba
    import numpy as np

    assert numba.config.DISABLE_JIT, "the kernels must run as Python here"
    from rths_hil.fei.sliding import LowBandSums, SlidingSums
    from rths_hil.fei.streaming import StreamingFEI
    from test_fei_kernels_python import (
        FS, STREAM_CASES, lowband_case, sliding_case, stream_signals,
    )

    out = {}
    out["sliding_rows"], out["sliding_ends"] = sliding_case(SlidingSums)
    out["lowband_rows"] = lowband_case(LowBandSums)
    for i, (N, band, L) in enumerate(STREAM_CASES):
        x, y = stream_signals(L)
        s = StreamingFEI(FS, N, 1, 1e-6, 0.05, band)
        parts = [s.process(x[:5], y[:5])[0].copy()]
        parts += [s.process(x[5:5 + 1], y[5:5 + 1])[0].copy()]  # one sample
        parts += [s.process(x[6:], y[6:])[0].copy()]
        out[f"stream{i}"] = np.concatenate(parts)
    np.savez(sys.argv[1], **out)
    """
)


def sliding_case(cls) -> tuple[np.ndarray, np.ndarray]:
    """Exact online sliding DFTs: N = 40, hop 1, three resynchronisations, odd block cuts."""
    N = 40
    x, y = random_walk_pair(3 * N + 9, 11)
    s = cls(N, hop=1)
    rows, ends = [], []
    for a, b in ((0, 7), (7, 8), (8, 90), (90, x.size)):
        r, e = s.process(x[a:b], y[a:b])
        rows.append(r.copy())
        ends.append(e.copy())
    return np.concatenate(rows), np.concatenate(ends)


def lowband_case(cls) -> np.ndarray:
    """Low band: N = 24, K0 = 5 bins, hop 2, two resynchronisation periods."""
    N = 24
    L = 2 * LB_RESYNC_WINDOWS * N + 7
    x, y = random_walk_pair(L, 3)
    lb = cls(N, 5, hop=2)
    return np.concatenate([lb.process(x[a : a + 100], y[a : a + 100]) for a in range(0, L, 100)])


def assert_same_sums(a: np.ndarray, b: np.ndarray) -> None:
    """Rows (E, F, Re S, Im S, …) equal to round-off: E, F relative, S relative to |S|."""
    np.testing.assert_allclose(a[:, :2], b[:, :2], rtol=1e-11)
    S_a = a[:, 2] + 1j * a[:, 3]
    S_b = b[:, 2] + 1j * b[:, 3]
    assert np.all(np.abs(S_a - S_b) <= 1e-11 * np.abs(S_b))
    np.testing.assert_array_equal(a[:, 4:], b[:, 4:])


def test_kernels_as_python_match_direct_dft_and_compiled(tmp_path):
    out = tmp_path / "python_kernels.npz"
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    here = os.path.dirname(os.path.abspath(__file__))
    root = os.path.dirname(os.path.dirname(here))
    env["PYTHONPATH"] = os.pathsep.join([here, root, env.get("PYTHONPATH", "")])
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(out)],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    py = np.load(out)

    # sliding DFTs (exact online): every window against the direct DFT sum
    N = 40
    x, y = random_walk_pair(3 * N + 9, 11)
    np.testing.assert_array_equal(py["sliding_ends"], np.arange(N - 1, x.size))
    for row, end in zip(py["sliding_rows"], py["sliding_ends"], strict=True):
        E, Fk, S = brute_sums(x, y, int(end), N)
        assert abs(row[0] - E) <= 1e-10 * E
        assert abs(row[1] - Fk) <= 1e-10 * Fk
        assert abs(complex(row[2], row[3]) - S) <= 1e-10 * abs(S)
    jit_rows, jit_ends = sliding_case(SlidingSums)
    np.testing.assert_array_equal(jit_ends, py["sliding_ends"])
    assert_same_sums(jit_rows, py["sliding_rows"])

    # low band: every window against the direct DFT over bins 1 … K0, across both swaps
    N, K0 = 24, 5
    x, y = random_walk_pair(2 * LB_RESYNC_WINDOWS * N + 7, 3)
    rows = py["lowband_rows"]
    np.testing.assert_array_equal(rows[:, 4], np.arange(N - 1, x.size, 2))
    for r in rows:
        E, Fk, S = brute_lowband(x, y, int(r[4]), N, K0)
        assert abs(r[0] - E) <= 1e-10 * E
        assert abs(r[1] - Fk) <= 1e-10 * Fk
        assert abs(complex(r[2], r[3]) - S) <= 1e-10 * abs(S)
    assert_same_sums(lowband_case(LowBandSums), rows)

    # streaming: the Python logic equals the compiled kernels to round-off, and with every bin
    # in the exact band equals the exact FEI
    for i, (N, band, L) in enumerate(STREAM_CASES):
        x, y = stream_signals(L)
        got = py[f"stream{i}"]
        jit, ends = StreamingFEI(FS, N, 1, 1e-6, 0.05, band).process(x, y)
        assert got.shape == jit.shape == (L - N + 1, 6)
        np.testing.assert_array_equal(got[:, 4], jit[:, 4])
        v = jit[:, 4] > 0.5
        assert v.mean() > 0.9
        np.testing.assert_allclose(got[v], jit[v], rtol=1e-9, atol=1e-12)
        ex = F.moving_fei(x, y, FS, N / FS)
        np.testing.assert_array_equal(ends, np.arange(N - 1, L))
        v &= ex.valid
        if i == 0:  # every bin exact: the exact FEI to round-off
            assert StreamingFEI(FS, N, 1, 1e-6, 0.05, band).K0 == N // 2 - 1
            np.testing.assert_array_equal(got[:, 4] > 0.5, ex.valid)
            np.testing.assert_allclose(got[v, 0], ex.amplitude[v], rtol=1e-9)
            np.testing.assert_allclose(got[v, 3], ex.delay[v], rtol=1e-8, atol=1e-12)
            np.testing.assert_allclose(got[v, 2], ex.f_eq[v], rtol=1e-9)
        # partial exact band: the streaming goal (1 %, 0.5 ms); none: looser (docs/fei.md)
        tol_d = 0.5e-3 if band > 0 else 3e-3
        assert np.max(np.abs(got[v, 0] / ex.amplitude[v] - 1)) < 0.01
        assert np.max(np.abs(got[v, 3] - ex.delay[v])) < tol_d

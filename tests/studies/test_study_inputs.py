"""``study compensators`` and ``study robustness`` refuse, before any trial, inputs no trial
can use: a copy of the RTHS benchmark example with its ground-motion record or its numerical
structure file missing, empty, garbage, NaN, non-monotonic, one row, a directory, a device or
a symlink loop, or with K[0, 0] = NaN — one line naming the file, exit 2 (they gave a table of
NaN and exit 0)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from tests.helpers.cli import one_line_exit_2
from tests.helpers.procs import ROOT

BENCH = ROOT / "examples" / "benchmark"


def _bad_record(path, how):
    path.unlink()
    if how == "missing":
        return
    if how == "empty":
        path.write_text("")
    elif how == "garbage":
        path.write_bytes(b"\x00\xff garbage \x01\n,,,\n")
    elif how == "nan":
        path.write_text("time_s,accel_m_s2\n0,0\n0.01,nan\n0.02,0.1\n")
    elif how == "non_monotonic":
        path.write_text("time_s,accel_m_s2\n0,0\n0.02,0.1\n0.01,0.2\n")
    elif how == "one_row":
        path.write_text("time_s,accel_m_s2\n0,0\n")
    elif how == "directory":
        path.mkdir()
    elif how == "device":
        path.symlink_to("/dev/zero")
    elif how == "loop":
        path.symlink_to(path)


def _bad_matrices(path, how):
    if how == "k_nan":
        d = dict(np.load(path))
        d["K"][0, 0] = np.nan
        np.savez(path, **d)
        return
    if how in ("nan", "non_monotonic", "one_row"):
        d = dict(np.load(path))
        if how == "nan":
            d["M"][0, 0] = np.nan
        elif how == "non_monotonic":
            d["M"] = -d["M"]  # a mass matrix that is not positive
        else:
            d = {"M": d["M"]}  # K and C missing
        np.savez(path, **d)
        return
    _bad_record(path, how)


HOWS = ["missing", "empty", "garbage", "nan", "non_monotonic", "one_row", "directory", "device",
        "loop"]  # fmt: skip


@pytest.mark.parametrize("study", ["compensators", "robustness"])
@pytest.mark.parametrize(
    ("target", "how"),
    [("el_centro.csv", h) for h in HOWS]
    + [("numerical_case1.npz", h) for h in HOWS]
    + [("numerical_case1.npz", "k_nan")],
)
def test_unusable_benchmark_inputs_are_refused_before_any_trial(
    tmp_path, capsys, study, target, how
):
    bench = tmp_path / "bench"
    shutil.copytree(BENCH, bench)
    (_bad_record if target.endswith(".csv") else _bad_matrices)(bench / target, how)
    out = tmp_path / "out"
    one_line_exit_2(
        ["study", study, str(bench / "benchmark.toml"), "--trials", "1", "--duration", "1s",
         "--workers", "1", "--no-plot", "--no-progress", "--out", str(out)],
        capsys,
        target,
    )  # fmt: skip
    assert not (out / "trials.csv").exists()

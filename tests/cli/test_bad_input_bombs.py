"""Resource bombs: refused in one line, exit 2, before anything is allocated.

Each refusal names the figure (memory, count) it was refused for. The memory figures are
checked against the arithmetic of the estimate (steps × bytes a step), so a wrong estimate or
a check after the allocation fails here (an allocation of petabytes would raise MemoryError).
"""

from __future__ import annotations

import re

import pytest

from rths_hil.resources import MAX_TRIALS, available_memory, max_workers
from tests.helpers.cli import one_line_exit_2 as _one_line_exit_2

EXAMPLE = "examples/two_actuators.toml"


def _pib(err: str) -> float:
    m = re.search(r"needs ([\d.e+]+) (\w+) of memory", err)
    assert m, err
    scale = {"GiB": 2**30, "TiB": 2**40, "PiB": 2**50, "EiB": 2**60}[m.group(2)]
    return float(m.group(1)) * scale


@pytest.mark.parametrize("mode", ["--lockstep", None])
@pytest.mark.parametrize("duration", ["1e12", "1e300"])
def test_run_duration_bomb(tmp_path, capsys, mode, duration):
    argv = ["run", "-q", "--out", str(tmp_path / "r"), "--duration", duration]
    if mode:
        argv.append(mode)
    err = _one_line_exit_2(argv, capsys, f"duration = {float(duration):g} s", "of memory")
    # 4 float64 arrays of one value a step at the default 1024 Hz
    assert _pib(err) == pytest.approx(32 * 1024 * float(duration), rel=1e-2)
    assert not (tmp_path / "r").exists()


def test_loop_duration_bomb_via_set(tmp_path, capsys):
    _one_line_exit_2(
        ["run", "-q", "--lockstep", "--out", str(tmp_path / "r"), "--set", "loop.duration=1e12"],
        capsys,
        "loop.duration = 1e+12 s",
        "of memory",
        "available",
    )


def test_a_long_run_that_fits_is_not_refused():
    """The check refuses what cannot fit, not what is long: an hour at 4096 Hz is fine."""
    from rths_hil.resources import check_memory

    check_memory(32 * 3600 * 4096, "an hour at 4096 Hz")  # 0.47 GB
    assert available_memory() > 32 * 3600 * 4096 * 2


def test_study_counts(tmp_path, capsys):
    out = str(tmp_path / "s")
    base = ["study", "robustness", EXAMPLE, "--out", out]
    _one_line_exit_2([*base, "--trials", "1000000000"], capsys, "--trials", str(MAX_TRIALS))
    _one_line_exit_2(
        [*base, "--trials", "2", "--workers", "100000"], capsys, "--workers", str(max_workers())
    )
    _one_line_exit_2(["study", "window-size", "--workers", "100000", "--out", out], capsys)
    _one_line_exit_2(
        [*base, "--trials", "2", "--duration", "1e12"], capsys, "--duration 1e+12 s", "of memory"
    )
    _one_line_exit_2([*base, "--trials", "2", "--seed", "-1"], capsys, "--seed", "-1")
    assert not (tmp_path / "s").exists()


def test_simulate_sampling_rate_bomb(tmp_path, capsys):
    err = _one_line_exit_2(
        ["simulate", "--fn", "1", "--fs", "1e9", "--out", str(tmp_path / "s.csv")],
        capsys,
        "--fs 1e+09 Hz",
        "of memory",
    )
    assert _pib(err) > 2**40  # terabytes for the bundled record at 1 GHz
    assert not (tmp_path / "s.csv").exists()


@pytest.mark.parametrize("sweep, needle", [("1:1e9:1", "1e+09 values"), ("1:inf:1", "start")])
def test_tune_sweep_bomb(tmp_path, capsys, sweep, needle):
    _one_line_exit_2(
        ["tune", "--sweep", sweep, "--out", str(tmp_path / "t")], capsys, "--sweep", needle
    )


def test_exact_hop_bomb(tmp_path, capsys):
    _one_line_exit_2(
        [
            "run",
            "-q",
            "--lockstep",
            "--duration",
            "1",
            "--out",
            str(tmp_path / "r"),
            "--set",
            "fei.exact_hop=1000000000",
        ],
        capsys,
        "fei.exact_hop = 1000000000",
        "(1024 steps)",
    )

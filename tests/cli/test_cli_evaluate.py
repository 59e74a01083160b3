"""``rths-hil evaluate`` end to end through the CLI entry point."""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay

from rths_hil.cli import main
from rths_hil.records.csvfiles import write_record

FS = 512.0


@pytest.fixture()
def record(tmp_path):
    t = np.arange(int(30 * FS)) / FS
    rng = np.random.default_rng(4)
    x = 0.01 * np.convolve(rng.standard_normal(t.size), np.hanning(400), "same")
    y = 0.97 * fractional_delay(x, 0.012, FS)
    path = tmp_path / "rec.csv"
    write_record(path, {"time": t, "target": x, "measured": y, "command": x})
    return path


def test_evaluate_prints_summary_and_writes_outputs(record, tmp_path, capsys):
    out, png = tmp_path / "w.csv", tmp_path / "f.png"
    code = main(
        [
            "evaluate",
            str(record),
            "--window",
            "4s",
            "--hop",
            "16",
            "--out",
            str(out),
            "--plot",
            str(png),
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    line = next(ln for ln in text.splitlines() if ln.startswith("FEI"))
    a = float(line.split("A = ")[1].split()[0])
    d = float(line.split("d = ")[1].split()[0])
    assert a == pytest.approx(0.97, abs=0.01)
    assert d == pytest.approx(12.0, abs=0.3)
    j1 = float(text.split("J1 = ")[1].split()[0])
    assert j1 == pytest.approx(12.0, abs=0.3)
    with open(out) as fh:
        assert fh.readline().strip() == "t_end,amplitude,phase,f_eq,delay,valid,level"
    win = np.loadtxt(out, delimiter=",", skiprows=1)
    assert win.shape == ((int(30 * FS) - int(4 * FS)) // 16 + 1, 7)
    valid = win[:, 5] > 0.5
    assert np.nanmedian(win[valid, 4]) == pytest.approx(0.012, abs=3e-4)
    assert png.stat().st_size > 10_000


def test_window_in_periods_needs_fn(record, capsys):
    assert main(["evaluate", str(record), "--window", "3T"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--fn" in err
    assert main(["evaluate", str(record), "--window", "3T", "--fn", "0.5"]) == 0


@pytest.mark.parametrize(
    "args, what",
    [
        (["--window", "40s"], "shorter than one window"),
        (["--window", "abc"], "cannot read window"),
        (["--hop", "0"], "--hop"),
        (["--fn", "-1", "--window", "3T"], "--fn"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(record, capsys, args, what):
    assert main(["evaluate", str(record), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert what in err and "\n" not in err and "Traceback" not in err


def test_bad_record_exit_2(tmp_path, capsys):
    p = tmp_path / "bad.csv"
    p.write_text("time,target,measured\n0,0,0\n0.1,nan,0\n")
    assert main(["evaluate", str(p)]) == 2
    assert f"{p}:3" in capsys.readouterr().err


def test_evaluate_against_command(record, capsys):
    assert main(["evaluate", str(record), "--pair", "command", "--hop", "64"]) == 0
    assert "measured vs command" in capsys.readouterr().out


def test_columns_it_does_not_use_may_hold_nan(tmp_path, capsys):
    """An exported run has FEI columns that are NaN until the first valid window."""
    t = np.arange(4096) / FS
    x = 0.01 * np.sin(2 * np.pi * t)
    p = tmp_path / "run.csv"
    write_record(p, {"time": t, "target": x, "measured": x, "fei_delay": np.full(t.size, np.nan)})
    assert main(["evaluate", str(p), "--window", "2s", "--hop", "64"]) == 0
    assert "A = 1.0000" in capsys.readouterr().out


def test_a_run_record_npy_exits_2_naming_export(tmp_path, capsys):
    np.save(tmp_path / "record.npy", np.zeros(10, dtype=[("time", "f8"), ("target", "f8")]))
    assert main(["evaluate", str(tmp_path / "record.npy")]) == 2
    err = capsys.readouterr().err.strip()
    assert "rths-hil export" in err and len(err.splitlines()) == 1

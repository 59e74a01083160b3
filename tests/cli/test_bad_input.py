"""Bad input gets one clear line and exit 2; a trip at step 0 exits 3; nothing leaves a traceback.

Each case is a bad input a safety reviewer tried: run through the real CLI entry
point, it must return 2 with exactly one line on stderr that names what is wrong.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.records.csvfiles import write_record
from rths_hil.units import G
from tests.helpers.cli import one_line_exit_2 as _one_line_exit_2

FS = 256.0


@pytest.fixture()
def huge_record(tmp_path):
    """A record CSV whose measured column carries one 1e300 sample."""
    t = np.arange(int(10 * FS)) / FS
    x = 0.01 * np.sin(2 * np.pi * 1.0 * t)
    y = x.copy()
    y[700] = 1e300
    path = tmp_path / "huge.csv"
    write_record(path, {"time": t, "target": x, "command": x, "measured": y})
    return path


@pytest.fixture()
def good_record(tmp_path):
    t = np.arange(int(10 * FS)) / FS
    x = 0.01 * np.sin(2 * np.pi * 1.0 * t)
    path = tmp_path / "good.csv"
    write_record(path, {"time": t, "target": x, "command": x, "measured": x})
    return path


def _spike_record(tmp_path, g_value: float):
    """A ground-motion CSV (time_s, accel_g) with one spike of ``g_value`` g."""
    t = np.arange(2000) * 0.01
    a = 0.2 * np.sin(2 * np.pi * 1.5 * t)
    a[1234] = g_value
    path = tmp_path / f"spike_{g_value:g}.csv"
    np.savetxt(path, np.column_stack([t, a]), delimiter=",", header="time_s,accel_g", comments="")
    return path


def test_record_with_1e300_is_refused_by_every_reader(huge_record, tmp_path, capsys):
    # the record's row 702 (header line 1, samples from line 2)
    for argv in (
        ["evaluate", str(huge_record)],
        ["twin", "calibrate", str(huge_record)],
        ["diagnose", str(huge_record), "--out", str(tmp_path / "dx")],
    ):
        _one_line_exit_2(argv, capsys, f"{huge_record}:702", "'measured'", "not physical")


@pytest.mark.parametrize("flag", ["--out", "--plot"])
def test_evaluate_into_a_missing_directory(good_record, tmp_path, capsys, flag):
    target = tmp_path / "missing" / ("w.csv" if flag == "--out" else "f.png")
    _one_line_exit_2(
        ["evaluate", str(good_record), "--window", "2s", flag, str(target)],
        capsys,
        flag,
        "does not exist",
    )
    assert not target.parent.exists()


def test_negative_window_says_how_to_write_it(good_record, capsys):
    err = _one_line_exit_2(["evaluate", str(good_record), "--window", "-3s"], capsys)
    assert "--window=-value" in err or "--option=-value" in err
    # written the way the message says, it reaches the window check
    _one_line_exit_2(["evaluate", str(good_record), "--window=-3s"], capsys, "--window")


@pytest.mark.parametrize("port", ["80000", "-1"])
def test_twin_serve_port_out_of_range(capsys, port):
    _one_line_exit_2(
        ["twin", "serve", "--driver", "modbus", f"--port={port}"], capsys, "0..65535", port
    )


def test_in_process_modbus_twin_with_port_out_of_range(tmp_path, capsys):
    _one_line_exit_2(
        [
            "run",
            "--lockstep",
            "--duration",
            "1",
            "-q",
            "--out",
            str(tmp_path / "r"),
            "--set",
            "driver.name=modbus",
            "--set",
            "driver.connection={port = 80000}",
        ],
        capsys,
        "driver.connection.port: must be ≤ 65535, got 80000",
    )


def test_host_0000_needs_allow_remote(capsys, caplog):
    _one_line_exit_2(
        ["twin", "serve", "--driver", "modbus", "--host", "0.0.0.0"],
        capsys,
        "0.0.0.0",
        "--allow-remote",
    )
    from rths_hil.sim_backends.twin import default_plant, start_twin

    with (
        caplog.at_level(logging.WARNING),
        start_twin("modbus", default_plant(), host="0.0.0.0", allow_remote=True) as twin,
    ):
        port = twin.connection["port"]
    msgs = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("0.0.0.0" in m and f"port {port}" in m for m in msgs), msgs


def test_run_config_host_0000_needs_allow_remote(tmp_path, capsys):
    _one_line_exit_2(
        [
            "run",
            "--lockstep",
            "--duration",
            "1",
            "-q",
            "--out",
            str(tmp_path / "r"),
            "--set",
            "driver.name=modbus",
            "--set",
            "driver.connection={host = '0.0.0.0'}",
        ],
        capsys,
        "allow_remote",
    )


@pytest.mark.parametrize("g_value", [1e6, 1e300])
def test_ground_motion_spike_is_refused(tmp_path, capsys, g_value):
    path = _spike_record(tmp_path, g_value)
    err = _one_line_exit_2(
        [
            "run",
            "--lockstep",
            "-q",
            "--out",
            str(tmp_path / "r"),
            "--set",
            f"ground_motion.record={path}",
        ],
        capsys,
        "sample 1234",
        "not a physical ground acceleration",
    )
    assert f"{g_value:.6g} g" in err
    assert not (tmp_path / "r").exists()


def test_ground_motion_of_a_real_size_is_accepted():
    from rths_hil.groundmotion import MAX_ACCEL_G, default_record

    assert np.abs(default_record().accel).max() / G < MAX_ACCEL_G / 20


def test_fei_window_longer_than_the_record(tmp_path, capsys):
    _one_line_exit_2(
        ["run", "--lockstep", "-q", "--out", str(tmp_path / "r"), "--set", "fei.window=1000s"],
        capsys,
        "fei.window",
        "never arms",
    )


def test_empty_output_dir(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _one_line_exit_2(
        ["run", "--lockstep", "--duration", "1", "-q", "--set", "output.dir="],
        capsys,
        "output.dir is empty",
    )
    _one_line_exit_2(["run", "--lockstep", "--duration", "1", "-q", "--out", ""], capsys, "--out")
    assert list(tmp_path.iterdir()) == []


def test_directory_with_old_events_is_not_reused(tmp_path, capsys):
    d = tmp_path / "old"
    d.mkdir()
    old = '{"kind": "start", "time": 0.0, "step": 0}\n'
    (d / "events.jsonl").write_text(old)
    _one_line_exit_2(
        ["run", "--lockstep", "--duration", "1", "-q", "--out", str(d)],
        capsys,
        "already holds a run",
        "events.jsonl",
    )
    assert (d / "events.jsonl").read_text() == old  # nothing appended
    # the default pattern skips such a directory instead
    from rths_hil.hybrid import new_run_dir

    assert new_run_dir(str(d)) == tmp_path / "old-1"


def test_trip_at_step_0_exits_3_with_one_line(tmp_path, capsys):
    out = tmp_path / "r"
    code = main(
        [
            "run",
            "--lockstep",
            "--duration",
            "2",
            "-q",
            "--no-plot",
            "--out",
            str(out),
            "--set",
            "safety.force_limit=1e-6",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 3, err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert "e-stop: force" in err and "(step 0)" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["trip"]["rule"] == "force" and summary["trip"]["step"] == 0
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    end = events[-1]
    assert end["kind"] == "end" and end["status"] == "trip"
    # wall_time is the ISO 8601 stamp on every event; the duration is wall_duration (s)
    from datetime import datetime

    for ev in events:
        assert datetime.fromisoformat(ev["wall_time"]).tzinfo is not None
    assert isinstance(end["wall_duration"], float) and end["wall_duration"] >= 0


def test_a_bad_record_names_where_it_was_given(tmp_path, capsys):
    """A record that cannot be read: the error names the ``--set`` item that gave it, not the
    configuration file the run read (which names another record), or the file that gave it."""
    at2 = tmp_path / "cut.AT2"  # a header of 5 samples and only 2 of them
    at2.write_text(
        "PEER NGA STRONG MOTION DATABASE RECORD\nsite, 1940\nACCELERATION TIME SERIES IN UNITS "
        "OF G\nNPTS=      5, DT=   .0100 SEC\n   .1000000E-02   .2000000E-02\n"
    )
    cfg = tmp_path / "test.toml"
    cfg.write_text('[ground_motion]\nrecord = "default"\n')
    item = f"ground_motion.record={at2}"
    line = _one_line_exit_2(
        ["run", str(cfg), "--lockstep", "--set", item, "--out", str(tmp_path / "a")],
        capsys, f"--set {item}: ground_motion.record:", "NPTS=5", "only 2 values",
    )  # fmt: skip
    assert str(cfg) not in line
    cfg.write_text(f'[ground_motion]\nrecord = "{at2}"\n')
    _one_line_exit_2(
        ["run", str(cfg), "--lockstep", "--out", str(tmp_path / "b")],
        capsys, f"{cfg}: ground_motion.record:", "only 2 values",
    )  # fmt: skip

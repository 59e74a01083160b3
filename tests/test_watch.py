"""``rths-hil watch`` without a browser: reading a growing record, channels, writer, CLI errors.

The browser tests (headless Chromium against real runs) are in ``test_watch_browser.py``.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from watch_records import AMPLITUDE, _recorder, columns_for, row_values, write_run

from rths_hil.cli import main
from rths_hil.recorder import Recorder, header_row_count, read_run
from rths_hil.watch.source import RunFollower, find_channels, find_writer


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


def test_channels_from_column_names():
    assert find_channels(["time", "target", "command", "measured", "force"]) == [""]
    names = [c[0] for c in columns_for(["left", "right"], n_dof=2)]
    assert "target_left" in names and "measured_right" in names and "u_2" in names
    assert find_channels(names) == ["left", "right"]
    # a suffix with a target but no measured column is not a channel
    assert find_channels(["time", "target_a", "measured_a", "target_b"]) == ["a"]


@pytest.mark.parametrize("channels", [[""], ["left", "right"]])
def test_follower_reads_a_growing_record_incrementally(tmp_path, monkeypatch, channels):
    fs = 256.0
    cols = columns_for(channels, n_dof=2 if channels != [""] else 1)
    run_dir = tmp_path / "run"
    f = RunFollower(run_dir)
    st = f.poll()
    assert st.phase == "missing" and "does not exist" in st.message
    run_dir.mkdir()
    st = f.poll()
    assert st.phase == "empty" and "no run record" in st.message
    rec = _recorder(run_dir, fs, cols, monkeypatch, flush_interval=0.05, extra_meta={"mode": "x"})
    rec.event("start", 0.0, 0)
    st = f.poll()
    assert st.phase == "starting" and st.rows == 0
    seen = []
    for k in range(3 * 256):
        rec.append(*row_values(cols, k, fs))
        if k % 100 == 99:
            st = f.poll()
            # never more than the header counts, never a row that is not complete on disk
            assert st.rows == header_row_count(run_dir / "record.npy") <= k + 1
            assert st.phase == "running"
            seen.append(st.rows)
    assert seen == sorted(seen) and seen[-1] > seen[0]
    assert f.channels == channels
    rec.close()
    st = f.poll()
    assert st.rows == 3 * 256
    ch = channels[-1]
    name = f"measured_{ch}" if ch else "measured"
    t = np.arange(3 * 256) / fs
    expected = AMPLITUDE[ch] * np.sin(2 * np.pi * (t - 0.005))
    np.testing.assert_allclose(np.asarray(f.record[name]), expected, rtol=1e-12, atol=1e-15)
    # no end event and nobody writing: after the record stops growing the run counts as killed
    f.stale_after = 0.0
    st = f.poll()
    assert st.phase == "killed" and "768 steps" in st.message


def test_finished_runs_states(tmp_path, monkeypatch):
    done = write_run(tmp_path / "done", monkeypatch, [""], seconds=2)
    st = RunFollower(done).poll()
    assert st.phase == "completed" and st.finished and st.rows == 512
    trip = {"rule": "fei", "reason": "|d| = 20 ms > 15 ms", "time": 1.5, "step": 384}
    tripped = write_run(
        tmp_path / "trip",
        monkeypatch,
        ["left", "right"],
        seconds=2,
        end="trip",
        trip=trip | {"channel": "right"},
    )
    st = RunFollower(tripped).poll()
    assert st.phase == "trip"
    assert "e-stop: fei on channel right at t = 1.500 s (step 384)" in st.message
    assert "|d| = 20 ms" in st.message


def test_unreadable_record_is_a_message(tmp_path):
    d = tmp_path / "bad"
    d.mkdir()
    (d / "record.npy").write_bytes(b"not a numpy file at all")
    st = RunFollower(d).poll()
    assert st.phase == "unreadable" and "unreadable record" in st.message


def test_find_writer_is_the_process_holding_the_record_open(tmp_path):
    run_dir = tmp_path / "run"
    code = (
        "import sys, time; from rths_hil.recorder import Recorder; "
        f"r = Recorder({str(run_dir)!r}, 100.0); print('open', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "open"
        assert find_writer(run_dir / "record.npy") == proc.pid
        # a reader is not a writer
        with open(run_dir / "record.npy", "rb"):
            assert find_writer(run_dir / "record.npy", hint=os.getpid()) == proc.pid
    finally:
        proc.kill()
        proc.wait()
    assert find_writer(run_dir / "record.npy") is None
    # this process writing its own record is not its own writer (the watcher never stops itself)
    with Recorder(tmp_path / "mine", 100.0):
        assert find_writer(tmp_path / "mine" / "record.npy") is None


def test_cli_errors_are_one_line_exit_2(tmp_path, capsys):
    assert main(["watch"]) == 2
    assert "RUN_DIR" in _one_line(capsys.readouterr().err)
    assert main(["watch", str(tmp_path), "--latest"]) == 2
    assert "not both" in _one_line(capsys.readouterr().err)
    assert main(["watch", "--latest", "--runs", str(tmp_path / "none")]) == 2
    assert "does not exist" in _one_line(capsys.readouterr().err)
    assert main(["watch", "--latest", "--runs", str(tmp_path)]) == 2
    assert "no run directory" in _one_line(capsys.readouterr().err)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["watch", str(tmp_path), "--port", str(port)]) == 2
        line = _one_line(capsys.readouterr().err)
        assert f"port {port}" in line and "in use" in line


def test_latest_picks_the_newest_run(tmp_path, monkeypatch):
    from rths_hil.cli.watch import latest_run

    write_run(tmp_path / "a", monkeypatch, [""], seconds=0.5)
    time.sleep(0.05)
    write_run(tmp_path / "b", monkeypatch, [""], seconds=0.5)
    (tmp_path / "not-a-run").mkdir()
    assert latest_run(tmp_path) == tmp_path / "b"
    assert len(read_run(latest_run(tmp_path)).record) == 128


def test_channel_limits_come_from_its_actuators_entry():
    from rths_hil.watch.app import channel_config

    cfg = {
        "safety": {"displacement_limit": 0.05, "force_limit": 1e5},
        "actuators": [{"name": "left", "safety": {"displacement_limit": 0.02}}, {"name": "right"}],
    }
    assert channel_config(cfg, "left")["safety"] == {"displacement_limit": 0.02, "force_limit": 1e5}
    assert channel_config(cfg, "right")["safety"] == cfg["safety"]
    assert channel_config(cfg, "")["safety"] == cfg["safety"]

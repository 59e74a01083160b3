"""``rths-hil watch`` without a browser: reading a growing record, channels, writer, CLI errors.

The browser tests (headless Chromium against real runs) are in ``test_watch_browser.py``.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.records.recorder import Recorder, header_row_count, read_run
from rths_hil.watch.source import RunFollower, find_channels, find_writer
from tests.helpers.watch_records import AMPLITUDE, _recorder, columns_for, row_values, write_run


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
        "import sys, time; from rths_hil.records.recorder import Recorder; "
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
    from rths_hil.watch.shaping import channel_config

    cfg = {
        "safety": {"displacement_limit": 0.05, "force_limit": 1e5},
        "actuators": [{"name": "left", "safety": {"displacement_limit": 0.02}}, {"name": "right"}],
    }
    assert channel_config(cfg, "left")["safety"] == {"displacement_limit": 0.02, "force_limit": 1e5}
    assert channel_config(cfg, "right")["safety"] == cfg["safety"]
    assert channel_config(cfg, "")["safety"] == cfg["safety"]


def test_meta_names_the_recording_process(tmp_path):
    with Recorder(tmp_path / "run", 100.0) as rec:
        assert rec.meta["pid"] == os.getpid()
    assert read_run(tmp_path / "run").meta["pid"] == os.getpid()


def _hold_record(run_dir, meta_pid: bool = True) -> subprocess.Popen:
    """A process recording ``run_dir`` (its Recorder open) until it is signalled.

    It takes SIGINT as Python does by default even when started with SIGINT ignored (a
    non-interactive shell starts background jobs so, and children inherit it)."""
    code = (
        "import json, signal, sys, time; from rths_hil.records.recorder import Recorder; "
        "signal.signal(signal.SIGINT, signal.default_int_handler); "
        f"r = Recorder({str(run_dir)!r}, 100.0); "
        + ("" if meta_pid else "r.meta.pop('pid'); r.update_meta(); ")
        + "print('open', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "open"
    return proc


@pytest.mark.parametrize("meta_pid", [True, False], ids=["pid in meta", "older run: /proc"])
def test_stop_signals_the_process_recording_the_run(tmp_path, meta_pid):
    run_dir = tmp_path / "run"
    proc = _hold_record(run_dir, meta_pid)
    try:
        f = RunFollower(run_dir)
        st = f.poll()
        assert f.meta_pid == (proc.pid if meta_pid else None)
        assert st.writer == proc.pid and st.phase == "starting"
        assert f.signal_writer(signal.SIGINT) == proc.pid
        # Python's default SIGINT: KeyboardInterrupt, then the process ends by that signal
        assert proc.wait(10) == -signal.SIGINT
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert f.signal_writer(signal.SIGINT) is None  # nobody left to stop


def test_a_stale_pid_in_meta_never_signals_a_stranger(tmp_path, monkeypatch):
    """The recorder's process ended; its id now names another process: that one is left alone,
    and so is a process that holds the record but is not the one the metadata names."""
    run_dir = write_run(tmp_path / "run", monkeypatch, [""], seconds=1)
    stranger = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    holder = None
    try:
        meta = json.loads((run_dir / "meta.json").read_text())
        meta["pid"] = stranger.pid
        (run_dir / "meta.json").write_text(json.dumps(meta))
        f = RunFollower(run_dir)
        f.poll()
        assert f.meta_pid == stranger.pid and f.writer is None
        assert f.signal_writer(signal.SIGINT) is None
        # a process that opened the record for writing is not the run's recorder either
        holder = subprocess.Popen(
            [
                sys.executable,
                "-c",
                f"import time; fh = open({str(run_dir / 'record.npy')!r}, 'r+b'); "
                "print('open', flush=True); time.sleep(60)",
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert holder.stdout.readline().strip() == "open"
        assert find_writer(run_dir / "record.npy") == holder.pid  # the /proc search sees it
        assert f.signal_writer(signal.SIGINT) is None  # the metadata's pid decides
        time.sleep(0.2)
        assert stranger.poll() is None and holder.poll() is None
    finally:
        for p in (stranger, holder):
            if p is not None:
                p.kill()
                p.wait()


def test_envelope_keeps_each_buckets_extremes_in_order():
    from rths_hil.watch.shaping import envelope

    rng = np.random.default_rng(1)
    for _ in range(200):
        m, n = int(rng.integers(1, 9)), int(rng.integers(0, 80))
        x = rng.normal(size=n)
        x[rng.random(n) < 0.2] = np.nan
        e = envelope(x, m).reshape(-1, 2)
        assert len(e) == n // m
        for i, (first, second) in enumerate(e):
            b = x[i * m : (i + 1) * m]
            if np.isnan(b).all():
                assert np.isnan(first) and np.isnan(second)
                continue
            lo, hi = np.nanargmin(b), np.nanargmax(b)
            assert (first, second) == ((b[lo], b[hi]) if lo <= hi else (b[hi], b[lo]))


def test_invalid_spans_read_in_pieces_match_a_whole_read():
    from rths_hil.watch.shaping import InvalidSpans

    def whole(valid: np.ndarray, gap: int) -> list[list[int]]:
        spans: list[list[int]] = []
        k = 0
        while k < valid.size:
            if valid[k]:
                k += 1
                continue
            e = k
            while e < valid.size and not valid[e]:
                e += 1
            if spans and k - spans[-1][1] < gap:
                spans[-1][1] = e
            else:
                spans.append([k, e])
            k = e
        if spans and spans[-1][1] == valid.size:
            spans[-1][1] = -1  # open: still invalid at the newest row
        return spans

    rng = np.random.default_rng(2)
    for _ in range(300):
        gap = int(rng.integers(1, 6))
        valid = np.repeat(rng.random(80) < 0.6, rng.integers(1, 5, size=80))
        tr, a = InvalidSpans(gap), 0
        while a < valid.size:
            b = min(valid.size, a + int(rng.integers(1, 25)))
            tr.update(valid[a:b], a)
            a = b
        assert tr.spans == whole(valid, gap)
    # columns: an open span reaches far right; one that ended before the window is left out
    tr = InvalidSpans(1)
    tr.update(np.array([1, 0, 0, 1, 1, 1, 0, 0], dtype=bool), 0)
    cols = tr.columns(0.0, 2.0, 0.0)
    assert cols["l"] == [0.25, 2.75] and cols["r"] == [1.25, 3.0 + InvalidSpans.OPEN]
    assert tr.columns(0.0, 2.0, 2.0) == {"l": [2.75], "r": [3.0 + InvalidSpans.OPEN]}

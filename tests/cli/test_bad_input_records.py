"""Records and run directories under bad or unusual input.

Every case runs the real CLI entry point and expects exit 2 with exactly one line on stderr
naming what is wrong (or, for the 20-channel record, that it reads back end to end).
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.records.recorder import (
    EVENTS_FILE,
    META_FILE,
    RECORD_FILE,
    header_row_count,
    read_npy_header,
    read_run,
)
from tests.helpers.cli import one_line_exit_2 as _one_line_exit_2


def many_channel_config(n: int, first_name: str | None = None) -> str:
    """A lockstep test of ``n`` actuators on an ``n``-storey shear building (the layout of
    examples/two_actuators.toml), ten CAN nodes per virtual bus."""
    masses = ", ".join(["2.0e5"] * n)
    stiff = ", ".join(["1.2e8"] * n)
    text = f"""
[structure]
kind = "shear_building"
masses = [{masses}]
stiffnesses = [{stiff}]
damping = "2%"
bouc_wen = false
k_specimen = 1.0e6
[ground_motion]
pga = 0.2
[loop]
fs = 256
duration = "0.5s"
[driver]
name = "can"
connection = {{ interface = "virtual", channel = "rths-many" }}
[twin]
enabled = true
[fei]
window = "0.5s"
"""
    for i in range(n):
        name = first_name if (first_name is not None and i == 0) else f"ch{i + 1}"
        text += f"""
[[actuators]]
name = "{name}"
dof = {i + 1}
driver = {{ connection = {{ channel = "rths-many-{i // 10}", node = {i % 10 + 1} }} }}
"""
    return text


@pytest.fixture(scope="module")
def run20(tmp_path_factory):
    """A completed 20-channel lockstep run (its record header is over 10 000 bytes); without
    its report.png (170 plots: most of the test's time, and not what it reads back)."""
    d = tmp_path_factory.mktemp("many")
    cfg = d / "c20.toml"
    cfg.write_text(many_channel_config(20))
    out = d / "run"
    code = main(["run", str(cfg), "--lockstep", "-q", "--no-plot", "--out", str(out)])
    assert code == 0
    return out


def test_twenty_channel_record_reads_back_end_to_end(run20, capsys):
    h = read_npy_header(run20 / RECORD_FILE)
    assert h.offset > 10_000  # numpy's np.load refuses this header without max_header_size
    run = read_run(run20)
    assert len(run.record) == 128 == h.rows
    names = run.record.dtype.names
    assert all(f"measured_ch{i}" in names for i in range(1, 21))
    # the twins track: each channel's measured displacement follows its target
    for i in (1, 20):
        tgt, meas = run.column(f"target_ch{i}"), run.column(f"measured_ch{i}")
        assert np.abs(tgt).max() > 0
        assert np.abs(meas - tgt).max() < np.abs(tgt).max()
    summary = json.loads((run20 / "summary.json").read_text())
    assert sorted(summary["channels"]) == sorted(f"ch{i}" for i in range(1, 21))
    capsys.readouterr()
    assert main(["export", str(run20), "--csv", "--out", str(run20 / "x")]) == 0
    csv = run20 / "x" / "record.csv"
    head = csv.read_text().splitlines()[0].split(",")
    assert head[0] == "time" and len(head) == len(names)
    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    np.testing.assert_allclose(data[:, head.index("target_ch20")], run.column("target_ch20"))
    from rths_hil.watch.source import RunFollower

    f = RunFollower(run20)
    state = f.poll()
    assert state.phase == "completed" and state.rows == 128
    assert len(f.channels) == 20


def test_channel_name_of_4000_characters(tmp_path, capsys):
    cfg = tmp_path / "long.toml"
    cfg.write_text(many_channel_config(2, first_name="a" * 4000))
    err = _one_line_exit_2(
        ["run", str(cfg), "--lockstep", "-q", "--out", str(tmp_path / "r")],
        capsys,
        "actuators[0].name",
        "1 to 32 letters",
    )
    assert len(err) < 400  # the name is abbreviated, not echoed in full
    assert not (tmp_path / "r").exists()


def _small_run(tmp_path):
    out = tmp_path / "run"
    assert main(["run", "--lockstep", "--duration", "1", "-q", "--no-plot", "--out", str(out)]) == 0
    return out


@pytest.fixture()
def small_run(tmp_path):
    return _small_run(tmp_path)


def test_hand_edited_row_count_is_refused_before_allocating(small_run, capsys):
    rec = small_run / RECORD_FILE
    rows = header_row_count(rec)
    assert rows > 0
    raw = bytearray(rec.read_bytes())
    at = raw.index(b"'shape': (") + len(b"'shape': (")
    big = b"99999999999999,)}"  # 156 TiB of rows at 176 bytes a row
    raw[at : at + len(big)] = big  # over the old digits and the header's padding
    rec.write_bytes(bytes(raw))
    _one_line_exit_2(
        ["export", str(small_run)], capsys, "header counts 99999999999999 rows", "the file holds"
    )
    from rths_hil.watch.source import RunFollower

    state = RunFollower(small_run).poll()  # the watcher names it as a state
    assert state.phase == "unreadable" and "99999999999999" in state.message


def test_garbage_in_the_npy_header(small_run, capsys):
    rec = small_run / RECORD_FILE
    raw = bytearray(rec.read_bytes())
    raw[12:40] = b"__import__('os').system('x')"[:28]
    rec.write_bytes(bytes(raw))
    _one_line_exit_2(["export", str(small_run)], capsys, str(rec), "unreadable record")
    # a header length field pointing past the end of the file
    raw = bytearray(rec.read_bytes())
    raw[8:10] = struct.pack("<H", 65535)
    rec.write_bytes(bytes(raw[:2000]))
    _one_line_exit_2(["export", str(small_run)], capsys, "header length 65535")


def test_meta_json_holding_a_list(small_run, capsys):
    (small_run / META_FILE).write_text("[1, 2, 3]\n")
    _one_line_exit_2(["export", str(small_run)], capsys, "meta.json", "expected a JSON object")


def test_events_line_that_is_json_but_not_an_object(small_run, capsys):
    ep = small_run / EVENTS_FILE
    lines = ep.read_text().splitlines()
    lines.insert(1, "[1, 2]")
    lines.insert(2, "42")
    ep.write_text("\n".join(lines) + "\n")
    _one_line_exit_2(["export", str(small_run)], capsys, "events.jsonl:2", "not a JSON object")
    from rths_hil.watch.source import RunFollower

    f = RunFollower(small_run)
    state = f.poll()  # the watcher skips and counts such lines, and goes on
    assert state.phase == "completed"
    assert f.skipped_events == 2
    assert all(isinstance(e, dict) for e in f.events) and len(f.events) == len(lines) - 2


def test_export_of_a_run_killed_before_its_first_flush(tmp_path, capsys):
    from rths_hil.records.recorder import Recorder

    d = tmp_path / "killed"
    rec = Recorder(d, fs=1024.0)
    rec.event("start", 0.0, 0)
    # kill -9 here: the header counts 0 rows; nothing more is ever written
    assert header_row_count(d / RECORD_FILE) == 0
    _one_line_exit_2(["export", str(d)], capsys, "holds no rows", "nothing to export")
    assert not (d / "record.csv").exists()
    rec.close()

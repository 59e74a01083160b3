"""Record CSV reading: every defect is one InputError naming file and row."""

from __future__ import annotations

import numpy as np
import pytest

from rths_hil.errors import InputError
from rths_hil.records.csvfiles import read_record, write_record


def write(tmp_path, text, name="r.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_round_trip(tmp_path):
    t = np.arange(100) / 256.0
    cols = {"time": t, "target": np.sin(t), "measured": np.cos(t), "force": 3 * t}
    write_record(tmp_path / "a.csv", cols)
    rec = read_record(tmp_path / "a.csv")
    assert rec.fs == pytest.approx(256.0)
    assert rec.names == ["time", "target", "measured", "force"]
    np.testing.assert_allclose(rec["measured"], np.cos(t), rtol=1e-8)
    only = read_record(tmp_path / "a.csv", optional=())
    assert "force" not in only


@pytest.mark.parametrize(
    "text, where, what",
    [
        ("time,target\n0,1\n1,2\n", ":1:", "missing column"),
        ("time,target,measured\n0,1,1\n0.1,x,1\n", ":3:", "not a number"),
        ("time,target,measured\n0,1,1\n0.1,nan,1\n", ":3:", "non-finite"),
        ("time,target,measured\n0,1,1\n0.1,1,1\n0.1,1,1\n", ":4:", "strictly increasing"),
        (
            "time,target,measured\n0,1,1\n0.1,1,1\n0.2,1,1\n0.3,1,1\n0.45,1,1\n",
            ":6:",
            "non-uniform",
        ),
        ("time,target,measured\n0,1,1\n0.1,1\n", ":3:", "expected 3 values"),
        ("time,target,measured\n0,1,1\n", "", "need at least"),
        ("", "", "empty file"),
    ],
)
def test_defects_name_file_and_row(tmp_path, text, where, what):
    p = write(tmp_path, text)
    with pytest.raises(InputError) as err:
        read_record(p)
    msg = str(err.value)
    assert str(p) in msg and what in msg and where in msg
    assert "\n" not in msg


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="cannot open"):
        read_record(tmp_path / "nope.csv")


def test_a_run_record_npy_or_run_directory_says_how_to_export(tmp_path):
    """A run's binary record or its directory: one line naming ``rths-hil export``."""
    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "record.npy", np.zeros(10, dtype=[("time", "f8"), ("target", "f8")]))
    for path in (run / "record.npy", run):
        with pytest.raises(InputError) as err:
            read_record(path)
        msg = str(err.value)
        assert f"rths-hil export {run}" in msg and str(run / "record.csv") in msg
        assert "\n" not in msg and "codec" not in msg

"""A damaged run directory is refused in one line where reading it would lose data silently:
metadata or events that are there but unreadable, a MATLAB/HDF5 export without the units,
a summary without the metadata, an empty column list, metadata nested past any parser."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
import scipy.io

import rths_hil
from rths_hil.errors import InputError
from rths_hil.records.recorder import export_run, read_run
from tests.helpers.cli import one_line_exit_2
from tests.helpers.loop import run_loop


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs") / "base"
    r = run_loop(d, None, "loop.duration=0.1", mode="lockstep")
    assert r.result.status == "completed" and len(r.run.events) > 0
    return d


def _copy(base, tmp_path, name="run"):
    d = tmp_path / name
    shutil.copytree(base, d)
    return d


def _damage(d, how):
    meta, events = d / "meta.json", d / "events.jsonl"
    if how == "meta_dir":
        meta.unlink()
        meta.mkdir()
    elif how == "meta_loop":
        meta.unlink()
        meta.symlink_to("meta.json")
    elif how == "events_loop":
        events.unlink()
        events.symlink_to("events.jsonl")
    elif how == "events_dir":
        events.unlink()
        events.mkdir()


@pytest.mark.parametrize(
    ("how", "needle"),
    [
        ("meta_dir", "meta.json: not a readable file (a directory)"),
        ("meta_loop", "meta.json: not a readable file (Too many levels of symbolic links)"),
        ("events_loop", "events.jsonl: not a readable file (Too many levels of symbolic links)"),
        ("events_dir", "events.jsonl: not a readable file (a directory)"),
    ],
)
@pytest.mark.parametrize("fmt", ["--csv", "--mat", "--hdf5"])
def test_unreadable_metadata_or_events_are_refused_by_every_export(
    base, tmp_path, capsys, how, needle, fmt
):
    d = _copy(base, tmp_path)
    _damage(d, how)
    one_line_exit_2(["export", str(d), fmt, "--out", str(tmp_path / "o")], capsys, needle)
    assert not list((tmp_path / "o").glob("record.*"))
    with pytest.raises(InputError, match="not a readable file"):
        rths_hil.open_run(d)


@pytest.mark.parametrize("fmt", ["--mat", "--hdf5"])
def test_mat_and_hdf5_need_the_units(base, tmp_path, capsys, fmt):
    d = _copy(base, tmp_path)
    (d / "meta.json").unlink()
    one_line_exit_2(["export", str(d), fmt, "--out", str(tmp_path / "o")], capsys,
                    "meta.json: missing or empty")  # fmt: skip
    # CSV carries no units or events: the record alone is still exported
    (p,) = export_run(d, csv=True, out_dir=tmp_path / "o")
    assert p.name == "record.csv" and len(p.read_text().splitlines()) == 1 + len(read_run(d).record)
    # truncated metadata: columns without a unit
    d2 = _copy(base, tmp_path, "trunc")
    meta = json.loads((d2 / "meta.json").read_text())
    kept = meta["columns"][:3]
    meta["columns"] = kept
    (d2 / "meta.json").write_text(json.dumps(meta))
    lost = [n for n in read_run(d2).record.dtype.names if n not in {c["name"] for c in kept}]
    one_line_exit_2(["export", str(d2), fmt, "--out", str(tmp_path / "o2")], capsys,
                    f"no unit for column(s) {', '.join(lost[:5])}")  # fmt: skip
    # the same columns the metadata describes are exported with their units
    names = [c["name"] for c in kept]
    export_run(d2, csv=False, mat=True, out_dir=tmp_path / "o3", columns=names)
    mat = scipy.io.loadmat(tmp_path / "o3" / "record.mat", squeeze_me=True)
    want = {c["name"]: c["unit"] for c in kept}
    for n in names:
        assert mat["units"][n].item() == want[n], n
    assert np.allclose(mat["record"]["time"].item(), read_run(d2).record["time"])


def test_an_empty_column_list_is_refused(base, tmp_path, capsys):
    one_line_exit_2(["export", str(base), "--columns", ",,,", "--out", str(tmp_path / "o")],
                    capsys, "--columns ',,,': no column name")  # fmt: skip
    assert not (tmp_path / "o").exists()


def test_a_summary_needs_the_metadata(base, tmp_path):
    d = _copy(base, tmp_path)
    (d / "meta.json").unlink()
    run = rths_hil.open_run(d)  # the record is still readable
    assert len(run.record) == len(read_run(base).record)
    with pytest.raises(InputError, match=r"meta.json: missing or empty: .* cannot be summarised"):
        run.summary()


@pytest.mark.parametrize("which", ["meta.json", "events.jsonl"])
def test_metadata_nested_past_the_parser_is_one_line(base, tmp_path, capsys, which):
    d = _copy(base, tmp_path)
    deep = "[" * 200_000 + "]" * 200_000
    if which == "meta.json":
        text = (d / which).read_text().rstrip()
        (d / which).write_text(text[:-1] + ', "deep": ' + deep + "}")
        needle = "meta.json: unreadable metadata (nested too deeply)"
    else:
        with open(d / which, "a") as fh:
            fh.write('{"kind": "x", "deep": ' + deep + "}\n" + '{"kind": "y"}\n')
        needle = "malformed event line (nested too deeply)"
    for fmt in ("--csv", "--mat", "--hdf5"):
        one_line_exit_2(["export", str(d), fmt, "--out", str(tmp_path / "o")], capsys, needle)
    with pytest.raises(InputError, match=r"nested too deeply"):
        _ = rths_hil.open_run(d).record
    assert os.path.exists(d / "record.npy")

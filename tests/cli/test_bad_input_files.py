"""File-system errors and races: one line, exit 2, no traceback."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.errors import InputError
from rths_hil.records.recorder import RECORD_FILE, Recorder
from tests.helpers.cli import one_line_exit_2 as _one_line_exit_2

# file-system errors and races between processes, in lockstep: no test here depends on the wall
# clock (they run with the parallel tests, not under the "timing" marker)

LONG = "a" * 300  # one path component over the 255-byte limit of Linux file systems
RUN = ["run", "--lockstep", "--duration", "1", "-q", "--no-plot"]


def test_two_processes_into_one_out_at_the_same_instant(tmp_path):
    out = tmp_path / "same"
    argv = [sys.executable, "-m", "rths_hil", *RUN, "--out", str(out)]
    procs = [
        subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    results = [(p.wait(timeout=120), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    err = next(e for code, e in results if code == 2)
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if not ln.startswith("WARNING")]
    assert len(lines) == 1 and "already holds a run" in lines[0], err


def test_recorders_racing_for_one_directory(tmp_path):
    """Eight recorders created at one instant in one directory: exactly one claims it."""
    d = tmp_path / "race"
    barrier = threading.Barrier(8)
    won, refused = [], []

    def claim():
        barrier.wait()
        try:
            won.append(Recorder(d, fs=1024.0))
        except InputError as exc:
            refused.append(str(exc))

    threads = [threading.Thread(target=claim) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(won) == 1 and len(refused) == 7
    assert all("already holds a run" in m for m in refused)
    won[0].close()


def test_output_dir_component_too_long(tmp_path, capsys):
    _one_line_exit_2(
        [*RUN, "--set", f"output.dir={tmp_path / LONG}"], capsys, "output.dir", "too long"
    )
    _one_line_exit_2([*RUN, "--out", str(tmp_path / LONG)], capsys, "too long")


def test_ground_motion_path_component_too_long(tmp_path, capsys):
    _one_line_exit_2(
        [
            *RUN,
            "--out",
            str(tmp_path / "r"),
            "--set",
            f"ground_motion.record={tmp_path / LONG}.csv",
        ],
        capsys,
        "ground_motion.record",
        "too long",
    )
    assert not (tmp_path / "r").exists()


def test_output_dir_under_a_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    _one_line_exit_2(
        [*RUN, "--out", str(tmp_path / "afile" / "sub")], capsys, "afile", "Not a directory"
    )


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("files") / "run"
    assert main([*RUN, "--duration", "2", "--out", str(out)]) == 0
    return out


def test_export_onto_a_full_disk(run_dir, tmp_path, capsys):
    d = tmp_path / "full"
    d.mkdir()
    os.symlink("/dev/full", d / "record.csv")
    _one_line_exit_2(
        ["export", str(run_dir), "--out", str(d)], capsys, "record.csv", "No space left"
    )
    _one_line_exit_2(["export", str(run_dir), "--out", "/dev/full"], capsys, "/dev/full")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_export_into_a_read_only_run_dir(run_dir, tmp_path, capsys):
    import shutil

    ro = tmp_path / "ro"
    shutil.copytree(run_dir, ro)
    ro.chmod(0o555)
    try:
        _one_line_exit_2(["export", str(ro)], capsys, "record.csv", "Permission denied")
    finally:
        ro.chmod(0o755)


def test_export_hdf5_while_another_process_holds_the_file(run_dir, tmp_path, capsys):
    pytest.importorskip("h5py")
    out = tmp_path / "h5"
    assert main(["export", str(run_dir), "--hdf5", "--out", str(out)]) == 0
    capsys.readouterr()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import h5py, sys, time; f = h5py.File(sys.argv[1], 'r'); print('open', flush=True); "
            "time.sleep(60)",
            str(out / "record.h5"),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "open"
        err = _one_line_exit_2(
            ["export", str(run_dir), "--hdf5", "--out", str(out)], capsys, "record.h5"
        )
        assert "lock" in err or "already open" in err, err
    finally:
        holder.kill()
        holder.wait()


def test_evaluate_plot_onto_a_full_disk(run_dir, capsys):
    assert main(["export", str(run_dir)]) == 0
    capsys.readouterr()
    _one_line_exit_2(
        ["evaluate", str(run_dir / "record.csv"), "--window", "1s", "--plot", "/dev/full"],
        capsys,
        "/dev/full",
        "No space left",
    )


def test_record_of_the_run_is_intact(run_dir):
    rec = np.load(run_dir / RECORD_FILE)  # a single-channel record: plain numpy reads it too
    assert len(rec) == 2048


@pytest.mark.parametrize("kind", ["fifo", "/dev/zero"])
def test_config_or_record_that_is_not_a_regular_file(tmp_path, capsys, kind):
    if kind == "fifo":
        path = tmp_path / "c.toml"
        os.mkfifo(path)  # no writer: a plain read would block for ever
        what = "a FIFO"
    else:
        path, what = kind, "a device"
    _one_line_exit_2(["run", str(path), "--lockstep"], capsys, str(path), "regular file", what)
    _one_line_exit_2(["evaluate", str(path)], capsys, str(path), "regular file", what)
    _one_line_exit_2(["tune", str(path)], capsys, str(path), "regular file", what)

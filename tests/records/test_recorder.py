"""Crash-safe recorder: growing .npy, events, metadata, kill -9, export."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from rths_hil.errors import InputError
from rths_hil.records.recorder import (
    COLUMNS,
    Recorder,
    _header_bytes,
    export_run,
    header_row_count,
    read_run,
    record_dtype,
)
from tests.helpers.records import row as _row

# The recorder in-process runs with the parallel tests; the paced writer killed (-9) runs apart
# from them (the "timing" marker, pyproject.toml; make test).

NAMES = [c[0] for c in COLUMNS]


def _expected(n: int) -> np.ndarray:
    arr = np.zeros(n, dtype=record_dtype())
    for k in range(n):
        arr[k] = _row(k)
    return arr


def test_rows_are_on_disk_after_each_flush_and_header_counts_them(tmp_path):
    rec = Recorder(tmp_path / "run", fs=1024.0, flush_interval=0.05)
    assert rec.flush_rows == 51  # floor(0.05 s · 1024 Hz)
    for k in range(130):
        rec.append(*_row(k))
    # two full chunks written; the rest is still in memory
    assert rec.rows == 102 and header_row_count(rec.path) == 102
    data = np.load(rec.path)  # read while the recorder is open
    np.testing.assert_array_equal(data, _expected(102))
    rec.close()
    data = np.load(rec.path)
    assert data.dtype.names == tuple(NAMES)
    np.testing.assert_array_equal(data, _expected(130))


def test_a_reader_never_sees_more_rows_counted_than_written(tmp_path):
    """A reader following a record that is being written (the live view, a test waiting for
    rows) reads the header, then the file's size: the writer appends its rows before it
    patches their count, so every counted row is in the file (read the other way round, the
    size could be older than the count: "the header counts 663 rows but the file holds 612")."""
    import threading

    from rths_hil.records.recorder import read_npy_header

    rec = Recorder(tmp_path / "run", fs=1000.0, flush_interval=0.001)  # a flush a row
    done = threading.Event()

    def write() -> None:
        for k in range(20000):
            rec.append(*_row(k))
        done.set()

    t = threading.Thread(target=write)
    t.start()
    reads = 0
    try:
        while not done.is_set():
            read_npy_header(rec.path)  # InputError when the count ran ahead of the data
            reads += 1
    finally:
        t.join()
        rec.close()
    assert reads > 100 and header_row_count(rec.path) == 20000


def test_patched_header_equals_a_freshly_built_one(tmp_path):
    """Only the row count is rewritten; the header must be byte for byte the full rebuild."""
    rec = Recorder(tmp_path / "run", fs=1000.0, flush_interval=0.001)
    assert rec.flush_rows == 1
    hlen = rec._header_len
    for k in range(1, 1005):  # through 1 → 2, 2 → 3 and 3 → 4 digits
        rec.append(*_row(k - 1, 1000.0))
        if k in (1, 9, 10, 11, 99, 100, 101, 999, 1000, 1004):
            with open(rec.path, "rb") as fh:
                raw = fh.read(hlen)
                assert raw == _header_bytes(rec._descr, k, hlen)
                fh.seek(0)
                np.lib.format.read_magic(fh)
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            assert shape == (k,) and not fortran and dtype == record_dtype()
    rec.close()
    np.testing.assert_array_equal(np.load(rec.path)["step"], _expected(1004)["step"])


def test_pandas_reads_the_record_with_column_names(tmp_path):
    pd = pytest.importorskip("pandas")
    with Recorder(tmp_path / "run", fs=100.0) as rec:
        for k in range(20):
            rec.append(*_row(k, 100.0))
    df = pd.DataFrame(np.load(tmp_path / "run" / "record.npy"))
    assert list(df.columns) == NAMES and len(df) == 20
    assert df["time"].iloc[-1] == pytest.approx(19 / 100.0)


def test_bytes_beyond_the_counted_rows_are_ignored(tmp_path):
    rec = Recorder(tmp_path / "run", fs=1024.0, flush_interval=0.01)
    for k in range(40):
        rec.append(*_row(k))
    rows = rec.rows
    # a torn write: half a row after the counted rows (what a kill during write() leaves)
    os.write(rec._fd, b"\x01" * (record_dtype().itemsize // 2))
    np.testing.assert_array_equal(np.load(rec.path), _expected(rows))
    os.close(rec._fd)
    rec.closed = True


def test_events_are_flushed_immediately_and_meta_written_first(tmp_path):
    rec = Recorder(tmp_path / "run", fs=1024.0, config={"loop": {"fs": 1024.0}})
    meta = json.loads((tmp_path / "run" / "meta.json").read_text())
    assert meta["config"] == {"loop": {"fs": 1024.0}}
    assert meta["fs"] == 1024.0 and "numpy" in meta["versions"] and meta["start_time"]
    assert [c["name"] for c in meta["columns"]] == NAMES
    rec.event("trip", time=1.5, step=1536, rule="fei", values={"delay": float("nan")})
    lines = (tmp_path / "run" / "events.jsonl").read_text().splitlines()  # before close
    ev = json.loads(lines[-1])
    assert ev["kind"] == "trip" and ev["step"] == 1536 and ev["values"]["delay"] == "nan"
    rec.close()


def test_existing_record_is_refused(tmp_path):
    Recorder(tmp_path / "run", fs=10.0).close()
    with pytest.raises(InputError, match="already holds a run"):
        Recorder(tmp_path / "run", fs=10.0)
    with pytest.raises(InputError, match="flush interval"):
        Recorder(tmp_path / "run2", fs=10.0, flush_interval=0.5)


@pytest.mark.timing
def test_kill_9_leaves_every_flushed_row_readable(tmp_path):
    run = tmp_path / "run"
    script = textwrap.dedent(
        f"""
        import sys, time
        sys.path.insert(0, {str(os.getcwd())!r})
        from tests.helpers.records import row as _row
        from rths_hil.records.recorder import Recorder
        rec = Recorder({str(run)!r}, fs=1000.0, flush_interval=0.05)
        k = 0
        t0 = time.perf_counter()
        while True:
            while time.perf_counter() < t0 + k / 1000.0:
                pass
            rec.append(*_row(k, 1000.0))
            if k == 100:
                print("ready", flush=True)
            k += 1
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(0.6)
    t_kill = time.perf_counter()
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    run_data = read_run(run)
    n = len(run_data.record)
    # paced at 1 kHz, started ~0.1 s before "ready": at least 0.6 s more was flushed up to 0.05 s
    assert n >= 600, n
    expected = np.zeros(n, dtype=record_dtype())
    for k in range(n):
        expected[k] = _row(k, 1000.0)
    np.testing.assert_array_equal(run_data.record, expected)
    assert time.perf_counter() - t_kill < 5


def test_read_run_tolerates_a_truncated_last_event_line(tmp_path):
    with Recorder(tmp_path / "run", fs=10.0) as rec:
        rec.append(*_row(0, 10.0))
        rec.event("start", time=0.0, step=0)
    with open(tmp_path / "run" / "events.jsonl", "a") as fh:
        fh.write('{"kind": "tri')
    run = read_run(tmp_path / "run")
    assert [e["kind"] for e in run.events] == ["start"]
    with pytest.raises(InputError, match="not a run directory"):
        read_run(tmp_path)


def test_export_csv_and_hdf5(tmp_path):
    with Recorder(tmp_path / "run", fs=1024.0) as rec:
        for k in range(300):
            rec.append(*_row(k))
        rec.event("end", time=300 / 1024, step=299)
    files = export_run(tmp_path / "run", csv=True, hdf5=True)
    assert [f.name for f in files] == ["record.csv", "record.h5"]
    with open(files[0]) as fh:
        header = fh.readline().strip().split(",")
    assert header == NAMES
    data = np.loadtxt(files[0], delimiter=",", skiprows=1)
    exp = _expected(300)
    for j, name in enumerate(NAMES):
        np.testing.assert_allclose(data[:, j], exp[name].astype(float), rtol=1e-9, atol=1e-15)
    h5py = pytest.importorskip("h5py")
    with h5py.File(files[1]) as h5:
        np.testing.assert_array_equal(h5["record/target"][()], exp["target"])
        assert h5["record/target"].attrs["unit"] == "m"
        assert json.loads(h5.attrs["events"])[0]["kind"] == "end"

"""Crash-safe run records: a growing NumPy ``.npy`` file, an event log and metadata.

A run directory holds

``record.npy``
    One row per loop step, a structured dtype with named columns (:data:`COLUMNS`, SI units).
    Rows are packed into a small in-memory chunk and written with one ``write`` system call
    every ``flush_rows`` steps (≤ 0.1 s of loop time); after each data write the row count in
    the file's fixed-size ``.npy`` header is patched in place (``pwrite`` of the digits only;
    the header is built once). The header therefore
    never claims a row that is not on disk: after ``kill -9`` (the
    data is in the OS page cache) ``np.load`` reads every flushed row; bytes of a data write
    that the kill interrupted lie beyond the counted rows and are ignored by ``np.load``.
    ``pandas.DataFrame(np.load("record.npy"))`` gives a table with the column names.
``events.jsonl``
    One JSON object per line, appended and flushed immediately: ``start``, ``trip``,
    ``operator_stop``, ``end`` and notices, each with loop ``time`` (s), ``step`` and the wall
    clock ``wall_time`` (ISO 8601, UTC).
``meta.json``
    Written (atomically) before the first step: the resolved configuration, package versions,
    start time, sampling rate, the column table (name, dtype, unit, description), a
    description of the format and the id of the process writing the record (``pid``: what
    ``rths-hil watch`` signals for an operator stop, after checking that this process still
    holds ``record.npy`` open for writing).

:func:`read_run` reads a (possibly crashed) run directory back, and :func:`export_run` writes
``record.csv`` (the record CSV of :mod:`rths_hil.records.csvfiles`,
``time`` first, same column names)
and, when ``h5py`` is importable, ``record.h5``. See ``docs/records.md``.
"""

from __future__ import annotations

import ast
import contextlib
import datetime as _dt
import functools
import json
import logging
import math
import os
import platform
import struct
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..formats import json_safe
from .columns import single_channel_columns

__all__ = [
    "COLUMNS",
    "EVENTS_FILE",
    "META_FILE",
    "RECORD_FILE",
    "RUN_FILES",
    "RecordWriteError",
    "Recorder",
    "RunData",
    "export_run",
    "package_versions",
    "read_run",
    "record_dtype",
]

log = logging.getLogger(__name__)

RECORD_FILE = "record.npy"
EVENTS_FILE = "events.jsonl"
META_FILE = "meta.json"
#: The files whose presence marks a directory as holding a run (never reused).
RUN_FILES = (RECORD_FILE, EVENTS_FILE, META_FILE)


class RecordWriteError(RuntimeError):
    """The record could not be written (disk full, file-size limit, device gone).

    The loop treats it as a safety event: e-stop, keep what was flushed, exit 3. After it the
    :class:`Recorder` writes nothing more to ``record.npy``; the rows counted in its header
    (:attr:`Recorder.rows`) are intact.
    """


#: The columns of a single-channel record up to ``seq``: (name, numpy dtype, unit,
#: description), in file order; the default of :class:`Recorder`. Defined with every other
#: column in :data:`rths_hil.records.columns.TABLE`.
COLUMNS: tuple[tuple[str, str, str, str], ...] = single_channel_columns()

_STRUCT_CODES = {"<f8": "d", "<i8": "q", "|b1": "?"}
_MAGIC = b"\x93NUMPY\x01\x00"
_HEADER_ALIGN = 64


def record_dtype(columns: Sequence[tuple[str, str, str, str]] = COLUMNS) -> np.dtype:
    """The structured dtype of ``record.npy`` (packed, little-endian)."""
    return np.dtype([(name, code) for name, code, _, _ in columns])


def _header_bytes(descr, rows: int, total_len: int | None = None) -> bytes:
    """A ``.npy`` v1.0 header for ``rows`` rows padded to ``total_len`` bytes (or aligned)."""
    text = repr({"descr": descr, "fortran_order": False, "shape": (int(rows),)})
    body = text.encode("latin1")
    if total_len is None:
        # room for the largest row count we could ever write, then 64-byte alignment
        probe = repr({"descr": descr, "fortran_order": False, "shape": (10**18,)})
        need = len(_MAGIC) + 2 + len(probe.encode("latin1")) + 1
        total_len = -(-need // _HEADER_ALIGN) * _HEADER_ALIGN
    hlen = total_len - len(_MAGIC) - 2
    pad = hlen - len(body) - 1
    if pad < 0 or hlen > 65535:
        raise ValueError("record header does not fit")
    return _MAGIC + struct.pack("<H", hlen) + body + b" " * pad + b"\n"


def package_versions() -> dict[str, str]:
    """Versions of Python, the platform and the packages a run depends on (a new dict)."""
    return dict(_package_versions())


@functools.cache
def _package_versions() -> dict[str, str]:
    """Read once per process: installed versions do not change under a running process, and
    the metadata lookups cost about 50 ms, on every run of a study or a test session."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in (
        "rths_hil",
        "numpy",
        "scipy",
        "python-can",
        "cantools",
        "pymodbus",
        "pyserial",
        "filterpy",
        "cobs",
        "matplotlib",
    ):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="microseconds")


def _write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(json_safe(data, "name"), fh, indent=2, default=repr, allow_nan=False)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class Recorder:
    """Write a run directory while the loop runs (see the module docstring for the format).

    Parameters
    ----------
    run_dir : str or Path
        Directory to create (parents too). Existing record files in it are an error.
    fs : float
        Loop rate in Hz (stored in the metadata; sets the default flush size).
    config : dict, optional
        The resolved configuration, stored in ``meta.json``.
    flush_interval : float
        Loop time between data flushes in s (0 < interval ≤ 0.1).
    extra_meta : dict, optional
        More metadata keys.
    columns : sequence of (name, dtype, unit, description)
        The record's columns (default :data:`COLUMNS`, a single-channel test; the runner
        passes its plan's, :func:`rths_hil.records.columns.specs`).

    Notes
    -----
    :meth:`append` takes one value per column of ``columns``, positionally, in order; it packs
    them with :meth:`struct.Struct.pack_into` into a preallocated chunk (about 0.5 µs) and writes
    the chunk when it is full. Use it as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        run_dir: str | Path,
        fs: float,
        config: dict | None = None,
        flush_interval: float = 0.05,
        extra_meta: dict | None = None,
        columns: Sequence[tuple[str, str, str, str]] = COLUMNS,
    ) -> None:
        if not (0 < flush_interval <= 0.1):
            raise InputError(f"recorder flush interval must be in (0, 0.1] s, got {flush_interval}")
        if not (fs > 0 and math.isfinite(fs)):
            raise InputError(f"recorder: sampling rate must be > 0 Hz, got {fs}")
        self.run_dir = Path(run_dir)
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(
                f"cannot create run directory {self.run_dir}: {exc.strerror}"
            ) from None
        self.path = self.run_dir / RECORD_FILE
        for name in RUN_FILES:
            if (self.run_dir / name).exists():
                raise InputError(
                    f"{self.run_dir} already holds a run ({name}): choose a new output directory"
                )
        self.fs = float(fs)
        self.columns = tuple((name, code, unit, doc) for name, code, unit, doc in columns)
        self.dtype = record_dtype(self.columns)
        self._descr = np.lib.format.dtype_to_descr(self.dtype)
        try:
            header = _header_bytes(self._descr, 0)
        except ValueError:
            raise InputError(
                f"recorder: {len(self.columns)} columns do not fit a record header (64 KiB): "
                "fewer channels"
            ) from None
        self._header_len = len(header)
        # the row count is the only part of the header that changes: its digits start right
        # after "'shape': (" and are followed by ",)}" and the padding (rows only grow, so
        # writing the new digits and ",)}" over the old ones gives the full new header)
        self._count_at = header.index(b"'shape': (") + len(b"'shape': (")
        fmt = "<" + "".join(_STRUCT_CODES[c] for _, c, _, _ in self.columns)
        self._struct = struct.Struct(fmt)
        assert self._struct.size == self.dtype.itemsize
        self._rowsize = self._struct.size
        self.flush_rows = max(1, math.floor(flush_interval * fs))
        self._chunk = bytearray(self._rowsize * self.flush_rows)
        self._chunk_end = len(self._chunk)
        self._pack = self._struct.pack_into
        self._off = 0
        self.rows = 0  # rows on disk and counted in the header
        # the exclusive create is the claim on the directory: of two runs started at the same
        # instant into one directory, exactly one creates record.npy, the other is refused
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise InputError(
                f"{self.run_dir} already holds a run ({RECORD_FILE}): choose a new output directory"
            ) from None
        except OSError as exc:
            raise InputError(f"cannot create {self.path}: {exc.strerror}") from None
        try:
            os.write(self._fd, header)
            self._events = open(self.run_dir / EVENTS_FILE, "x", encoding="utf-8")
        except OSError as exc:
            os.close(self._fd)
            with contextlib.suppress(OSError):
                os.unlink(self.path)
            if isinstance(exc, FileExistsError):
                raise InputError(
                    f"{self.run_dir} already holds a run ({EVENTS_FILE}): choose a new output "
                    "directory"
                ) from None
            raise InputError(
                f"cannot create the record in {self.run_dir}: {exc.strerror}"
            ) from None
        self.failed: str | None = None  # why writing stopped (RecordWriteError), else None
        self.start_time = _now_iso()
        meta = {
            "format": "rths_hil run directory v1 (see docs/records.md)",
            "start_time": self.start_time,
            "pid": os.getpid(),
            "fs": self.fs,
            "dt": 1.0 / self.fs,
            "record": RECORD_FILE,
            "events": EVENTS_FILE,
            "flush_interval": self.flush_rows / self.fs,
            "columns": [
                {"name": n, "dtype": c, "unit": u, "description": d} for n, c, u, d in self.columns
            ],
            "versions": package_versions(),
            "config": config or {},
        }
        if extra_meta:
            meta.update(extra_meta)
        self.meta = meta
        _write_json_atomic(self.run_dir / META_FILE, meta)
        self.closed = False
        # bound method the loop calls once per step
        self.append = self._append

    # -- step path -------------------------------------------------------------------------
    def _append(self, *values) -> None:
        """Append one row (one value per column of :attr:`columns`, in order)."""
        off = self._off
        self._pack(self._chunk, off, *values)
        off += self._rowsize
        self._off = off
        if off == self._chunk_end:
            self.flush()

    # -- slow path ---------------------------------------------------------------------------
    def flush(self) -> None:
        """Write the buffered rows, then patch the header's row count (digits only).

        Raises
        ------
        RecordWriteError
            The write failed (disk full, file-size limit …). Every complete row that reached
            the file is counted in the header; nothing more is written afterwards.
        """
        n = self._off
        if n == 0 or self.closed or self.failed is not None:
            return
        fd = self._fd
        written = 0
        try:
            written = os.write(fd, self._chunk if n == self._chunk_end else self._chunk[:n])
            if written < n:  # a short write to a regular file: the disk is (nearly) full
                view = memoryview(self._chunk)[:n]
                while written < n:
                    written += os.write(fd, view[written:])
        except OSError as exc:
            rows = self.rows + written // self._rowsize  # complete rows that reached the file
            self._fail(exc, rows)
        self.rows += n // self._rowsize
        self._off = 0
        try:
            os.pwrite(fd, b"%d,)}" % self.rows, self._count_at)
        except OSError as exc:
            self._fail(exc, self.rows)

    def _fail(self, exc: OSError, rows: int) -> None:
        """Stop writing; keep the header counting ``rows``; raise :class:`RecordWriteError`."""
        self.failed = f"{exc.strerror or exc}"
        self._off = 0
        self.rows = rows
        with contextlib.suppress(OSError):
            os.pwrite(self._fd, b"%d,)}" % rows, self._count_at)
        log.info("record write failed: %s (%d rows kept in %s)", self.failed, rows, self.path)
        raise RecordWriteError(
            f"cannot write the record ({self.failed}); {rows} rows kept in {self.path}"
        ) from None

    def event(self, kind: str, time: float = math.nan, step: int = -1, **fields) -> dict:
        """Append an event line to ``events.jsonl`` and flush it to the OS immediately."""
        ev = {"kind": kind, "time": time, "step": step, **fields, "wall_time": _now_iso()}
        line = json.dumps(json_safe(ev, "name"), default=repr, allow_nan=False) + "\n"
        try:
            self._events.write(line)
            self._events.flush()
        except OSError as exc:  # disk full: the event is lost, the run must still stop cleanly
            if self.failed is None:
                self.failed = f"{exc.strerror or exc}"
            log.error("cannot write event %r to %s: %s", kind, EVENTS_FILE, exc.strerror or exc)
        return ev

    def update_meta(self, **fields) -> None:
        """Add keys to ``meta.json`` (rewritten atomically)."""
        self.meta.update(fields)
        _write_json_atomic(self.run_dir / META_FILE, self.meta)

    def close(self) -> None:
        """Flush the last rows and close the files (idempotent)."""
        if self.closed:
            return
        try:
            with contextlib.suppress(RecordWriteError):
                self.flush()
            with contextlib.suppress(OSError):
                os.fsync(self._fd)
        finally:
            self.closed = True
            os.close(self._fd)
            with contextlib.suppress(OSError):
                self._events.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class RunData:
    """A run directory read back.

    Attributes
    ----------
    record : ndarray
        Structured array, one row per flushed step (``record["target"]`` …).
    events : list of dict
        The event log, in order.
    meta : dict
        ``meta.json``.
    path : Path
        The run directory.
    """

    record: np.ndarray
    events: list[dict]
    meta: dict
    path: Path

    @property
    def fs(self) -> float:
        """Loop rate in Hz."""
        fs = self.meta.get("fs")
        if fs is not None:
            return float(fs)
        t = self.record["time"]
        if len(t) < 2:
            raise InputError(f"{self.path}: no sampling rate (no meta.json and < 2 rows)")
        return 1.0 / float(t[1] - t[0])

    def column(self, name: str) -> np.ndarray:
        """One column as a float array."""
        return np.asarray(self.record[name], dtype=float)


def read_run(run_dir: str | Path, mmap: bool = False) -> RunData:
    """Read a run directory written by :class:`Recorder` (also after a crash).

    With ``mmap=True`` the record is memory-mapped read-only (:func:`read_record`):
    nothing is read until a column is used, so a long record costs no memory up front.

    Raises
    ------
    InputError
        Not a run directory, or an unreadable record.
    """
    d = Path(run_dir)
    rec_path = d / RECORD_FILE
    if not rec_path.is_file():
        raise InputError(f"{d}: not a run directory (no {RECORD_FILE})")
    record = read_record(rec_path, mmap=mmap)
    mp, ep = d / META_FILE, d / EVENTS_FILE
    for p in (mp, ep):  # there but not readable: its data would be lost silently
        if os.path.lexists(p) and not p.is_file():
            raise InputError(
                f"{p}: not a readable file ({_not_a_file(p)}); the run's "
                f"{'metadata' if p == mp else 'events'} cannot be read"
            )
    meta = _read_meta(mp) if mp.is_file() else {}
    events = _read_events(ep) if ep.is_file() else []
    return RunData(record=record, events=events, meta=meta, path=d)


def _read_meta(mp: Path) -> dict:
    """``meta.json`` as a dict, or one line saying why it cannot be read."""
    try:
        meta = json.loads(mp.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{mp}: unreadable metadata ({exc})") from None
    except RecursionError:
        raise InputError(f"{mp}: unreadable metadata (nested too deeply)") from None
    except OSError as exc:
        raise InputError(f"{mp}: unreadable metadata ({exc.strerror})") from None
    if not isinstance(meta, dict):
        raise InputError(
            f"{mp}: unreadable metadata (expected a JSON object, got {type(meta).__name__})"
        )
    return meta


def _read_events(ep: Path) -> list[dict]:
    """The event lines of ``events.jsonl`` (a truncated last line, as a kill leaves it, is
    skipped with a warning; any other bad line is one error naming it)."""
    events: list[dict] = []
    lines = ep.read_text(encoding="utf-8", errors="replace").splitlines()
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            ev = json.loads(line)
        except RecursionError:
            raise InputError(f"{ep}:{i + 1}: malformed event line (nested too deeply)") from None
        except json.JSONDecodeError:
            if i == len(lines) - 1:
                log.warning("%s: ignoring a truncated last event line", ep)
                continue
            raise InputError(f"{ep}:{i + 1}: malformed event line") from None
        if not isinstance(ev, dict):
            raise InputError(f"{ep}:{i + 1}: malformed event line (not a JSON object)")
        events.append(ev)
    return events


def _not_a_file(p: Path) -> str:
    """Why ``p``, which exists, is not a readable regular file (for a message)."""
    try:
        p.stat()
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    return "a directory" if p.is_dir() else "not a regular file"


def _check_described(run: RunData, names: list[str], what: str) -> None:
    """Refuse an export that would silently lose the units or events (``meta.json`` missing or
    not describing every exported column)."""
    if not run.meta:
        raise InputError(
            f"{run.path / META_FILE}: missing or empty: {what} would have no units, "
            "configuration or events metadata (export --csv writes the record alone)"
        )
    described = {c.get("name") for c in run.meta.get("columns", []) if isinstance(c, dict)}
    missing = [n for n in names if n not in described]
    if missing:
        raise InputError(
            f"{run.path / META_FILE}: no unit for column(s) {', '.join(missing[:5])}"
            f"{' …' if len(missing) > 5 else ''} (truncated metadata?): {what} would lose them"
        )


def export_run(
    run_dir: str | Path,
    csv: bool = True,
    hdf5: bool = False,
    out_dir: str | Path | None = None,
    columns: Sequence[str] | None = None,
    mat: bool = False,
) -> list[Path]:
    """Export a run's record to ``record.csv``, ``record.h5`` and/or ``record.mat``.

    The CSV is a record CSV (:func:`rths_hil.records.csvfiles.write_record`):
    header line with the column
    names of :data:`COLUMNS`, ``time`` first, SI units, booleans as 0/1, NaN as ``nan``
    (estimates of invalid windows). The HDF5 file has one dataset per column under ``/record``
    (attributes ``unit`` and ``description``), the metadata as the JSON attribute ``meta`` and the
    events as the JSON attribute ``events`` of the root group. The MATLAB file (``mat``,
    :func:`scipy.io.savemat`, format 5) has one struct ``record`` with a double column vector
    per record column (booleans as 0/1), a struct ``units`` with each column's unit as text,
    and ``meta`` and ``events`` as JSON text: ``load('record.mat'); plot(record.time,
    record.measured)``. ``columns`` restricts the export
    to those columns (``time`` is always first), e.g. ``("target", "command", "measured",
    "force")`` for a record without the NaN of invalid FEI windows.

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    InputError
        Not a run directory; HDF5 asked for but ``h5py`` (the ``hdf5`` extra) is not
        installed.
    """
    from .csvfiles import write_record

    run = read_run(run_dir)
    if len(run.record) == 0:
        raise InputError(
            f"{run.path / RECORD_FILE}: the record holds no rows (the run ended or was killed "
            "before its first flush): nothing to export"
        )
    dest = Path(out_dir) if out_dir is not None else run.path
    try:
        dest.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"export: cannot create {dest}: {exc.strerror}") from None
    if not dest.is_dir():
        raise InputError(f"export: {dest} is not a directory")
    names = list(run.record.dtype.names or ())
    if columns is not None:
        unknown = [c for c in columns if c not in names]
        if unknown:
            raise InputError(
                f"{run.path}: no column(s) {', '.join(unknown)} (columns: {', '.join(names)})"
            )
        names = ["time", *[c for c in columns if c != "time"]]
    if hdf5:
        _check_described(run, names, "record.h5")
    if mat:
        _check_described(run, names, "record.mat")
    written: list[Path] = []
    if csv:
        p = dest / "record.csv"
        cols = {n: np.asarray(run.record[n], dtype=float) for n in names}
        try:
            write_record(p, cols, fmt="%.10g")
        except OSError as exc:
            raise InputError(f"export: cannot write {p}: {exc.strerror or exc}") from None
        written.append(p)
    if hdf5:
        from ..errors import require

        require("hdf5", "HDF5 export (--hdf5)")
        import h5py

        p = dest / "record.h5"
        units = {c["name"]: c for c in run.meta.get("columns", [])}
        try:
            with h5py.File(p, "w") as h5:
                grp = h5.create_group("record")
                for n in names:
                    ds = grp.create_dataset(n, data=np.asarray(run.record[n]))
                    info = units.get(n, {})
                    ds.attrs["unit"] = info.get("unit", "")
                    ds.attrs["description"] = info.get("description", "")
                h5.attrs["meta"] = json.dumps(run.meta)
                h5.attrs["events"] = json.dumps(run.events)
        except OSError as exc:
            # h5py: read-only directory, disk full, or another process holds the file's lock
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise InputError(f"export: cannot write {p}: {reason}") from None
        written.append(p)
    if mat:
        from scipy.io import savemat

        p = dest / "record.mat"
        units = {c["name"]: c.get("unit", "") for c in run.meta.get("columns", [])}
        savemat(
            p,
            {
                "record": {n: np.asarray(run.record[n], dtype=float)[:, None] for n in names},
                "units": {n: units.get(n, "") for n in names},
                "meta": json.dumps(run.meta),
                "events": json.dumps(run.events),
            },
            do_compression=True,
            oned_as="column",
        )
        written.append(p)
    return written


#: Largest ``.npy`` header read back (bytes): 1 MiB is room for thousands of columns; a
#: larger length field is garbage, refused before anything is read or allocated.
MAX_HEADER_BYTES = 1 << 20


@dataclass(frozen=True)
class NpyHeader:
    """The parsed, checked header of a record ``.npy`` file.

    Attributes
    ----------
    dtype : numpy.dtype
        The structured row dtype.
    rows : int
        Rows the header counts (checked against the file size).
    offset : int
        Byte offset of the first row.
    """

    dtype: np.dtype
    rows: int
    offset: int


def read_npy_header(path: str | Path) -> NpyHeader:
    """Parse and check the ``.npy`` header of a record without trusting any of it.

    numpy's own reader refuses headers over 10 000 bytes unless told otherwise (a record of
    16 or more channels has a longer one) and allocates whatever row count the header claims.
    Here the header length is bounded (:data:`MAX_HEADER_BYTES`), the header is a literal
    (``ast.literal_eval``, never pickle), the dtype must be a structured dtype of plain numbers
    with a ``time`` column, and the claimed rows must lie in the file: a hand-edited row count
    is refused naming both figures, before anything is allocated.

    Raises
    ------
    InputError
        Any of the above, naming the file.
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            head = fh.read(12)
            if len(head) < 10 or head[:6] != _MAGIC[:6]:
                raise InputError(f"{p}: unreadable record (not a .npy file)")
            major = head[6]
            if major == 1:
                (hlen,) = struct.unpack("<H", head[8:10])
                start = 10
            elif major in (2, 3) and len(head) == 12:
                (hlen,) = struct.unpack("<I", head[8:12])
                start = 12
            else:
                raise InputError(f"{p}: unreadable record (.npy version {major} unknown)")
            if hlen > MAX_HEADER_BYTES or start + hlen > size:
                raise InputError(
                    f"{p}: unreadable record (header length {hlen} bytes in a file of {size})"
                )
            fh.seek(start)
            text = fh.read(hlen)
            # the size again, after the header: a recorder still writing appends its rows
            # before it patches their count, so rows counted here are in the file now
            size = os.fstat(fh.fileno()).st_size
    except OSError as exc:
        raise InputError(f"{p}: unreadable record ({exc.strerror})") from None
    try:
        header = ast.literal_eval(text.decode("latin1"))
    except (ValueError, SyntaxError, MemoryError, RecursionError, TypeError):
        raise InputError(f"{p}: unreadable record (the .npy header is not a literal)") from None
    shape = header.get("shape") if isinstance(header, dict) else None
    if (
        not isinstance(header, dict)
        or not isinstance(shape, tuple)
        or len(shape) != 1
        or not isinstance(shape[0], int)
        or isinstance(shape[0], bool)
        or shape[0] < 0
        or header.get("fortran_order") is not False
    ):
        raise InputError(f"{p}: unreadable record (the .npy header is not a record's header)")
    try:
        dtype = np.lib.format.descr_to_dtype(header["descr"])
    except (ValueError, TypeError, KeyError, IndexError):
        raise InputError(f"{p}: unreadable record (bad dtype in the .npy header)") from None
    if dtype.names is None or "time" not in dtype.names or dtype.hasobject:
        raise InputError(f"{p}: not an rths_hil record (no named columns)")
    rows = shape[0]
    on_disk = (size - start - hlen) // max(1, dtype.itemsize)
    if rows > on_disk:
        raise InputError(
            f"{p}: the .npy header counts {rows} rows but the file holds {on_disk} "
            "(hand-edited or damaged header)"
        )
    return NpyHeader(dtype=dtype, rows=rows, offset=start + hlen)


def read_record(path: str | Path, mmap: bool = False) -> np.ndarray:
    """The rows a record's header counts (checked by :func:`read_npy_header`).

    With ``mmap`` the rows are mapped read-only; else read into memory.
    """
    h = read_npy_header(path)
    if h.rows == 0:
        return np.zeros(0, dtype=h.dtype)
    try:
        if mmap:
            return np.memmap(path, dtype=h.dtype, mode="r", offset=h.offset, shape=(h.rows,))
        with open(path, "rb") as fh:
            fh.seek(h.offset)
            return np.fromfile(fh, dtype=h.dtype, count=h.rows)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: unreadable record ({exc})") from None


def header_row_count(path: str | Path) -> int:
    """The row count the ``.npy`` header of ``path`` currently claims (for tests and tools)."""
    return read_npy_header(path).rows

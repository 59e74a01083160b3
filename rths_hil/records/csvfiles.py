"""Record CSV files: a header line with column names, one row per sample, SI units.

A record is what ``rths-hil simulate`` writes and ``rths-hil evaluate``, ``diagnose`` and
``twin calibrate`` read: a ``time`` column (s, uniform step, strictly increasing) and signal
columns such as ``target``, ``command``, ``measured`` (m), ``force`` (N), ``ground_accel`` (m/s²).
See ``docs/records.md``.

Every problem is reported as :class:`~rths_hil.errors.InputError` naming the file and the row
(1-based line number in the file, the header being line 1).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, check_regular_file

#: Relative tolerance on the time step when checking that a record is uniformly sampled.
UNIFORM_RTOL = 1e-3
#: Largest |value| accepted in a record (SI units: m, N, m/s², s). Far beyond any test (a
#: 10⁶ MN force, 10¹² m), it refuses corrupt values such as 1e300 whose squares overflow the
#: FEI and metric sums into inf or nonsense.
MAX_ABS_VALUE = 1e12


@dataclass
class Record:
    """A uniformly sampled record read from CSV.

    Attributes
    ----------
    path : str
        File the record came from.
    time : ndarray
        Sample times in s.
    fs : float
        Sampling rate in Hz (from the mean time step).
    columns : dict of str to ndarray
        Every column except ``time``, in file order.
    """

    path: str
    time: np.ndarray
    fs: float
    columns: dict[str, np.ndarray] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "time":
            return self.time
        return self.columns[name]

    def __contains__(self, name: str) -> bool:
        return name == "time" or name in self.columns

    def __len__(self) -> int:
        return len(self.time)

    @property
    def names(self) -> list[str]:
        """Column names, ``time`` first."""
        return ["time", *self.columns]


def _kept_columns(
    header: list[str], name: str, required: Sequence[str], optional: Sequence[str] | None
) -> list[str]:
    """The columns of ``header`` to keep (``time``, ``required``, ``optional``: all if None)."""
    need = ["time", *[c for c in required if c != "time"]]
    missing = [c for c in need if c not in header]
    if missing:
        raise InputError(
            f"{name}:1: missing column(s) {', '.join(missing)} (header has: {', '.join(header)})"
        )
    if len(set(header)) != len(header):
        raise InputError(f"{name}:1: duplicate column names in header")
    return [h for h in header if h in need or optional is None or h in optional]


def _cell(text: str, name: str, lineno: int, column: str) -> float:
    """One value of a record CSV (file ``name``, line ``lineno``, column ``column``)."""
    try:
        v = float(text)
    except ValueError:
        raise InputError(
            f"{name}:{lineno}: column {column!r}: not a number: {text.strip()!r}"
        ) from None
    if not math.isfinite(v):
        raise InputError(f"{name}:{lineno}: column {column!r}: non-finite value {text.strip()!r}")
    if abs(v) > MAX_ABS_VALUE:
        raise InputError(
            f"{name}:{lineno}: column {column!r}: value {text.strip()!r} is "
            f"not physical (|value| > {MAX_ABS_VALUE:g} in SI units)"
        )
    return v


def read_record(
    path: str | Path,
    required: Sequence[str] = ("time", "target", "measured"),
    optional: Sequence[str] | None = None,
    min_samples: int = 2,
) -> Record:
    """Read and validate a record CSV.

    Parameters
    ----------
    path : str or Path
        CSV file with a header line.
    required : sequence of str
        Columns that must be present (``time`` is always required).
    optional : sequence of str, optional
        Extra columns to keep when present. ``None`` keeps every column.
    min_samples : int
        Fewer data rows than this is an error (e.g. fewer samples than one FEI window).

    Returns
    -------
    Record

    Raises
    ------
    InputError
        Missing file or column, unreadable, non-finite or non-physical (|v| >
        :data:`MAX_ABS_VALUE`) value, non-monotonic or non-uniform time, too few samples —
        naming the file and the row.
    """
    p = Path(path)
    name = str(path)
    if p.is_dir():
        raise InputError(
            f"{name}: is a directory; for a run directory, write its record CSV with "
            f"`rths-hil export {name}` and evaluate {p / 'record.csv'}"
        )
    check_regular_file(p, "a record")
    try:
        with p.open("rb") as fb:
            magic = fb.read(6)
        fh = p.open(newline="")
    except OSError as exc:
        raise InputError(f"{name}: cannot open record ({exc.strerror})") from None
    if magic == b"\x93NUMPY":
        fh.close()
        run = p.parent
        raise InputError(
            f"{name}: a NumPy record (a run's record.npy), not a CSV; write the CSV with "
            f"`rths-hil export {run}` and evaluate {run / 'record.csv'}"
        )
    with fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise InputError(f"{name}: empty file, expected a header line") from None
        except (csv.Error, UnicodeDecodeError) as exc:
            raise InputError(f"{name}:1: cannot read header ({exc})") from None
        header = [h.strip() for h in header]
        keep = _kept_columns(header, name, required, optional)
        idx = [header.index(h) for h in keep]
        rows: list[list[float]] = []
        ncol = len(header)
        try:
            for lineno, row in enumerate(reader, start=2):
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) != ncol:
                    raise InputError(f"{name}:{lineno}: expected {ncol} values, found {len(row)}")
                rows.append([_cell(row[i], name, lineno, header[i]) for i in idx])
        except csv.Error as exc:
            raise InputError(f"{name}:{reader.line_num}: malformed CSV ({exc})") from None
        except UnicodeDecodeError:
            raise InputError(f"{name}: not a text CSV file") from None
    if len(rows) < max(min_samples, 2):
        raise InputError(f"{name}: {len(rows)} samples, need at least {max(min_samples, 2)}")
    data = np.asarray(rows, dtype=float)
    t = data[:, keep.index("time")]
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        raise InputError(f"{name}:{bad[0] + 3}: time is not strictly increasing")
    ref_dt = float(np.median(dt))
    off = np.flatnonzero(np.abs(dt - ref_dt) > UNIFORM_RTOL * ref_dt)
    if off.size:
        raise InputError(
            f"{name}:{off[0] + 3}: non-uniform time step ({dt[off[0]]:.6g} s, "
            f"expected {ref_dt:.6g} s)"
        )
    mean_dt = (t[-1] - t[0]) / (len(t) - 1)
    cols = {h: data[:, j].copy() for j, h in enumerate(keep) if h != "time"}
    return Record(path=name, time=t.copy(), fs=1.0 / mean_dt, columns=cols)


def write_record(path: str | Path, columns: Mapping[str, np.ndarray], fmt: str = "%.9g") -> None:
    """Write a record CSV: header line, then one row per sample.

    Parameters
    ----------
    path : str or Path
        Output file.
    columns : mapping of str to array
        Columns in order; ``time`` should be first. All of equal length.
    fmt : str
        printf-style number format.
    """
    names = list(columns)
    arrays = [np.asarray(columns[n], dtype=float) for n in names]
    n = {a.shape[0] for a in arrays}
    if len(n) != 1:
        raise ValueError(f"columns have different lengths: {sorted(n)}")
    data = np.column_stack(arrays) if arrays else np.empty((0, 0))
    np.savetxt(path, data, fmt=fmt, delimiter=",", header=",".join(names), comments="")

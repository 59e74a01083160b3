"""Recorded ground motions: PEER AT2 and CSV accelerograms, PGA scaling, resampling.

The FEI paper (Section 4) drives an SDOF structure with records from the PEER strong-motion database
sampled at 1024 Hz. :func:`load` reads

* **PEER AT2** files: free-text header lines followed by the acceleration values (in g), any
  number per line. The number of points and the time step are read from the header in any of
  the variants found in the NGA databases::

      NPTS=   5372, DT=   .0100 SEC,          (NGA-West2)
      NPTS= 5372 DT= 0.01 SEC                 (spacing / comma variants, any case)
      DT= .0050 SEC, NPTS= 18000              (order swapped)
      5372   .0100   NPTS, DT                 (NGA-West1 "old" header)

  The units line (``... IN UNITS OF G``) is honoured: ``G`` (default), ``CM/S/S`` (or
  ``CM/SEC/SEC``, ``GAL``) and ``M/S/S``.
* **CSV** files with a header line. The time column is ``time_s`` (or ``time``/``t``, s); the
  acceleration column is chosen by its name, which carries the unit: ``accel_g`` (g),
  ``accel_ms2``/``accel_m_s2``/``accel`` (m/s²) or ``accel_cms2``/``accel_gal`` (cm/s²).
  ``column=`` selects another column (its unit given with ``units=``).

Every problem (missing file, unknown format, truncated or malformed data, non-uniform time)
raises :class:`~rths_hil.errors.InputError` naming the file and, where it applies, the line.

Accelerations are stored in m/s² (standard gravity ``g = 9.80665 m/s²``).
"""

from __future__ import annotations

import csv
import logging
import math
import re
from dataclasses import dataclass, field
from fractions import Fraction
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.signal import resample, resample_poly

from .errors import InputError
from .units import G, parse_accel

log = logging.getLogger(__name__)

#: Name of the bundled default record (El Centro 1940, PEER NGA-West2 RSN 6, component 180).
DEFAULT_RECORD = "RSN6_IMPVALL.I_I-ELC180-hor1.AT2"

#: Relative tolerance on the time step of a CSV record.
UNIFORM_RTOL = 1e-3

_UNIT_FACTORS = {"g": G, "m/s2": 1.0, "cm/s2": 0.01}
_CSV_ACCEL_COLUMNS = {
    "accel_g": "g",
    "accel_ms2": "m/s2",
    "accel_m_s2": "m/s2",
    "accel": "m/s2",
    "accel_cms2": "cm/s2",
    "accel_gal": "cm/s2",
}
_CSV_TIME_COLUMNS = ("time_s", "time", "t")


@dataclass(frozen=True)
class GroundMotion:
    """A uniformly sampled ground acceleration history.

    Attributes
    ----------
    name : str
        Short name (file stem unless given).
    dt : float
        Time step in s.
    accel : ndarray
        Ground acceleration in m/s², ``accel[i]`` at time ``i·dt`` (the record starts at t = 0).
    source : str
        File the record was read from ('' if built in memory).
    """

    name: str
    dt: float
    accel: np.ndarray = field(repr=False)
    source: str = ""

    def __post_init__(self) -> None:
        a = np.asarray(self.accel, dtype=float)
        if a.ndim != 1 or a.size < 2:
            raise InputError(f"ground motion {self.name!r}: need a 1-D history of ≥ 2 samples")
        if not np.all(np.isfinite(a)):
            raise InputError(f"ground motion {self.name!r}: non-finite acceleration value")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise InputError(f"ground motion {self.name!r}: time step must be > 0, got {self.dt}")
        a.setflags(write=False)
        object.__setattr__(self, "accel", a)

    @property
    def fs(self) -> float:
        """Sampling rate in Hz."""
        return 1.0 / self.dt

    @property
    def npts(self) -> int:
        """Number of samples."""
        return int(self.accel.size)

    @property
    def duration(self) -> float:
        """Time of the last sample in s (``(npts - 1)·dt``)."""
        return (self.npts - 1) * self.dt

    @property
    def time(self) -> np.ndarray:
        """Sample times in s, starting at 0."""
        return np.arange(self.npts) * self.dt

    @property
    def pga(self) -> float:
        """Peak ground acceleration ``max |a|`` in m/s²."""
        return float(np.max(np.abs(self.accel)))

    def scaled(self, pga: float | str) -> GroundMotion:
        """Return a copy scaled so that its peak absolute acceleration equals ``pga``.

        Parameters
        ----------
        pga : float or str
            Target PGA in m/s², or a string such as ``"0.0528g"`` or ``"0.322"`` (m/s²).
        """
        target = parse_accel(pga, "PGA")
        if not (math.isfinite(target) and target > 0):
            raise InputError(f"PGA must be > 0, got {pga!r}")
        peak = self.pga
        if peak == 0:
            raise InputError(f"ground motion {self.name!r} is all zeros: cannot scale its PGA")
        return GroundMotion(self.name, self.dt, self.accel * (target / peak), self.source)

    def resampled(self, fs: float) -> GroundMotion:
        """Return the record resampled to ``fs`` Hz, band-limited (anti-aliased) resampling.

        When ``fs·dt`` is a ratio of small integers (e.g. 100 Hz → 1024 Hz = 256/25) a polyphase
        FIR (:func:`scipy.signal.resample_poly`, Kaiser window β = 10: 6e-6 relative error on a 2 Hz
        tone from 100 Hz, vs 2e-3 for linear interpolation) is used; otherwise the Fourier
        method (:func:`scipy.signal.resample`). The new record has ``ceil(npts·fs·dt)`` samples
        starting at t = 0. Downsampling low-pass filters at the new Nyquist frequency.
        """
        if not (isinstance(fs, int | float) and math.isfinite(fs) and fs > 0):
            raise InputError(f"sampling rate must be a positive number of Hz, got {fs!r}")
        ratio = fs * self.dt
        if abs(ratio - 1.0) < 1e-12:
            return self
        frac = Fraction(ratio).limit_denominator(1000)
        n_out = math.ceil(self.npts * ratio - 1e-9)
        if (
            abs(float(frac) - ratio) <= 1e-9 * ratio
            and max(frac.numerator, frac.denominator) <= 4096
        ):
            y = resample_poly(
                self.accel, frac.numerator, frac.denominator, window=("kaiser", 10.0)
            )[:n_out]
        else:
            y = resample(self.accel, n_out)
        return GroundMotion(self.name, 1.0 / fs, y, self.source)

    def padded(self, seconds: float) -> GroundMotion:
        """Return the record followed by ``seconds`` of zero acceleration (free vibration)."""
        n = round(seconds / self.dt)
        if n < 0:
            raise InputError(f"padding must be ≥ 0 s, got {seconds}")
        return GroundMotion(
            self.name, self.dt, np.concatenate([self.accel, np.zeros(n)]), self.source
        )


# --------------------------------------------------------------------------------------------
# AT2

_NPTS_RE = re.compile(r"NPTS\s*[=:]?\s*(\d+)", re.IGNORECASE)
_DT_RE = re.compile(r"\bDT\s*[=:]?\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", re.IGNORECASE)
_OLD_HEADER_RE = re.compile(
    r"^\s*(\d+)\s*,?\s+([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*,?\s*NPTS\s*,\s*DT", re.I
)


def _at2_units(header: list[str], name: str) -> float:
    text = " ".join(header).upper()
    if re.search(r"UNITS?\s+OF\s+G\b|IN\s+G\b|\(G\)", text):
        return G
    if re.search(r"CM/S(EC)?/S(EC)?|CM/S(EC)?\^?2|CM/S\*\*2|\bGALS?\b", text):
        return 0.01
    if re.search(r"\bM/S(EC)?/S(EC)?|\bM/S(EC)?\^?2|\bM/S\*\*2", text):
        return 1.0
    if "UNITS" in text:
        raise InputError(f"{name}: AT2 header names units that are not g, cm/s² or m/s²")
    log.info("%s: no units line in the AT2 header, assuming g", name)
    return G


def _parse_at2(path: Path, name: str) -> tuple[float, np.ndarray]:
    try:
        text = path.read_text(encoding="latin-1")
    except OSError as exc:
        raise InputError(f"{name}: cannot open ground motion ({exc.strerror})") from None
    lines = text.splitlines()
    npts = dt = None
    header_end = None
    for i, line in enumerate(lines[:12]):
        m_old = _OLD_HEADER_RE.match(line)
        if m_old:
            npts, dt = int(m_old.group(1)), float(m_old.group(2))
            header_end = i + 1
            break
        m_n, m_d = _NPTS_RE.search(line), _DT_RE.search(line)
        if m_n and m_d:
            npts, dt = int(m_n.group(1)), float(m_d.group(1))
            header_end = i + 1
            break
    if header_end is None or npts is None or dt is None:
        raise InputError(f"{name}: not a PEER AT2 file: no 'NPTS=..., DT=... SEC' header line")
    if npts < 2:
        raise InputError(f"{name}:{header_end}: NPTS={npts}, need at least 2 points")
    if not dt > 0:
        raise InputError(f"{name}:{header_end}: DT={dt} s, must be > 0")
    scale = _at2_units(lines[: header_end - 1], name)
    values: list[float] = []
    for lineno, line in enumerate(lines[header_end:], start=header_end + 1):
        for tok in line.split():
            try:
                v = float(tok)
            except ValueError:
                raise InputError(f"{name}:{lineno}: not a number: {tok!r}") from None
            if not math.isfinite(v):
                raise InputError(f"{name}:{lineno}: non-finite value {tok!r}")
            values.append(v)
    if len(values) < npts:
        raise InputError(
            f"{name}: truncated AT2 file: header says NPTS={npts} but only {len(values)} values"
        )
    if len(values) > npts:
        raise InputError(f"{name}: AT2 file has {len(values)} values but header says NPTS={npts}")
    return dt, np.asarray(values) * scale


# --------------------------------------------------------------------------------------------
# CSV


def _csv_accel_column(
    name: str, header: list[str], lower: list[str], column: str | None, units: str | None
) -> tuple[int, str]:
    """Index and unit of the acceleration column (``column`` or the first known one)."""
    if column is not None:
        if column.lower() not in lower:
            raise InputError(f"{name}:1: no column {column!r} (header has: {', '.join(header)})")
        unit = units or _CSV_ACCEL_COLUMNS.get(column.lower())
        if unit is None:
            raise InputError(f"{name}: give the units of column {column!r} (g, m/s2 or cm/s2)")
        return lower.index(column.lower()), unit
    acol = next((lower.index(c) for c in _CSV_ACCEL_COLUMNS if c in lower), None)
    if acol is None:
        raise InputError(
            f"{name}:1: no acceleration column (expected one of "
            f"{', '.join(_CSV_ACCEL_COLUMNS)}; header has: {', '.join(header)})"
        )
    return acol, units or _CSV_ACCEL_COLUMNS[lower[acol]]


def _parse_csv(
    path: Path, name: str, column: str | None, units: str | None
) -> tuple[float, np.ndarray]:
    try:
        fh = path.open(newline="", encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{name}: cannot open ground motion ({exc.strerror})") from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
            rows = list(enumerate(reader, start=2))
        except StopIteration:
            raise InputError(f"{name}: empty file, expected a header line") from None
        except (csv.Error, UnicodeDecodeError) as exc:
            raise InputError(f"{name}: malformed CSV ({exc})") from None
    lower = [h.lower() for h in header]
    tcol = next((lower.index(c) for c in _CSV_TIME_COLUMNS if c in lower), None)
    if tcol is None:
        raise InputError(
            f"{name}:1: no time column (expected one of {', '.join(_CSV_TIME_COLUMNS)};"
            f" header has: {', '.join(header)})"
        )
    acol, unit = _csv_accel_column(name, header, lower, column, units)
    if unit not in _UNIT_FACTORS:
        raise InputError(f"{name}: unknown acceleration unit {unit!r} (use g, m/s2 or cm/s2)")
    t: list[float] = []
    a: list[float] = []
    for lineno, row in rows:
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{name}:{lineno}: expected {len(header)} values, found {len(row)}")
        try:
            tv, av = float(row[tcol]), float(row[acol])
        except ValueError:
            raise InputError(f"{name}:{lineno}: not a number in {row!r}") from None
        if not (math.isfinite(tv) and math.isfinite(av)):
            raise InputError(f"{name}:{lineno}: non-finite value")
        t.append(tv)
        a.append(av)
    if len(t) < 2:
        raise InputError(f"{name}: {len(t)} samples, need at least 2")
    tt = np.asarray(t)
    steps = np.diff(tt)
    dt = float((tt[-1] - tt[0]) / (len(tt) - 1))
    if not dt > 0 or np.any(np.abs(steps - dt) > UNIFORM_RTOL * dt):
        bad = int(np.argmax(np.abs(steps - dt))) + 3  # line of the second sample of the pair
        raise InputError(f"{name}:{bad}: time is not uniformly increasing (step {dt:g} s)")
    if abs(tt[0]) > UNIFORM_RTOL * dt:
        log.info("%s: record starts at t = %g s; time is re-based to 0", name, tt[0])
    return dt, np.asarray(a) * _UNIT_FACTORS[unit]


# --------------------------------------------------------------------------------------------
# public


def load(
    path: str | Path,
    *,
    name: str | None = None,
    column: str | None = None,
    units: str | None = None,
) -> GroundMotion:
    """Read a ground motion from a PEER AT2 or CSV file.

    Parameters
    ----------
    path : str or Path
        ``*.AT2`` (any case) or ``*.csv``; other extensions are sniffed (an ``NPTS``/``DT``
        header means AT2, a header with a time column means CSV).
    name : str, optional
        Name of the record; the file stem by default.
    column, units : str, optional
        CSV only: acceleration column and its unit (``g``, ``m/s2``, ``cm/s2``).

    Returns
    -------
    GroundMotion
        Acceleration in m/s².

    Raises
    ------
    InputError
        Missing file, unknown format, truncated or malformed data.
    """
    p = Path(path)
    label = str(path)
    if not p.is_file():
        raise InputError(f"{label}: no such ground-motion file")
    suffix = p.suffix.lower()
    if suffix == ".at2":
        kind = "at2"
    elif suffix == ".csv":
        kind = "csv"
    else:
        try:
            head = p.read_text(encoding="latin-1")[:2000]
        except OSError as exc:
            raise InputError(f"{label}: cannot open ground motion ({exc.strerror})") from None
        first = head.splitlines()[0].lower() if head.strip() else ""
        if _NPTS_RE.search(head) or "peer" in head.lower():
            kind = "at2"
        elif "," in first and any(c in first.split(",")[0] for c in _CSV_TIME_COLUMNS):
            kind = "csv"
        else:
            raise InputError(
                f"{label}: unknown ground-motion format (expected a PEER .AT2 or a .csv"
                " with a time_s,accel_g header)"
            )
    if kind == "at2":
        if column is not None:
            raise InputError(f"{label}: column= applies to CSV files only")
        dt, accel = _parse_at2(p, label)
    else:
        dt, accel = _parse_csv(p, label, column, units)
    _check_physical(accel, dt, label)
    return GroundMotion(name or p.stem, dt, accel, label)


#: Largest |acceleration| accepted from a record file, in g. The strongest recorded ground
#: motions peak near 4 g (2008 Iwate–Miyagi, IWTH25: 4.36 g); 20 g leaves room for any real
#: record and refuses spikes (a wrong unit, a corrupt sample) that PGA scaling would hide.
MAX_ACCEL_G = 20.0


def _check_physical(accel: np.ndarray, dt: float, label: str) -> None:
    """Refuse non-finite or non-physical samples, naming the first (index and time)."""
    a = np.asarray(accel, dtype=float)
    limit = MAX_ACCEL_G * G
    bad = ~(np.abs(a) <= limit)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{label}: sample {i} (t = {i * dt:.4g} s) is {a[i] / G:.6g} g: not a physical "
            f"ground acceleration (limit ±{MAX_ACCEL_G:g} g; check the units and the data)"
        )


def bundled_records() -> list[Path]:
    """Paths of the ground motions shipped in ``rths_hil/data/ground_motions`` (sorted)."""
    root = resources.files("rths_hil") / "data" / "ground_motions"
    out = [
        Path(str(p))
        for p in root.iterdir()
        if p.is_file() and Path(str(p)).suffix.lower() in (".at2", ".csv")
    ]
    return sorted(out)


def bundled_path(name: str) -> Path:
    """Path of a bundled record, by file name or stem (case-insensitive)."""
    for p in bundled_records():
        if name.lower() in (p.name.lower(), p.stem.lower()):
            return p
    names = ", ".join(p.name for p in bundled_records())
    raise InputError(f"no bundled record {name!r} (bundled: {names})")


def default_record() -> GroundMotion:
    """The bundled El Centro 1940 record (PEER NGA-West2 RSN 6, component 180, dt = 0.01 s)."""
    return load(bundled_path(DEFAULT_RECORD), name="elcentro_1940_ELC180")


def resolve(spec: str | Path) -> GroundMotion:
    """Load ``spec``: a file path, or the name/stem of a bundled record."""
    p = Path(spec)
    if p.is_file():
        return load(p)
    try:
        return load(bundled_path(str(spec)))
    except InputError:
        raise InputError(f"{spec}: no such ground-motion file (nor a bundled record)") from None

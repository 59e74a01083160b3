"""Follow a run directory while it is written: the growing record, the events, the writer.

The watcher never talks to the loop. It reads what the loop's crash-safe recorder
(:mod:`rths_hil.records.recorder`) puts on disk: ``meta.json`` (written before the first step),
``record.npy`` (a ``.npy`` file whose header row count is patched after each flush and never
counts a row that is not on disk) and ``events.jsonl`` (one JSON line per event, flushed at
once). :class:`RunFollower` re-reads the header's row count on each :meth:`RunFollower.poll`
and maps the counted rows read-only (``np.load(mmap_mode="r")``), so a poll costs a few system
calls whatever the length of the run, and reads the events appended since the last poll.

The process writing the record is the one ``meta.json`` names (``pid``, written by the
recorder), and only while it holds ``record.npy`` open for writing: on Linux,
``/proc/<pid>/fd`` lists a process's open files (:func:`find_writer`), so a stale id of a
finished run, reused by another process, is never taken for the writer. For a run recorded
without ``pid`` in its metadata, every process this user may inspect is searched the way
``lsof`` would. That is what the operator-stop button signals (:func:`signal_writer`: SIGINT,
the same stop as Ctrl-C), and its disappearance without an ``end`` event is how a killed run
is recognised.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..records.columns import channel_columns, column_name
from ..records.recorder import EVENTS_FILE, META_FILE, RECORD_FILE, read_npy_header

__all__ = [
    "CHANNEL_COLUMNS",
    "RunFollower",
    "RunState",
    "channel_column",
    "find_channels",
    "find_writer",
    "signal_writer",
]

log = logging.getLogger(__name__)

#: Columns a multi-channel record carries once per actuator channel, as ``<name>_<channel>``
#: (:func:`rths_hil.records.columns.column_name`).
CHANNEL_COLUMNS = tuple(c.name for c in channel_columns())


def find_channels(names: tuple[str, ...] | list[str]) -> list[str]:
    """The actuator channels of a record, from its column names.

    A single-channel record has ``target`` and ``measured``: one channel, named ``""``. A
    multi-channel record suffixes each per-channel column with ``_<channel>`` (``target_left``,
    ``measured_left`` …): its channels are the suffixes that have both a target and a measured
    column, in column order.
    """
    names = list(names)
    if "target" in names and "measured" in names:
        return [""]
    have = set(names)
    out = []
    for n in names:
        if n.startswith("target_"):
            ch = n[len("target_") :]
            if ch and column_name("measured", ch) in have:
                out.append(ch)
    return out


def channel_column(names, base: str, channel: str) -> str | None:
    """The column holding ``base`` for ``channel`` (``base_channel``, else a shared ``base``)."""
    name = column_name(base, channel)
    if channel and name in names:
        return name
    if base in names:
        return base
    return None


# ----------------------------------------------------------------------------------------------
# the writer process


def _holds_for_writing(pid: str, target: str) -> bool:
    fd_dir = f"/proc/{pid}/fd"
    try:
        fds = os.listdir(fd_dir)
    except OSError:
        return False
    for fd in fds:
        try:
            if os.readlink(f"{fd_dir}/{fd}") != target:
                continue
            with open(f"/proc/{pid}/fdinfo/{fd}", encoding="ascii") as fh:
                for line in fh:
                    if line.startswith("flags:"):
                        flags = int(line.split()[1], 8)
                        if flags & (os.O_WRONLY | os.O_RDWR):
                            return True
        except (OSError, ValueError):
            continue
    return False


def find_writer(record_path: str | Path, hint: int | None = None, scan: bool = True) -> int | None:
    """The id of the process that holds ``record_path`` open for writing, or None.

    Looks at ``hint`` first (the id the run's metadata names, or one found before), then, with
    ``scan``, at every process this user may inspect (``/proc/<pid>/fd``, Linux). Processes of
    other users are not visible, and could not be signalled anyway. This process is never its
    own writer (the watcher never stops itself).
    """
    try:
        target = os.path.realpath(record_path)
    except OSError:
        return None
    if not os.path.isdir("/proc"):
        return None
    me = os.getpid()
    if hint is not None and hint != me and _holds_for_writing(str(hint), target):
        return hint
    if not scan:
        return None
    try:
        pids = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return None
    for p in pids:
        if int(p) != me and _holds_for_writing(p, target):
            return int(p)
    return None


def signal_writer(
    record_path: str | Path, sig: int, hint: int | None = None, scan: bool = True
) -> int | None:
    """Send ``sig`` to the process writing ``record_path``; its id, or None when there is none.

    The process (``hint``, else, with ``scan``, the one :func:`find_writer` finds) is checked
    to hold the record open for writing just before the signal, through a pidfd where Linux
    has them (``os.pidfd_open``): the signal then reaches that very process or none, even if
    it ended and its id was taken by another process in between. Raises OSError when the
    signal cannot be sent (permission).
    """
    pid = find_writer(record_path, hint=hint, scan=scan)
    if pid is None:
        return None
    try:
        pidfd = os.pidfd_open(pid)
    except (AttributeError, OSError):
        pidfd = None  # no pidfd here (old kernel, not Linux): the check and the signal
    try:
        if find_writer(record_path, hint=pid, scan=False) != pid:
            return None  # it ended between the two looks
        if pidfd is not None:
            signal.pidfd_send_signal(pidfd, sig)
        else:
            os.kill(pid, sig)
    except ProcessLookupError:
        return None
    finally:
        if pidfd is not None:
            os.close(pidfd)
    return pid


# ----------------------------------------------------------------------------------------------
# the follower


@dataclass
class RunState:
    """What the watcher knows about a run at one poll.

    Attributes
    ----------
    phase : str
        ``missing`` (no directory), ``empty`` (no record yet), ``unreadable``, ``starting``
        (record with no row yet), ``running``, ``completed``, ``trip``, ``operator_stop``,
        ``error`` or ``killed`` (no ``end`` event and no process writing the record).
    message : str
        One line for the operator.
    rows : int
        Rows on disk (counted by the record's header).
    time : float
        Loop time of the last row (s), NaN before the first.
    writer : int or None
        Id of the process writing the record.
    """

    phase: str
    message: str
    rows: int = 0
    time: float = float("nan")
    writer: int | None = None
    trip: dict | None = None
    end: dict | None = None
    events: list[dict] = field(default_factory=list)

    @property
    def live(self) -> bool:
        """The run is being written (its record may still grow)."""
        return self.phase in ("starting", "running")

    @property
    def finished(self) -> bool:
        """The run has ended (normally, by a trip or stop, or killed)."""
        return self.phase in ("completed", "trip", "operator_stop", "error", "killed")


_SHAPE = re.compile(rb"'shape': \((\d+),\)")


class RunFollower:
    """Incremental reader of a run directory being written by
    :class:`rths_hil.records.recorder.Recorder`.

    Parameters
    ----------
    run_dir : str or Path
        The run directory (it may not exist yet).
    writer_check : float
        Seconds between two searches for the writing process while none is known.

    Notes
    -----
    :attr:`record` is the record mapped read-only up to the counted rows (a structured array, or
    None before there is one); :attr:`events` the events read so far; :attr:`meta` the metadata.
    """

    def __init__(self, run_dir: str | Path, writer_check: float = 1.0) -> None:
        self.run_dir = Path(run_dir)
        self.record_path = self.run_dir / RECORD_FILE
        self.meta: dict = {}
        self.events: list[dict] = []
        self.record: np.ndarray | None = None
        self.rows = 0
        self.writer: int | None = None
        self.writer_check = float(writer_check)
        self._events_off = 0
        self._events_tail = b""
        self.skipped_events = 0  # event lines that were not JSON objects
        self._header_len = 0
        self._dtype: np.dtype | None = None
        self._last_writer_check = -1e9
        self._grown_at = -1e9
        self._seen_header = False
        self.stale_after = 2.0
        self.state = RunState("missing", "")

    # -- parts -----------------------------------------------------------------------------
    def _read_meta(self) -> None:
        if self.meta:
            return
        p = self.run_dir / META_FILE
        try:
            meta = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError):
            meta = {}
        if not isinstance(meta, dict):
            log.warning("%s: metadata is not a JSON object; ignored", p)
            meta = {}
        self.meta = meta

    def _read_events(self) -> None:
        p = self.run_dir / EVENTS_FILE
        try:
            with open(p, "rb") as fh:
                fh.seek(self._events_off)
                data = fh.read()
        except OSError:
            return
        if not data:
            return
        self._events_off += len(data)
        data = self._events_tail + data
        lines = data.split(b"\n")
        self._events_tail = lines.pop()  # an incomplete last line waits for the next poll
        for line in lines:
            if not line.strip():
                continue
            try:
                ev = json.loads(line)
            except (ValueError, RecursionError):
                ev = None
            if isinstance(ev, dict):
                self.events.append(ev)
            else:
                self.skipped_events += 1
                log.warning("%s: skipping a malformed event line (not a JSON object)", p)

    def _read_record(self) -> None:
        """Map the rows the header counts (the header never counts a row not on disk)."""
        if self._dtype is None:
            if not self.record_path.exists():
                return
            h = read_npy_header(self.record_path)  # checked; any header length
            self._dtype, self._header_len = h.dtype, h.offset
        try:
            with open(self.record_path, "rb") as fh:
                head = fh.read(self._header_len)
        except FileNotFoundError:
            return
        m = _SHAPE.search(head)
        if m is None:
            raise ValueError("no row count in the .npy header")
        rows = int(m.group(1))
        if rows == self.rows and self._seen_header:
            return
        self._seen_header = True
        # when the record last grew, on the monotonic clock (from the file's age on disk)
        try:
            age = max(0.0, time.time() - os.stat(self.record_path).st_mtime)
        except OSError:
            age = 0.0
        self._grown_at = time.monotonic() - age
        self.rows = rows
        if rows:
            self.record = np.memmap(
                self.record_path,
                dtype=self._dtype,
                mode="r",
                offset=self._header_len,
                shape=(rows,),
            )

    @property
    def meta_pid(self) -> int | None:
        """The id of the recording process named by ``meta.json`` (None for older runs)."""
        pid = self.meta.get("pid")
        return pid if isinstance(pid, int) and not isinstance(pid, bool) and pid > 0 else None

    def _find_writer(self, now: float) -> None:
        pid = self.meta_pid
        if pid is not None:  # the recorder's process, while it holds the record
            self.writer = find_writer(self.record_path, hint=pid, scan=False)
            return
        if self.writer is not None:
            if find_writer(self.record_path, hint=self.writer) == self.writer:
                return
            self.writer = None
        if now - self._last_writer_check >= self.writer_check:
            self._last_writer_check = now
            self.writer = find_writer(self.record_path)

    # -- public ----------------------------------------------------------------------------
    @property
    def channels(self) -> list[str]:
        """The record's actuator channels (``[""]`` for a single-channel record)."""
        if self._dtype is None:
            return []
        return find_channels(self._dtype.names or ())

    @property
    def names(self) -> tuple[str, ...]:
        """The record's column names (empty before the record exists)."""
        return () if self._dtype is None else tuple(self._dtype.names or ())

    def poll(self, now: float | None = None) -> RunState:
        """Read what is new on disk and return the run's :class:`RunState`."""
        now = time.monotonic() if now is None else now
        d = self.run_dir
        if not d.exists():
            self.state = RunState(
                "missing", f"{d} does not exist (yet): waiting for the run to start"
            )
            return self.state
        if not d.is_dir():
            self.state = RunState("unreadable", f"{d} is not a directory")
            return self.state
        self._read_meta()
        self._read_events()
        if not self.record_path.exists():
            msg = (
                f"{d}: run starting, no {RECORD_FILE} yet"
                if self.meta
                else f"{d} has no run record ({RECORD_FILE}) yet: waiting for the run to start"
            )
            self.state = RunState("empty", msg)
            return self.state
        try:
            self._read_record()
        except (OSError, ValueError, SyntaxError) as exc:
            self.state = RunState("unreadable", f"{self.record_path}: unreadable record ({exc})")
            return self.state
        self._read_meta()  # written before the record; reread if it was missing a moment ago
        end = next((e for e in reversed(self.events) if e.get("kind") == "end"), None)
        if end is None:
            self._find_writer(now)
        else:
            self.writer = None  # the run has ended: nobody to look for
        trip = next((e for e in reversed(self.events) if e.get("kind") == "trip"), None)
        t_last = float(self.record["time"][-1]) if self.record is not None and self.rows else None
        t = float("nan") if t_last is None else t_last

        def state(phase: str, message: str) -> RunState:
            return RunState(
                phase,
                message,
                rows=self.rows,
                time=t,
                writer=self.writer,
                trip=trip,
                end=end,
                events=self.events,
            )

        if end is not None:
            status = str(end.get("status", "completed"))
            phase = status if status in ("completed", "trip", "operator_stop") else "error"
            self.state = state(phase, _end_message(status, end, trip, self.events))
        elif self.writer is not None or now - self._grown_at < self.stale_after:
            # a record that still grows is live even when its writer is not visible here
            phase = "running" if self.rows else "starting"
            mode, fs = self.meta.get("mode", "?"), self.meta.get("fs", 0)
            msg = (
                f"test in progress ({mode} at {fs:g} Hz)"
                if self.rows
                else "run starting: waiting for the first rows"
            )
            if trip is not None:
                msg = "e-stop: " + _trip_text(trip)
                phase = "trip"
            self.state = state(phase, msg)
        else:
            err = next((e for e in reversed(self.events) if e.get("kind") == "error"), None)
            msg = (
                f"killed or crashed: no end event and no process writing {RECORD_FILE}; "
                f"the record holds {self.rows} steps"
            )
            if err is not None:
                msg = f"crashed: {err.get('error', 'error')}; the record holds {self.rows} steps"
            self.state = state("killed", msg)
        return self.state

    def signal_writer(self, sig: int = signal.SIGINT) -> int | None:
        """Send ``sig`` to the process writing the record (:func:`signal_writer`).

        The process ``meta.json`` names, and only that one, when the metadata names one;
        otherwise (a run recorded without ``pid``) the process found by searching ``/proc``.
        """
        pid = self.meta_pid
        if pid is not None:
            return signal_writer(self.record_path, sig, hint=pid, scan=False)
        return signal_writer(self.record_path, sig, hint=self.writer, scan=True)

    def fs(self) -> float:
        """The loop rate (Hz) from the metadata (or the record's time step)."""
        fs = self.meta.get("fs")
        if fs:
            return float(fs)
        if self.record is not None and self.rows > 1:
            return 1.0 / float(self.record["time"][1] - self.record["time"][0])
        return 1.0

    def planned_duration(self) -> float:
        """Planned test length (s) from the metadata (0 when unknown)."""
        n = self.meta.get("planned_steps") or 0
        return float(n) / self.fs() if n else 0.0

    def wall_t0(self) -> float | None:
        """Wall-clock time (Unix s) of step 0's deadline (the last ``clock`` event: a paced
        run that slipped its time base after a stall of the bridge writes a new one)."""
        for e in reversed(self.events):
            if e.get("kind") == "clock":
                try:
                    return float(e["wall_t0"])
                except (KeyError, TypeError, ValueError):
                    return None
        return None


def _trip_text(trip: dict) -> str:
    ch = trip.get("channel")
    where = f" on channel {ch}" if ch else ""
    t: Any = trip.get("time")  # from JSON: a number if well formed
    try:
        tt = f" at t = {float(t):.3f} s"
    except (TypeError, ValueError):
        tt = ""
    step = trip.get("step", "?")
    return f"{trip.get('rule', '?')}{where}{tt} (step {step}): {trip.get('reason', '')}"


def _end_message(status: str, end: dict, trip: dict | None, events: list[dict]) -> str:
    t: Any = end.get("time")  # from JSON: a number if well formed
    try:
        tt = f"{float(t):.2f} s"
    except (TypeError, ValueError):
        tt = "?"
    if status == "completed":
        return f"completed: {tt}, {end.get('step', '?')} steps"
    if status == "trip" and trip is not None:
        return "e-stop: " + _trip_text(trip)
    if status == "operator_stop":
        sig = next((e.get("signal") for e in events if e.get("kind") == "operator_stop"), None)
        return f"operator stop{f' ({sig})' if sig else ''} at t = {tt}"
    return f"ended: {status} at t = {tt}"

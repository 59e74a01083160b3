"""Up-front estimates of memory, disk and counts, so that a command refuses what cannot fit.

A duration of 1e12 s, a sampling rate of 1 GHz or a billion trials is bad input: it would
allocate terabytes or run for centuries. Each command estimates what it is about to allocate
or write and calls these checks *before* allocating; the refusal is one line naming the figure
(:class:`~rths_hil.errors.InputError`, exit 2).

Limits
------
Memory
    at most half of the memory the kernel reports available (``MemAvailable`` of
    ``/proc/meminfo``; the physical memory elsewhere), leaving room for the rest of the process.
Disk
    the run's record (rows × row size) must fit the free space of the file system it goes to.
Counts
    :data:`MAX_TRIALS`, :data:`MAX_SWEEP_POINTS` and :func:`max_workers`: numbers beyond which
    a study is certainly a typing error (days of runs, more processes than the machine holds).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from .errors import InputError

__all__ = [
    "MAX_SWEEP_POINTS",
    "MAX_TRIALS",
    "available_memory",
    "check_count",
    "check_disk",
    "check_memory",
    "format_bytes",
    "max_workers",
]

#: Most trials of one robustness study (200 is the default; 100 000 lockstep runs are days).
MAX_TRIALS = 100_000
#: Most α values of one tuning sweep (each a trial test).
MAX_SWEEP_POINTS = 1_000


def format_bytes(n: float) -> str:
    """``n`` bytes in binary units (``1.5 GiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"):
        if abs(n) < 1024 or unit == "EiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def available_memory() -> int:
    """Bytes of memory available to a new allocation (``MemAvailable``, else physical)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return 1 << 34


def check_memory(nbytes: float, what: str) -> None:
    """Refuse ``what`` when it needs more than half of the available memory."""
    limit = available_memory() // 2
    if not nbytes <= limit:
        raise InputError(
            f"{what} needs {format_bytes(nbytes)} of memory; this machine has "
            f"{format_bytes(2 * limit)} available (at most half is used): shorten it"
        )


def check_disk(nbytes: float, path: str | Path, what: str) -> None:
    """Refuse ``what`` when ``nbytes`` do not fit the free space where ``path`` will be."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir():
        return  # a file where a directory must be: the writer names it ("Not a directory")
    try:
        vfs = os.statvfs(p)
        free = shutil.disk_usage(p).free
    except OSError:
        return  # the writer reports the path itself
    if vfs.f_flag & os.ST_RDONLY:
        raise InputError(f"{what} cannot be written under {p}: a read-only file system")
    if vfs.f_blocks == 0:
        raise InputError(
            f"{what} cannot be written under {p}: a virtual file system with no room for "
            "files (such as /proc or /sys); choose another output directory"
        )
    if not os.access(p, os.W_OK | os.X_OK):
        raise InputError(f"{what} cannot be written under {p}: permission denied")
    if not nbytes <= free:
        raise InputError(
            f"{what} needs {format_bytes(nbytes)} of disk; {p} has {format_bytes(free)} free: "
            "shorten it"
        )


def check_count(value: float, limit: float, what: str, why: str) -> None:
    """Refuse a count above ``limit`` (``what`` names the argument, ``why`` the cost)."""
    if not value <= limit:
        raise InputError(f"{what}: {value} is more than {limit} ({why})")


def max_workers() -> int:
    """Most worker processes of a local pool: four per CPU of this machine."""
    return 4 * (os.cpu_count() or 1)

"""Write a benchmark's latest table, with the machine's description, to ``benchmarks/results``.

Every benchmark script ends with::

    from _results import write_results
    write_results("bench_fei", table_markdown, goals="...")

which (re)writes ``benchmarks/results/bench_fei.md``: the command that reproduces it, the
machine (CPU model, cores, memory, OS, Python and the versions of the libraries that matter), the
table and the goals. README and ``docs/`` link to these files instead of copying numbers that
change from run to run.
"""

from __future__ import annotations

import os
import platform
import sys
from importlib import metadata
from pathlib import Path

RESULTS_DIR = Path(__file__).resolve().parent / "results"

_LIBRARIES = (
    "numpy",
    "scipy",
    "numba",
    "python-can",
    "pymodbus",
    "pyserial",
    "cantools",
    "filterpy",
    "openseespy",
    "dask",
    "distributed",
    "bokeh",
)


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    return "unknown"


def machine_description() -> str:
    """One Markdown block describing this machine and the library versions."""
    versions = []
    for name in _LIBRARIES:
        try:
            versions.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return "\n".join(
        [
            f"- CPU: {_cpu_model()}, {os.cpu_count()} logical cores, {_memory_gib()} memory",
            f"- OS: {platform.system()} {platform.release()} ({platform.machine()})",
            f"- Python {platform.python_version()} ({sys.implementation.name})",
            f"- Libraries: {', '.join(versions)}",
        ]
    )


def write_results(
    name: str,
    table: str,
    *,
    title: str | None = None,
    goals: str | None = None,
    command: str | None = None,
    notes: str | None = None,
) -> Path:
    """Write ``benchmarks/results/<name>.md`` and return its path.

    Parameters
    ----------
    name : str
        File stem, normally the script's name (``"bench_fei"``).
    table : str
        The results as Markdown (a table, or several with their own headings).
    title, goals, command, notes : str, optional
        A heading (default: the name), the goals the figures are judged against, the command
        that reproduces the file (default: ``python benchmarks/<name>.py``) and any remarks on
        how to read the figures.
    """
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    parts = [f"# {title or name}", ""]
    parts += ["Reproduce: `" + (command or f"python benchmarks/{name}.py") + "`", ""]
    parts += ["## Machine", "", machine_description(), ""]
    if goals:
        parts += ["## Goals", "", goals.strip(), ""]
    parts += ["## Results", "", table.strip(), ""]
    if notes:
        parts += ["## Notes", "", notes.strip(), ""]
    path = RESULTS_DIR / f"{name}.md"
    path.write_text("\n".join(parts))
    return path


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """A Markdown table from a header and rows (values formatted with ``str``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)

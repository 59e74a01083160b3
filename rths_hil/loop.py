"""Former name of :mod:`rths_hil.hybrid`, kept for scripts that import the loop from here.

The loop is :mod:`rths_hil.hybrid` (``from rths_hil.hybrid import RTHSLoop, run``); the
documented entry point for scripts is :func:`rths_hil.run`. This module only re-exports the
public names.
"""

from __future__ import annotations

from .hybrid.plan import build_ground_motion, new_run_dir
from .hybrid.result import RunResult
from .hybrid.rthsloop import RTHSLoop, run
from .hybrid.timing import (
    CAUSES,
    MACHINE,
    MACHINE_BACKLOG,
    ON_TIME,
    WORK,
    WORK_BACKLOG,
    attribute_overruns,
    count_causes,
    paced_floor,
)

__all__ = [
    "CAUSES",
    "MACHINE",
    "MACHINE_BACKLOG",
    "ON_TIME",
    "WORK",
    "WORK_BACKLOG",
    "RTHSLoop",
    "RunResult",
    "attribute_overruns",
    "build_ground_motion",
    "count_causes",
    "new_run_dir",
    "paced_floor",
    "run",
]

"""Run a test configuration through the loop and read its run directory back."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rths_hil.config import load_config
from rths_hil.hybrid import RTHSLoop, RunResult
from rths_hil.records.recorder import RunData, read_run

#: Overrides every helper run starts from: no console line, no report figure.
QUIET = ("loop.console=0", "output.plot=false")


@dataclass
class LoopRun:
    """What a run left: the loop object, its result and the run directory as read back."""

    loop: RTHSLoop
    result: RunResult
    run: RunData


def run_loop(
    run_dir: Path, config: str | Path | None = None, *overrides: str, **loop_kwargs: Any
) -> LoopRun:
    """Run ``config`` (``None``: the embedded default) with ``overrides`` into ``run_dir``.

    ``loop_kwargs`` go to :class:`rths_hil.hybrid.RTHSLoop` (``mode``, ``duration``, ``plant``,
    ``live``, …); the :data:`QUIET` overrides come first, so ``overrides`` may change them.
    """
    cfg = load_config(config, [*QUIET, *overrides])
    loop = RTHSLoop(cfg, run_dir, **loop_kwargs)
    result = loop.run()
    return LoopRun(loop, result, read_run(run_dir))

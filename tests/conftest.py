"""Fixtures shared by the tests (helpers live in ``tests/helpers/``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.helpers.loop import LoopRun
from tests.helpers.loop import run_loop as _run_loop


@pytest.fixture
def run_loop(tmp_path: Path) -> Callable[..., LoopRun]:
    """Run a configuration through the loop into ``tmp_path / name``; see
    :func:`tests.helpers.loop.run_loop` (``run_loop(config, *overrides, name="run", **kw)``)."""

    def run(
        config: str | Path | None = None, *overrides: str, name: str = "run", **kw: Any
    ) -> LoopRun:
        return _run_loop(tmp_path / name, config, *overrides, **kw)

    return run

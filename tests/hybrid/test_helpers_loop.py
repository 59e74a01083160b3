"""The shared ``run_loop`` fixture (tests/conftest.py, tests/helpers/loop.py)."""

from __future__ import annotations

import numpy as np


def test_run_loop_runs_the_default_test_and_reads_its_record_back(run_loop) -> None:
    r = run_loop(None, "loop.mode=lockstep", "loop.fs=512", duration=0.5)
    assert r.result.status == "completed"
    assert r.loop.cfg["loop"]["fs"] == 512
    assert r.loop.cfg["loop"]["console"] == 0 and r.loop.cfg["output"]["plot"] is False
    rec = r.run.record
    assert rec.size == r.result.steps > 0
    np.testing.assert_allclose(np.diff(rec["time"]), 1 / 512, rtol=1e-9)
    assert r.run.path.name == "run"


def test_run_loop_overrides_come_after_the_quiet_defaults(run_loop) -> None:
    r = run_loop(None, "loop.mode=lockstep", "output.plot=true", name="loud", duration=0.1)
    assert r.loop.cfg["output"]["plot"] is True
    assert r.run.path.name == "loud"

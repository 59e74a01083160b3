"""A scheduled load: the column example's vertical actuator follows ``control.load_schedule``
(piecewise linear in the test's time) instead of a constant load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import rths_hil
from rths_hil.records.recorder import read_run

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "column_axial.toml"
SCHEDULE = [[0.0, 2e5], [1.0, 2e5], [2.0, 5e5], [3.0, 3e5]]  # s, N


def test_the_load_follows_its_schedule(tmp_path):
    out = tmp_path / "run"
    rths_hil.run(
        EXAMPLE,
        [
            "actuators.vertical.control.load=0",
            f"actuators.vertical.control.load_schedule={json.dumps(SCHEDULE)}",
            "actuators.vertical.control.load_ramp=0.5",
            "start.ramp_time=0.5",
        ],
        mode="lockstep",
        duration=4.0,
        run_dir=out,
    )
    rec = read_run(out).record
    t = np.asarray(rec["time"])
    want = np.interp(t, *np.array(SCHEDULE).T)
    np.testing.assert_allclose(np.asarray(rec["target_vertical"]), want, rtol=1e-12)
    force = np.asarray(rec["force_vertical"])
    # the 300 kN/s slopes through the twin's 5 ms delay and 4.8 ms force loop (no lead on
    # this channel): about 3 kN behind while loading, within 1 % of the peak throughout
    err = np.abs(force - want)
    assert np.max(err) < 0.01 * 5e5, np.max(err)
    flat = (t > 0.1) & (t < 1.0) | (t > 3.1)
    assert np.max(err[flat]) < 1e-3 * 5e5  # held
    # ramped up to the schedule's first force, down from its last
    events = [json.loads(x) for x in (out / "events.jsonl").read_text().splitlines()]
    (ramp,) = [e for e in events if e["kind"] == "start_ramp"]
    (end,) = [e for e in events if e["kind"] == "end_ramp"]
    i = ramp["channels"].index("vertical")
    assert ramp["end"][i] == 2e5 and end["start"][i] == 3e5 and end["end"][i] == 0.0

"""The live page's numbers (rths_hil.watch.shaping), checked without Bokeh against direct loops."""

from __future__ import annotations

import math
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from rths_hil.watch.shaping import (
    LimitShares,
    actuator_label,
    block_max,
    channel_control,
    channel_values,
    consecutive,
    finite_or,
    fit_range,
    stability_levels,
    stride,
    true_runs,
)

RNG = np.random.default_rng(27)


def test_shaping_imports_without_bokeh():  # a fresh interpreter (no clock, no server)
    code = "import sys, rths_hil.watch.shaping; print('bokeh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("n_rows", [0, 1, 599, 600, 601, 10240, 12345])
def test_stride_is_the_smallest_step_within_the_points(n_rows):
    m = stride(n_rows, 600)
    assert math.ceil(n_rows / m) <= 600
    assert m == 1 or math.ceil(n_rows / (m - 1)) > 600


@pytest.mark.parametrize("m", [1, 3, 7, 64])
def test_block_max_is_each_blocks_maximum(m):
    x = RNG.standard_normal(1000)
    want = [x[i : i + m].max() for i in range(0, x.size, m)]
    assert np.array_equal(block_max(x, m), want)


def test_true_runs_and_consecutive_match_a_loop():
    mask = RNG.random(500) < 0.6
    starts, ends = [], []
    for i, v in enumerate(mask):
        if v and (i == 0 or not mask[i - 1]):
            starts.append(i)
        if v and (i == mask.size - 1 or not mask[i + 1]):
            ends.append(i + 1)
    s, e = true_runs(mask)
    assert s.tolist() == starts and e.tolist() == ends
    for carry in (0, 5):
        run, want = carry, []
        for v in mask:
            run = run + 1 if v else 0
            want.append(run)
        assert consecutive(mask, carry).tolist() == want
    assert true_runs(np.zeros(0, bool))[0].size == 0


def test_fit_range_moves_only_when_the_data_leaves_or_shrinks():
    rng = SimpleNamespace(start=-1.0, end=1.0)
    fit_range(rng, -0.5, 0.6, 1e-3)  # inside and using more than a third: unchanged
    assert (rng.start, rng.end) == (-1.0, 1.0)
    fit_range(rng, -0.5, 2.0, 1e-3)  # leaves: 15 % of the span as room on each side
    assert rng.start == pytest.approx(-0.5 - 0.15 * 2.5)
    assert rng.end == pytest.approx(2.0 + 0.15 * 2.5)
    fit_range(rng, 0.0, 0.01, 1e-3)  # uses less than a third: shrinks around the data
    assert rng.start == pytest.approx(-0.0015) and rng.end == pytest.approx(0.0115)
    fit_range(rng, math.nan, 1.0, 1e-3)  # no data: unchanged
    assert rng.end == pytest.approx(0.0115)


def _record(n: int, ch: str = "") -> tuple[np.ndarray, list[str]]:
    sfx = f"_{ch}" if ch else ""
    bases = ("target", "command", "measured", "force", "fei_amplitude", "feedback_ok")
    names = ["time", *(b + sfx for b in bases)]
    dtype = [(nm, bool if nm.startswith("feedback_ok") else float) for nm in names]
    rec = np.zeros(n, dtype=dtype)
    rec["time"] = np.arange(n) / 100.0
    rec["target" + sfx] = 0.01 * np.sin(np.arange(n) / 10.0)
    rec["command" + sfx] = 1.1 * rec["target" + sfx]
    rec["measured" + sfx] = 0.9 * rec["target" + sfx] + 0.001 * RNG.standard_normal(n)
    rec["force" + sfx] = 5e4 * RNG.standard_normal(n)
    rec["fei_amplitude" + sfx] = 1.0 + 0.05 * RNG.standard_normal(n)
    rec["feedback_ok" + sfx] = RNG.random(n) > 0.2
    return rec, names


@pytest.mark.parametrize("ch", ["", "left"])
def test_limit_shares_match_direct_maxima_read_whole_or_in_pieces(ch):
    safety = {
        "displacement_limit": 0.02,
        "force_limit": 2e5,
        "fei_amplitude_tol": 0.2,
        "watchdog_missed": 4,
    }
    cfg = {"loop": {"fs": 100.0}, "kalman": {"enabled": False}, "safety": safety}
    rec, names = _record(900, ch)
    sfx = f"_{ch}" if ch else ""
    whole = LimitShares(ch, safety, cfg, paced=False).update(rec, names, 900, 50)
    pieces = LimitShares(ch, safety, cfg, paced=False)
    for k in (1, 17, 300, 301, 900):
        out = pieces.update(rec, names, k, 50)
    assert out["limit"] == whole["limit"]
    assert out["peak"] == pytest.approx(whole["peak"], rel=1e-12)
    disp = np.max(np.abs([rec[b + sfx] for b in ("target", "command", "measured")]), axis=0)
    missed, run = 0, 0
    for ok in rec["feedback_ok" + sfx]:
        run = 0 if ok else run + 1
        missed = max(missed, run)
    want = {
        "displacement": disp.max() / 0.02,
        "force": np.abs(rec["force" + sfx]).max() / 2e5,
        "FEI |A−1|": np.abs(rec["fei_amplitude" + sfx] - 1.0).max() / 0.2,
        "missed replies": missed / 4,
    }
    got = dict(zip(whole["limit"], whole["peak"], strict=True))
    assert set(got) == set(want)
    for label, v in want.items():
        assert got[label] == pytest.approx(min(v, 1.1), rel=1e-12), label
    # "used" is the latest refresh period's share (here the last 50 rows) for the signals
    used = dict(zip(whole["limit"], whole["used"], strict=True))
    assert used["displacement"] == pytest.approx(min(disp[-50:].max() / 0.02, 1.1), rel=1e-12)


def test_channel_values_missing_column_is_nan_and_labels():
    rec, names = _record(10, "left")
    assert np.array_equal(
        channel_values(rec, names, "target", "left", slice(2, 5)), rec["target_left"][2:5]
    )
    assert np.isnan(channel_values(rec, names, "velocity", "left", np.arange(3))).all()
    assert finite_or("x", 2.0) == 2.0 and finite_or(math.inf) == 0.0 and finite_or("3") == 3.0
    assert actuator_label("", {"channels": [{"name": "east"}]}) == "Actuator east"
    assert actuator_label("", {}) == "Actuator" and actuator_label("w", {}) == "Actuator w"


def test_watchdog_bar_discounts_the_bridges_stalls_like_the_rule():
    """The feedback watchdog's bar is the silence the loop's rule measures: the time since the
    latest good reply less the bridge's own stalls (``stall`` events), here checked against
    :class:`rths_hil.safety.WatchdogRule` fed the same reply times and stalls."""
    from rths_hil.safety import WatchdogRule

    fs, n, fb_wait = 1000.0, 400, 0.8 / 1000.0
    names = ["time", "lateness", "feedback_ok", "feedback_time"]
    rec = np.zeros(n, dtype=[(nm, bool if nm == "feedback_ok" else float) for nm in names])
    rec["time"] = np.arange(n) / fs
    stalls = {100: 0.04, 101: 0.01, 250: 0.02}  # step → length (s): the bridge did not run
    rec["lateness"] = np.cumsum([stalls.get(k, 0.0) for k in range(n)])
    ok = RNG.random(n) > 0.3
    ok[95:140] = False  # silence across the stalls
    rec["feedback_ok"] = ok
    rec["feedback_time"] = np.where(ok, 3e-4 + 1e-4 * RNG.random(n), np.nan)
    arrive = rec["time"] + rec["lateness"] + np.where(ok, rec["feedback_time"], fb_wait)
    events = [{"kind": "stall", "step": k, "length": x} for k, x in stalls.items()]

    # the rule, with a tiny timeout so that every missed step reports the silence it counts
    now = iter(arrive)
    rule = WatchdogRule(0, timeout=1e-12, clock=lambda: next(now))
    want = np.full(n, np.nan)
    for k in range(n):
        if k in stalls:  # between the previous step's reply and this step's send
            end = arrive[k - 1] + 1e-5 + stalls[k]
            rule.stalled(end - stalls[k], end)
        trip = rule.check(bool(ok[k]))
        if trip is not None:
            want[k] = trip.values["elapsed"]

    safety = {"watchdog_timeout": 0.05, "watchdog_missed": 0}
    cfg = {"loop": {"fs": fs}, "kalman": {"enabled": False}, "safety": safety}
    for pieces in ((n,), (50, 99, 100, 101, 260, n)):
        shares = LimitShares("", safety, cfg, paced=True)
        shares.note_stalls(events)
        bounds = zip((0, *pieces[:-1]), pieces, strict=True)
        got = np.concatenate(
            [shares._shares(rec, names, a, b)["feedback watchdog"] for a, b in bounds]
        )
        miss = ~ok & np.isfinite(want)
        np.testing.assert_allclose(got[miss] * 0.05, want[miss], rtol=0, atol=1e-9)
        assert got[miss].max() < 1.0  # 45 missed replies across 70 ms of stalls: no alarm
    # without the stall events the bar would have counted the stalls as silence
    blind = LimitShares("", safety, cfg, paced=True)._shares(rec, names, 0, n)["feedback watchdog"]
    assert blind[139] * 0.05 - want[139] == pytest.approx(0.05, abs=1e-9)  # steps 100, 101


def test_stability_levels_are_the_rules_and_none_when_off():
    """The S plot's lines: the warning and the limit of ``[safety]`` while the rule is on
    (in "warn" the limit is where "trip" would stop), none when it is off; a level that is not
    a positive number is not drawn."""
    sf = {"stability": "warn", "stability_warn": 1.0, "stability_limit": 1.5}
    assert stability_levels(sf) == {"warn": 1.0, "limit": 1.5}
    assert stability_levels({**sf, "stability": "trip", "stability_warn": 0.8}) == {
        "warn": 0.8,
        "limit": 1.5,
    }
    assert stability_levels({**sf, "stability": "off"}) == {}
    assert stability_levels({}) == {}
    assert stability_levels({**sf, "stability_limit": 0.0}) == {"warn": 1.0}
    assert stability_levels({**sf, "stability_warn": "nan"}) == {"limit": 1.5}


def test_channel_control_from_the_channel_description_or_the_configuration():
    cfg = {
        "control": {"mode": "displacement"},
        "actuators": [{"name": "v", "control": {"mode": "load", "load": 6e5}}, {"name": "h"}],
    }
    assert channel_control({"config": cfg}, "v") == "load"
    assert channel_control({"config": cfg}, "h") == "displacement"
    # the run's channel description wins over the configuration
    meta = {"config": cfg, "channels": [{"name": "h", "control": "force"}]}
    assert channel_control(meta, "h") == "force"
    assert channel_control({"config": {"control": "force"}}, "") == "force"
    assert channel_control({}, "") == "displacement"


def test_limit_shares_of_a_force_channel_count_its_commands_as_forces():
    """A force-controlled channel's target and command are forces: they count against the force
    limit with the measured force; the displacement limit sees the measured and the trial
    displacement."""
    safety = {"displacement_limit": 0.02, "force_limit": 2e5}
    cfg = {"loop": {"fs": 100.0}, "kalman": {"enabled": False}, "safety": safety}
    rec0, names = _record(300, "")
    rec = np.zeros(300, dtype=[*rec0.dtype.descr, ("trial", float)])
    for nm in names:
        rec[nm] = rec0[nm]
    names = [*names, "trial"]
    rec["target"] = 1.5e5 * RNG.standard_normal(300)  # N
    rec["command"] = 1.5e5 * RNG.standard_normal(300)  # N
    rec["trial"] = 0.012 * RNG.standard_normal(300)  # m
    got = LimitShares("", safety, cfg, paced=False, control="force").update(rec, names, 300, 50)
    peak = dict(zip(got["limit"], got["peak"], strict=True))
    f = np.max(np.abs([rec["target"], rec["command"], rec["force"]]), axis=0).max()
    d = np.max(np.abs([rec["measured"], rec["trial"]]), axis=0).max()
    assert peak["force"] == pytest.approx(min(f / 2e5, 1.1), rel=1e-12)
    assert peak["displacement"] == pytest.approx(min(d / 0.02, 1.1), rel=1e-12)

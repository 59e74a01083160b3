"""The stability rule: its levels alone, and on the loop with stable and unstable twins.

The unstable twin is the reproducible runaway of ``docs/stability.md``: the default test
without compensation (20 ms lag + 5 ms delay) on a 30 MN/m, nearly elastic specimen, which
reaches the 50 mm displacement limit at 9.10 s when nothing else stops it. Its figures here come
from the run itself (the displacement limit's time from a run without the stability rule), not
from the rule's code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rths_hil import open_run, run
from rths_hil.errors import InputError
from rths_hil.safety import StabilityRule
from rths_hil.stability import stability_indicator

UNSTABLE = {
    "compensation.enabled": False,
    "twin.specimen": {"stiffness": 3e7, "damping": 114.6},
    "structure.k_specimen": 3e7,
    "safety.fei_amplitude_tol": 0,
    "safety.fei_delay_tol": 0,
    "safety.force_limit": 0,
    "safety.velocity_limit": 0,
    "loop.console": 0,
    "output.plot": False,
}


# ---------------------------------------------------------------------------------------------
# the rule alone


def test_warns_once_per_crossing_and_rearms_below_nine_tenths():
    rule = StabilityRule(1.0, 1.5, trip=False, channel="left")
    seen = []
    for s in (math.nan, 0.5, 1.1, 1.2, 0.95, 1.3, 0.85, 1.05, 2.0):
        assert rule.check(s) is None  # "warn": never a trip, even at 2
        if rule.warning is not None:
            seen.append(rule.warning)
            rule.warning = None
    assert seen == [1.1, 1.05]  # 0.95 does not re-arm; 0.85 does


def test_trips_above_the_limit_naming_channel_and_figure():
    rule = StabilityRule(1.0, 1.5, trip=True, channel="storey1")
    assert rule.check(1.49) is None
    trip = rule.check(1.7, injected=123.0)
    assert trip is not None and trip.rule == "stability"
    assert "storey1" in trip.reason and "1.7" in trip.reason and "1.5" in trip.reason
    assert trip.values["ratio"] == 1.7 and trip.values["injected"] == 123.0
    assert rule.check(0.1) is trip  # stays tripped
    assert rule.check(math.nan) is trip


def test_limit_below_warning_is_refused():
    with pytest.raises(InputError, match="stability_limit"):
        StabilityRule(2.0, 1.5, trip=True)


def test_unknown_mode_is_refused(tmp_path):
    with pytest.raises(InputError, match=r"safety\.stability"):
        run(None, {"safety.stability": "maybe"}, mode="lockstep", run_dir=tmp_path / "r")


# ---------------------------------------------------------------------------------------------
# on the loop


@pytest.fixture(scope="module")
def runaway(tmp_path_factory):
    """The unstable case with the displacement limit as the only stopping rule."""
    d = tmp_path_factory.mktemp("runaway")
    res = run(None, UNSTABLE, mode="lockstep", duration=10.0, run_dir=d / "r", summary=False)
    return res, open_run(res.run_dir)


def test_unstable_twin_trips_on_the_indicator_before_the_displacement_limit(tmp_path, runaway):
    free, _ = runaway
    assert free.trip is not None and free.trip.rule == "displacement"
    t_disp = free.trip.time
    res = run(
        None,
        {**UNSTABLE, "safety.stability": "trip"},
        mode="lockstep",
        duration=10.0,
        run_dir=tmp_path / "r",
        summary=False,
    )
    assert res.status == "trip" and res.trip.rule == "stability"
    assert res.trip.time < t_disp - 1.0  # more than a second before the runaway's trip
    rec = open_run(res.run_dir).record
    assert np.abs(rec["target"]).max() < 0.5 * 0.050  # stopped below half the stroke limit
    assert "S = " in res.trip.reason
    # the warning event came with (or before) the trip
    events = [e for e in open_run(res.run_dir).events if e.get("kind") == "stability"]
    assert events and events[0]["time"] <= res.trip.time


def test_the_record_column_is_the_indicator_of_the_recorded_signals(runaway):
    """The loop's ``stability`` column equals the indicator computed afterwards from the
    record's own target, measured, force and velocity (online = offline)."""
    _, r = runaway
    rec = r.record
    end = next(e for e in r.events if e.get("kind") == "end")
    e = end["stability"][""]
    res = stability_indicator(
        rec["target"], rec["measured"], rec["force"], rec["velocity"], r.fs, e["window"],
        e["damping"], 2e-4,
    )  # fmt: skip
    col = rec["stability"]
    assert np.array_equal(np.isfinite(col), res.valid)
    assert np.allclose(col, res.ratio, rtol=1e-9, equal_nan=True)
    assert e["injected"] == pytest.approx(res.injected[-1], rel=1e-9)
    # the SDOF frame's c = 2ζ√(k m) (2 %, 0.77 Hz, 503.4 t)
    m = 503.4e3
    assert e["damping"] == pytest.approx(2 * 0.02 * math.sqrt(m * (2 * math.pi * 0.77) ** 2 * m))
    # it warned: the runaway injects several times what the damping dissipates
    assert np.nanmin(col) > 3.0


def test_default_test_never_warns(tmp_path):
    """The default test (compensated) through the El Centro record's strong motion."""
    res = run(
        None,
        {"loop.console": 0, "output.plot": False},
        mode="lockstep",
        duration=15.0,
        run_dir=tmp_path / "r",
    )
    assert res.status == "completed"
    r = open_run(res.run_dir)
    assert not [e for e in r.events if e.get("kind") == "stability"]
    s = r.record["stability"]
    assert np.isfinite(s).mean() > 0.5  # the indicator was valid most of the run ...
    assert np.nanmax(np.abs(s)) < 0.1  # ... and far from its limit (compensated: S ≈ 0)
    summary = r.summary()
    assert summary["stability"]["warnings"] == 0
    assert summary["stability"]["peak"] < 0.1


def test_off_has_no_indicator(tmp_path):
    res = run(
        None,
        {**UNSTABLE, "safety.stability": "off"},
        mode="lockstep",
        duration=6.0,
        run_dir=tmp_path / "r",
        summary=False,
    )
    r = open_run(res.run_dir)
    assert np.isnan(r.record["stability"]).all()
    assert not [e for e in r.events if e.get("kind") == "stability"]


def test_live_view_bar_is_s_over_its_limit():
    """The live view's margin bar of the indicator: the largest valid S over the limit."""
    from rths_hil.watch.shaping import LimitShares

    n = 200
    rec = np.zeros(n, dtype=[("time", "<f8"), ("target", "<f8"), ("stability", "<f8")])
    rec["time"] = np.arange(n) / 100.0
    s = np.full(n, np.nan)
    s[50:] = np.linspace(-0.5, 1.2, n - 50)
    rec["stability"] = s
    safety = {"stability": "warn", "stability_limit": 1.5}
    cfg = {"loop": {"fs": 100.0}, "kalman": {"enabled": False}, "safety": safety}
    out = LimitShares("", safety, cfg, paced=False).update(rec, rec.dtype.names, n, 50)
    got = dict(zip(out["limit"], out["peak"], strict=True))
    assert got["stability S"] == pytest.approx(1.2 / 1.5)
    off = LimitShares("", {**safety, "stability": "off"}, cfg, paced=False)
    assert "stability S" not in off.update(rec, rec.dtype.names, n, 50)["limit"]

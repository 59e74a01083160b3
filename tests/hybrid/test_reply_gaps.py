"""Missed replies are a degradation, a dead link a trip (issue 33, item 7).

* The Kalman filter is never fed a held measurement as a fresh one: over a gap of 160 held
  samples its gain estimate stays where it was, where feeding them as measurements drags it
  towards 0.5 (the trip "Kalman gain estimate 0.4992" after 163 missed replies);
* the streaming FEI counts the held samples of its window (an independent count over the last
  N flags) and does not trust a window with more than :data:`MAX_HELD_SHARE` of them;
* a paced run whose controller pauses 40 ms (40 missed replies at 1024 Hz) completes under the
  default ``safety.watchdog_timeout``: one ``reply_gap`` event (start, count, length), the
  record's ``feedback_ok`` false exactly there, the summary's ``reply_gaps``;
* a closed transport trips the ``link`` rule at the first reply it costs, without waiting for
  the watchdog's limit.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from rths_hil.config import default_config
from rths_hil.estimation import DelayGainEstimator
from rths_hil.hybrid.evaluators import MAX_HELD_SHARE, StreamingFEI
from rths_hil.report import format_summary, summarize
from tests.helpers.loop import run_loop

FS = 1024.0


def _sine(n: int, gain: float, delay: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / FS
    u = 0.01 * np.sin(2 * np.pi * 1.5 * t)
    y = gain * 0.01 * np.sin(2 * np.pi * 1.5 * (t - delay))
    return u, y


def test_kalman_skips_held_measurements():
    u, y = _sine(4096 + 160 + 1024, gain=1.0, delay=0.01)
    gap = slice(4096, 4096 + 160)

    def run(fresh_in_gap: bool) -> tuple[list[float], DelayGainEstimator]:
        est = DelayGainEstimator(FS)
        gains = []
        held = 0.0
        for i, (a, b) in enumerate(zip(u, y, strict=True)):
            if gap.start <= i < gap.stop:  # no reply: the loop repeats the last measurement
                g, _ = est.update(a, held, fresh=fresh_in_gap)
            else:
                held = b
                g, _ = est.update(a, b)
            gains.append(g)
        return gains, est

    gains, est = run(fresh_in_gap=False)
    before = gains[gap.start - 1]
    assert abs(before - 1.0) < 0.02  # converged before the gap
    # through the gap (and the look-ahead after it) the estimate does not move
    assert max(abs(g - before) for g in gains[gap.start : gap.stop + est._m + 1]) < 1e-9
    assert abs(gains[-1] - 1.0) < 0.02 and abs(est.delay - 0.01) < 2e-3  # and tracks after it
    # the reference: the same held samples fed as measurements drag the gain far off
    bad, _ = run(fresh_in_gap=True)
    assert min(bad[gap.start : gap.stop + 50]) < 0.8


def test_streaming_fei_counts_held_samples_of_its_window():
    fei = StreamingFEI(FS, 1.0)
    n = fei.N
    rng = np.random.default_rng(3)
    flags = rng.random(3 * n) < 0.04
    flags[2 * n : 2 * n + int(0.15 * n)] = True  # one stretch: 15 % of a window held
    u, y = _sine(3 * n, 1.0, 0.005)
    valid_after = []
    for i, h in enumerate(flags):
        done = fei.push(u[i], y[i], bool(h))
        # an independent count: held flags among the last N samples
        assert fei.held == int(flags[max(0, i - n + 1) : i + 1].sum())
        if done:
            share = flags[i - n + 1 : i + 1].mean()
            valid_after.append((share, fei.latest[3]))
    assert any(s > MAX_HELD_SHARE for s, _ in valid_after)
    for share, valid in valid_after:
        if share > MAX_HELD_SHARE:
            assert not valid, share
    # below the limit the window is judged as ever (this sine gives valid windows)
    assert any(valid for share, valid in valid_after if 0 < share <= MAX_HELD_SHARE)


def test_default_watchdog_outlasts_controller_pauses_and_stays_inside_its_watchdog():
    """The documented default: above a 40 ms pause, well inside a 200 ms controller watchdog."""
    wd = default_config()["safety"]["watchdog_timeout"]
    assert 0.04 * 2 <= wd <= 0.2 / 2


BASE = [
    "loop.console=0",
    "output.plot=false",
    "fei.enabled=false",
    "kalman.enabled=true",
    "twin.sensor={displacement_noise = 0.0, force_noise = 0.0}",
    "safety.max_overruns=1000000",  # the rule under test only (the machine's stalls aside)
]
AT = 400  # first missed reply
PAUSE = 40  # missed replies in a row (≈ 39 ms at 1024 Hz): a controller's own pause


@pytest.mark.timing
def test_paced_pause_is_a_gap_not_a_trip(tmp_path):
    drops = ",".join(str(AT + i) for i in range(PAUSE))
    r = run_loop(tmp_path / "run", None, *BASE, f"twin.faults=drop={drops}", mode="paced",
                 duration=1.0)  # fmt: skip
    res, run = r.result, r.run
    assert res.status == "completed", res.trip
    ok = np.asarray(run.record["feedback_ok"], dtype=bool)
    # the twin's sequence numbers are the loop's (no start ramp: it is at rest)
    assert res.start_steps == 0
    missed = np.flatnonzero(~ok)
    assert set(range(AT, AT + PAUSE)) <= set(missed.tolist())
    gaps = [e for e in run.events if e["kind"] == "reply_gap"]
    (pause,) = [e for e in gaps if e["step"] <= AT < e["step"] + e["count"]]
    assert pause["step"] == AT and pause["count"] == PAUSE and pause["ended"] is True
    assert pause["start"] == pytest.approx(AT / FS)
    assert PAUSE / FS * 0.9 <= pause["length"] < 0.1
    # the held measurement: the record repeats the last good one through the gap
    meas = np.asarray(run.record["measured"])
    assert np.all(meas[AT : AT + PAUSE] == meas[AT - 1])
    summary = summarize(run.path)
    rg = summary["reply_gaps"]
    assert rg["missed"] == res.missed_replies == int((~ok).sum())
    assert rg["count"] == len(gaps) and rg["longest_steps"] >= PAUSE
    assert json.loads((run.path / "summary.json").read_text())["reply_gaps"] == rg
    assert f"{rg['longest_steps']} steps; measurement held" in format_summary(summary)
    # the Kalman filter held its estimate through the gap (no held sample as a measurement),
    # from the step its look-ahead M (the measurement M samples back) reaches the first one
    g = np.asarray(run.record["kf_gain"])
    m = r.loop.channels[0].kalman._m
    assert m < PAUSE - 5 and np.ptp(g[AT + m : AT + PAUSE]) < 1e-12


@pytest.mark.timing
@pytest.mark.parametrize("mode", ["paced", "lockstep"])
def test_closed_transport_trips_the_link_rule_at_once(tmp_path, mode):
    at = 300
    r = run_loop(tmp_path / "run", None, *BASE, "driver.name=modbus",
                 f"twin.faults=disconnect_from={at}", "loop.lockstep_timeout=1.0", mode=mode,
                 duration=1.0)  # fmt: skip
    res = r.result
    assert res.status == "trip" and res.trip.rule == "link", res.trip
    assert "modbus connection" in res.trip.reason
    # the first reply the closed socket costs (or the one after, when the close lands late)
    assert at <= res.trip.step <= at + 2, res.trip

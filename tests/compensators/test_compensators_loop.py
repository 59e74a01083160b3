"""Compensation goals measured end to end in lockstep on the twins (deterministic).

* the default configuration tracks at 2048 and 4096 Hz as at 1024 Hz (compensation in time);
* ``examples/two_actuators.toml`` with ``polynomial``: every channel |A − 1| ≤ 1 %, |d| ≤ 0.5 ms;
* ``ats`` from an initial delay 50 % wrong: |d| ≤ 1 ms within 10 s;
* ``ats`` on an actuator whose delay steps from 15 to 25 ms: back within 1 ms in ≤ 5 s, no trip.

A and d are the FEI paper's amplitude and equivalent delay of measured vs target.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rths_hil.fei import fei
from tests.helpers.loop import run_loop

ROOT = Path(__file__).resolve().parents[2]
TWO = ROOT / "examples" / "two_actuators.toml"


def _run(tmp_path, path, *sets, plant=None, name="run"):
    r = run_loop(tmp_path / name, path, "loop.mode=lockstep", *sets, plant=plant)
    return r.loop.cfg, r.result, r.run.record


def _whole(rec, fs, sfx=""):
    r = fei(rec["target" + sfx], rec["measured" + sfx], fs)
    return r.amplitude, r.delay


@pytest.fixture(scope="module")
def at_1024(tmp_path_factory):
    _, res, rec = _run(tmp_path_factory.mktemp("fs"), None, "loop.duration=10")
    assert res.status == "completed"
    return _whole(rec, 1024.0)


@pytest.mark.parametrize("fs", [2048.0, 4096.0])
def test_default_config_tracks_at_a_higher_rate_as_at_1024_hz(tmp_path, at_1024, fs):
    cfg, res, rec = _run(tmp_path, None, "loop.duration=10", f"loop.fs={fs}")
    assert res.status == "completed" and res.steps == 10 * fs
    assert cfg["compensation"]["delay"] == 0.025  # the same compensation, in time
    assert rec["alpha"][0] == pytest.approx(1 + 0.025 * fs)
    a, d = _whole(rec, fs)
    a0, d0 = at_1024
    assert abs(d - d0) <= 0.5e-3, (d, d0)
    assert abs(a - a0) <= 0.005, (a, a0)
    assert abs(d) < 1e-3  # and it tracks (without the change it tripped at d = 18 ms)


def test_two_actuators_with_polynomial_every_channel_within_1_percent_and_half_a_ms(tmp_path):
    _, res, rec = _run(tmp_path, TWO, "loop.duration=20", "compensation.method=polynomial")
    assert res.status == "completed"
    for sfx in ("_storey1", "_storey3"):
        a, d = _whole(rec, 1024.0, sfx)
        assert abs(a - 1) <= 0.01, (sfx, a)
        assert abs(d) <= 0.5e-3, (sfx, d)
    # inverse compensation leaves the 3 % overshoot on the 20 ms channel (the test can fail)
    _, res, rec = _run(tmp_path, TWO, "loop.duration=20", name="inverse")
    assert abs(_whole(rec, 1024.0, "_storey3")[0] - 1) > 0.02


def test_ats_from_a_delay_50_percent_wrong_tracks_within_1_ms_in_10_s(tmp_path):
    _, res, rec = _run(
        tmp_path,
        TWO,
        "loop.duration=20",
        "compensation.method=ats",
        "actuators.storey1.compensation.delay=5ms",  # twin: 10 ms
        "actuators.storey3.compensation.delay=10ms",  # twin: 20 ms
    )
    assert res.status == "completed"
    t = rec["time"]
    for sfx in ("_storey1", "_storey3"):
        assert rec["alpha" + sfx][0] == pytest.approx(
            1 + (0.005 if sfx == "_storey1" else 0.01) * 1024
        )
        late = rec["fei_valid" + sfx] & (t >= 10.0)
        assert late.sum() > 9 * 1024
        assert np.abs(rec["fei_delay" + sfx][late]).max() <= 1e-3, sfx
        a, _ = _whole(rec, 1024.0, sfx)
        assert abs(a - 1) <= 0.01


class DelayStepPlant:
    """A pure delay of ``d1`` samples growing to ``d2`` from step ``at``, on a linear spring.

    The delay grows by one sample every second step (the actuator moves at half speed for
    ten steps) rather than in one go, so that the measured displacement does not jump.
    """

    def __init__(self, d1: int, d2: int, at: int, fs: float, stiffness: float = 1.19e6) -> None:
        self.dt = 1 / fs
        self.d1, self.d2, self.at, self.stiffness = d1, d2, at, stiffness
        self.reset()

    def reset(self) -> None:
        self.hist: list[float] = []

    def step(self, command: float) -> tuple[float, float]:
        self.hist.append(command)
        k = len(self.hist) - 1
        d = self.d1 if k < self.at else min(self.d2, self.d1 + (k - self.at) // 2)
        x = self.hist[k - d] if k >= d else 0.0
        return x, self.stiffness * x


def test_ats_follows_a_delay_step_from_15_to_25_ms_within_5_s_without_a_trip(tmp_path):
    fs, t_step = 1024.0, 8.0
    plant = DelayStepPlant(round(0.015 * fs), round(0.025 * fs), int(t_step * fs), fs)
    _, res, rec = _run(
        tmp_path,
        None,
        "loop.duration=20",
        "compensation.method=ats",
        "compensation.delay=15ms",
        "twin.sensor={}",
        plant=plant,
    )
    assert res.status == "completed" and res.trip is None
    t, v, d = rec["time"], rec["fei_valid"], rec["fei_delay"]
    before = v & (t > 5.0) & (t < t_step)
    assert np.abs(d[before]).max() <= 1e-3
    after = v & (t >= t_step + 5.0)
    assert after.sum() > 6 * fs
    assert np.abs(d[after]).max() <= 1e-3
    assert rec["alpha"][-1] == pytest.approx(1 + 0.025 * fs, abs=2.0)  # a1 followed the step
    # between, the step shows (the check can fail): more than 1 ms somewhere after the step
    assert np.abs(d[v & (t > t_step) & (t < t_step + 5.0)]).max() > 1e-3

"""A stall of the bridge itself is not controller silence (safety.max_stall, loop.after_stall).

Unit tests of the watchdog's stall discount and of the stall rule on a scripted clock, then
real paced runs of the default test frozen with SIGSTOP/SIGCONT: a 40 ms freeze completes with
a stall event (and no watchdog trip), an 800 ms freeze trips on the stall rule, a catch-up
after a stall never commands faster than the velocity limit, and a console that goes away
mid-run does not stop the test.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rths_hil.records.recorder import header_row_count, read_run
from rths_hil.safety import StallRule, WatchdogRule

# the real runs, against the wall clock and in other processes, run apart from the parallel
# tests (the "timing" marker, pyproject.toml; make test); the rules on a scripted clock do not
timing = pytest.mark.timing


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


# ---- the rules --------------------------------------------------------------------------------


def test_watchdog_trips_on_silence_after_its_timeout():
    clk = Clock()
    wd = WatchdogRule(0, 0.02, clock=clk)
    assert wd.check(True) is None
    for _ in range(19):  # 19 ms of silence, one check per millisecond
        clk.t += 1e-3
        assert wd.check(False) is None
    clk.t += 1.5e-3
    trip = wd.check(False)
    assert trip is not None and trip.rule == "watchdog"
    assert trip.values["elapsed"] == pytest.approx(0.0205)
    assert trip.values["missed"] == 20


def test_watchdog_does_not_count_a_stall_of_the_bridge():
    clk = Clock()
    wd = WatchdogRule(0, 0.02, clock=clk)
    wd.check(True)
    t_ok = clk.t
    # the bridge froze for 40 ms (from 1 ms after the reply), then found no reply at once
    wd.stalled(t_ok + 1e-3, t_ok + 41e-3)
    clk.t = t_ok + 42e-3
    assert wd.check(False) is None  # 2 ms of silence while it ran
    clk.t = t_ok + 59e-3
    assert wd.check(False) is None  # 19 ms
    clk.t = t_ok + 62e-3
    trip = wd.check(False)  # 22 ms while it ran: the controller is silent
    assert trip is not None
    assert trip.values["elapsed"] == pytest.approx(0.022)
    assert trip.values["stalled"] == pytest.approx(0.040)
    assert "40.0 ms of bridge stall not counted" in trip.reason


def test_watchdog_stall_before_the_last_reply_is_not_discounted_again():
    clk = Clock()
    wd = WatchdogRule(0, 0.02, clock=clk)
    wd.check(True)
    t0 = clk.t
    clk.t = t0 + 50e-3
    assert wd.check(True) is None  # the reply after a freeze inside the receive: not silence
    # the same freeze found afterwards (the next deadline was late): only the part after the
    # reply may be discounted
    wd.stalled(t0 + 1e-3, t0 + 50.5e-3)
    clk.t = t0 + 50e-3 + 21e-3
    trip = wd.check(False)
    assert trip is not None
    assert trip.values["elapsed"] == pytest.approx(0.0205)


def test_watchdog_step_count_is_virtual_time():
    wd = WatchdogRule(21, None)
    assert all(wd.check(False) is None for _ in range(20))
    assert wd.check(False).values["missed"] == 21


def test_stall_rule_counts_and_trips_above_its_limit():
    rule = StallRule(0.2, 0.002)
    assert rule.check(0.04) is None and rule.check(0.15) is None
    trip = rule.check(0.8)
    assert trip is not None and trip.rule == "stall"
    assert "stalled for 800.0 ms" in trip.reason and "not at fault" in trip.reason
    assert rule.count == 3 and rule.longest == 0.8
    assert rule.total == pytest.approx(0.99)


def test_lockstep_watchdog_limit_is_the_timeout_in_steps():
    from rths_hil.config import load_config
    from rths_hil.hybrid.plan import build_plan

    # the default safety.watchdog_timeout, 0.1 s: ceil(0.1 · fs) steps of virtual time
    for fs, steps in ((1024, 103), (4096, 410)):
        cfg = load_config(None, [f"loop.fs={fs}", "loop.duration=1"])
        plan = build_plan(cfg, Path("unused"), mode="lockstep")
        assert plan.channels[0].monitor.watchdog.missed == steps
        plan = build_plan(cfg, Path("unused"), mode="paced")
        wd = plan.channels[0].monitor.watchdog
        assert wd.timeout == 0.1 and wd.missed == 0


# ---- real paced runs, frozen from outside -------------------------------------------------------


def _start(out: Path, *extra: str, quiet: bool = True, duration: str = "4") -> subprocess.Popen:
    cmd = [sys.executable, "-m", "rths_hil", "run", "--paced", "--duration", duration]
    cmd += ["--out", str(out), "--set", "output.plot=false", *extra]
    if quiet:
        cmd.append("-q")
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_rows(path: Path, proc: subprocess.Popen, rows: int = 1024, timeout: float = 60) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        assert proc.poll() is None, proc.communicate()
        if path.exists() and header_row_count(path) >= rows:
            return
        time.sleep(0.01)
    raise AssertionError("the run never flushed enough rows")


def _freeze(proc: subprocess.Popen, seconds: float) -> None:
    os.kill(proc.pid, signal.SIGSTOP)
    time.sleep(seconds)
    os.kill(proc.pid, signal.SIGCONT)


def _events(out: Path, kind: str) -> list[dict]:
    return [e for e in read_run(out).events if e["kind"] == kind]


@timing
def test_a_40_ms_freeze_of_the_bridge_completes_with_a_stall_event(tmp_path):
    out = tmp_path / "run"
    # frozen after 0.5 s; the 0.6 s left hold the ≥ 100 steps after the stall checked below
    proc = _start(out, duration="1.1")
    _wait_rows(out / "record.npy", proc, rows=512)
    _freeze(proc, 0.04)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    stalls = _events(out, "stall")
    longest = max(stalls, key=lambda e: e["length"])
    assert 0.035 <= longest["length"] <= 0.19, stalls
    assert longest["action"] == "slip"
    assert not _events(out, "trip")
    end = _events(out, "end")[0]
    assert end["status"] == "completed"
    assert end["stalls"]["count"] == len(stalls)
    assert end["stalls"]["longest"] == pytest.approx(longest["length"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stalls"] == end["stalls"]
    # slip: a new clock event at the stalled step, and the step after it on time again
    k = longest["step"]
    clocks = [e for e in _events(out, "clock") if e["step"] == k]
    assert len(clocks) == 1 and clocks[0]["slip"] >= longest["length"] - 1e-3
    lat = read_run(out).record["lateness"]
    assert lat[k] >= longest["length"] - 1e-3
    assert np.median(lat[k + 1 : k + 100]) < 1e-3


@timing
def test_an_800_ms_freeze_trips_naming_the_stall_not_the_controller(tmp_path):
    out = tmp_path / "run"
    proc = _start(out, duration="10")  # (it trips first)
    _wait_rows(out / "record.npy", proc, rows=256)
    _freeze(proc, 0.8)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 3, err
    trip = _events(out, "trip")[0]
    assert trip["rule"] == "stall", trip
    assert 0.75 <= trip["values"]["stall"] <= 1.5
    assert "bridge itself stalled" in err and "watchdog" not in err
    estops = _events(out, "estop")
    assert estops and all(e["confirmed"] for e in estops)
    assert _events(out, "end")[0]["status"] == "trip"


@timing
def test_catch_up_after_a_stall_keeps_the_command_within_the_velocity_limit(tmp_path):
    """loop.after_stall = catch_up: the missed steps are run back to back, but the command
    never moves faster (in wall-clock time between sends) than safety.velocity_limit."""
    out = tmp_path / "run"
    # m/s: above the structure's peak velocity (0.06 m/s), below a free catch-up's (several
    # steps per period)
    vlim = 0.1
    proc = _start(
        out,
        "--set", "loop.after_stall=catch_up",
        "--set", f"safety.velocity_limit={vlim}",
        "--set", "safety.max_overruns=100000",
        duration="3",  # frozen after 2 s; the catch-up (≈ 60 steps) ends well before the end
    )  # fmt: skip
    # the default test moves strongly from 1.8 s (≈ 0.04 m/s at 2 s: sent back to back, the
    # catch-up's steps would command several m/s)
    _wait_rows(out / "record.npy", proc, rows=2 * 1024)
    _freeze(proc, 0.06)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    # the freeze, or a stall of a loaded machine between the rows waited for and it: the
    # catch-up steps of every stall from there on are checked (not the longest stall's: on a
    # loaded machine that may come in the run's last steps)
    stall = next(e for e in _events(out, "stall") if e["step"] >= 2 * 1024)
    assert stall["action"] == "catch_up"
    assert not [e for e in _events(out, "clock") if "slip" in e]
    rec = read_run(out).record
    k = stall["step"]
    sent = rec["time"] + rec["lateness"]  # send time of each step on the run's grid
    late = np.flatnonzero(rec["lateness"][k:] > 0.5 / 1024) + k  # the catch-up steps
    assert late.size > 10  # it did catch up step by step
    i = late[late > 0]
    dc = np.abs(np.diff(rec["command"])[i - 1])
    dts = np.diff(sent)[i - 1]
    assert (dc <= vlim * dts * (1 + 1e-6) + 1e-9).all(), (dc / dts).max()


def test_catch_up_spacing_waits_for_the_slowest_channel():
    """The spacing rule itself: the send waits |Δc| / v_lim after the previous send for the
    channel that needs longest; channels without a velocity limit do not hold it back. The
    clock is a counter (0.1 ms a reading), so the wait is exact whatever the machine does."""
    from types import SimpleNamespace as NS

    from rths_hil.hybrid.pacer import Pacer
    from rths_hil.hybrid.step import Step

    ticks = iter(range(1, 10**6))
    pacer = Pacer(1e-3, 3e-4, clock=lambda: next(ticks) * 1e-4)
    chans = [
        NS(command=1e-3, last_command=0.0, monitor=NS(vel_limit=1.0)),  # 1 mm at 1 m/s: 1 ms
        NS(command=2e-3, last_command=1e-3, monitor=NS(vel_limit=0.5)),  # 1 mm at 0.5 m/s: 2 ms
        NS(command=1.0, last_command=0.0, monitor=NS(vel_limit=math.inf)),
    ]
    t = pacer.prev_send = 0.0
    sent = Step.catch_up(NS(chans=chans, pacer=pacer), t)
    assert 2e-3 <= sent - t < 2e-3 + 1e-4  # the first reading at or past 2 ms (not 1 or 3)
    sent = Step.catch_up(NS(chans=chans[2:], pacer=pacer), t)
    assert sent == t


@timing
def test_the_test_goes_on_when_the_console_goes_away(tmp_path):
    """Closing the terminal's stderr (the reading end of its pipe) mid-run: no traceback, no
    exit 1: the run completes and records its end."""
    out = tmp_path / "run"
    # closed after 0.5 s: a console line every 50 ms into the closed pipe for the 0.5 s left
    proc = _start(out, "--set", "loop.console=0.05", quiet=False, duration="1.0")
    _wait_rows(out / "record.npy", proc, rows=512)
    proc.stderr.close()
    proc.stdout.close()
    assert proc.wait(timeout=60) == 0
    end = _events(out, "end")[0]
    assert end["status"] == "completed"
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"


def _freeze_in_the_start_ramp(out: Path, seconds: float) -> subprocess.Popen:
    """A paced run whose actuator starts 10 mm off (a start ramp of π/2 · 10 mm / 10 mm/s ≈
    1.6 s, start.velocity), frozen for ``seconds`` about 0.5 s into the ramp."""
    over = ["--set", "twin.initial_position=0.01", "--set", "start.ramp_time=1"]
    proc = _start(out, *over, duration="0.2")
    events = out / "events.jsonl"
    t_end = time.monotonic() + 60
    while not (events.exists() and '"start_position"' in events.read_text()):
        assert proc.poll() is None and time.monotonic() < t_end, proc.communicate()
        time.sleep(0.005)
    time.sleep(0.5)
    _freeze(proc, seconds)
    return proc


@timing
def test_a_stall_in_the_start_ramp_slips_the_ramp_instead_of_bursting_through_it(tmp_path):
    """After a 60 ms freeze the ramp goes on at its own pace: its wall time is its duration plus
    the stall (the steps it missed are not sent back to back, faster than the ramp)."""
    out = tmp_path / "run"
    proc = _freeze_in_the_start_ramp(out, 0.06)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    stalls = [e for e in _events(out, "stall") if e.get("phase") == "start"]
    assert stalls, _events(out, "stall")
    stall = max(stalls, key=lambda e: e["length"])  # (the machine may add short ones)
    assert 0.05 <= stall["length"] <= 0.19 and stall["action"] == "slip", stall
    assert stall["step"] < 0  # a start-phase step
    ramp = _events(out, "start_ramp")[0]
    assert ramp["completed"] and ramp["duration"] > 1.5, ramp
    planned = ramp["duration"] + ramp["hold"]
    # slipped: the stall is added (bursting through, the ramp would end on its planned time)
    assert ramp["wall_duration"] >= planned + 0.8 * stall["length"], (ramp, stall)
    assert not _events(out, "trip")
    end = _events(out, "end")[0]
    assert end["status"] == "completed" and end["stalls"]["count"] == len(_events(out, "stall"))


@timing
def test_a_long_stall_in_the_start_ramp_trips_on_the_stall_before_the_first_step(tmp_path):
    out = tmp_path / "run"
    proc = _freeze_in_the_start_ramp(out, 0.4)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 3, err
    trip = _events(out, "trip")[0]
    assert trip["rule"] == "stall" and trip["step"] < 0, trip
    assert 0.35 <= trip["values"]["stall"] <= 1.5
    assert "bridge itself stalled" in err and "watchdog" not in err
    assert all(e["confirmed"] for e in _events(out, "estop"))
    assert header_row_count(out / "record.npy") == 0  # no step of the test was taken

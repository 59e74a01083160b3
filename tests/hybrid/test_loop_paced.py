"""Paced (wall-clock) runs: pacing, kill -9 crash safety, SIGINT operator stop."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rths_hil.config import load_config
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import header_row_count, read_run

# the paced runs: against the wall clock, with other processes; run apart from the parallel
# tests (the "timing" marker, pyproject.toml; make test)
timing = pytest.mark.timing

FS = 1024.0
# a loaded CI machine must not stop these runs for reasons they do not test
TOLERANT = [
    "--set", "safety.max_overruns=1000000",
    "--set", "safety.watchdog_missed=1000000",
    "--set", "safety.fei_delay_tol=0",
    "--set", "safety.fei_amplitude_tol=0",
    "--set", "kalman.enabled=false",
    "--set", "output.plot=false",
]  # fmt: skip


def _wall_t0(run) -> float:
    return next(e["wall_t0"] for e in run.events if e["kind"] == "clock")


def _start(out: Path, *extra: str) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "rths_hil",
        "run",
        "--paced",
        "--duration",
        "20",
        "--out",
        str(out),
        "-q",
        *TOLERANT,
        *extra,
    ]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_rows(path: Path, proc: subprocess.Popen, timeout: float = 30.0) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        assert proc.poll() is None, proc.communicate()
        if path.exists() and header_row_count(path) > 0:
            return
        time.sleep(0.02)
    raise AssertionError("the run never flushed a row")


@timing
def test_paced_run_keeps_the_wall_clock(tmp_path):
    # 1 s: 1024 paced steps, each checked below
    cfg = load_config(
        None, ["loop.duration=1.0", "loop.console=0", "output.plot=false", *TOLERANT[1::2]]
    )
    loop = RTHSLoop(cfg, tmp_path / "run", mode="paced")
    res = loop.run()
    assert res.status == "completed" and res.steps == round(1.0 * FS)
    # never early, and never faster than real time
    run = read_run(tmp_path / "run")
    lat = run.record["lateness"]
    assert (lat >= 0).all() and lat.max() > 0
    assert res.wall_time >= (res.steps - 1) / FS
    stats = res.lateness_stats()
    assert set(stats) == {"p50", "p99", "p99.9", "max", "overruns"}
    assert stats["overruns"] == int((lat > 0.5 / FS).sum())
    np.testing.assert_allclose(res.lateness, lat)
    # when the loop was ready for each step: never after the send, and mostly before the deadline
    assert res.ready.shape == lat.shape
    assert (lat >= res.ready - 1e-9).all()
    assert (res.ready < 0).mean() > 0.5
    causes = res.overrun_causes()
    assert sum(causes.values()) == stats["overruns"]
    end = run.events[-1]
    assert end["kind"] == "end" and end["overrun_causes"] == causes
    assert _wall_t0(run) > 0
    assert run.record["feedback_ok"].mean() > 0.9


@timing
def test_kill_9_leaves_the_record_complete_up_to_the_kill(tmp_path):
    out = tmp_path / "run"
    proc = _start(out)
    _wait_rows(out / "record.npy", proc)
    time.sleep(0.5)  # ten flushes (output.flush_interval 0.05 s) before the kill
    t_kill = time.time()
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    run = read_run(out)
    rec = run.record
    n = len(rec)
    assert n > FS * 0.4
    np.testing.assert_array_equal(rec["step"], np.arange(n))
    # the last flushed row was sent at most 0.25 s before the kill
    t_last = _wall_t0(run) + rec["time"][-1] + rec["lateness"][-1]
    assert t_kill - t_last <= 0.25, t_kill - t_last
    assert np.isfinite(rec["target"]).all() and rec["feedback_ok"].any()
    assert json.loads((out / "meta.json").read_text())["mode"] == "paced"
    assert [e["kind"] for e in run.events][:4] == ["start", "arm", "start_position", "clock"]


@timing
def test_sigint_is_an_operator_stop_with_the_same_flush_path(tmp_path):
    """Ctrl-C (SIGINT) stops the run as every stop signal does (a closed terminal's SIGHUP, a
    SIGTERM: the same handler, test_every_stop_signal_is_the_operator_stop_and_a_second_one_
    interrupts): the stop and end events, every controller handed back disabled and not
    latched, no e-stop, exit 130 with one line."""
    out = tmp_path / "run"
    proc = _start(out)
    _wait_rows(out / "record.npy", proc)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, stderr
    # (a loaded machine's own stalls are logged as they happen: not part of the stop's line)
    lines = [ln for ln in stderr.splitlines() if ln.strip() and "the bridge stalled" not in ln]
    assert len(lines) == 1 and "operator stop" in lines[0] and str(out) in lines[0]
    run = read_run(out)
    kinds = [e["kind"] for e in run.events]
    assert "operator_stop" in kinds and kinds[-1] == "end"
    stop = next(e for e in run.events if e["kind"] == "operator_stop")
    assert stop["signal"] == "SIGINT"
    end = run.events[-1]
    assert end["status"] == "operator_stop" and end["step"] == len(run.record)
    # an operator stop holds the actuator and hands the controller back disabled (no e-stop)
    assert "estop" not in kinds and kinds.index("end_ramp") < kinds.index("handback")
    handback = next(e for e in run.events if e["kind"] == "handback")
    assert handback["disabled"] is True and handback["latched"] is False
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "operator_stop" and summary["trip"]["rule"] == "operator"


def test_every_stop_signal_is_the_operator_stop_and_a_second_one_interrupts():
    """``run``, ``commission``, ``check-host`` and the studies catch the stop signals with
    :class:`rths_hil.stopping.OperatorStop`, one handler for every signal of STOP_SIGNALS:
    each one, sent to this process, is recorded by its name and the command's next check
    stops; a second one raises at once; the handlers are restored after. With this, one
    signal proves a command's whole stop path (SIGINT above; SIGTERM in test_start_end.py and
    test_commission.py)."""
    from rths_hil.hybrid.runner import STOP_SIGNALS
    from rths_hil.stopping import OperatorStop, Stopped

    wanted = {"SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2"}
    assert {s.name for s in map(signal.Signals, STOP_SIGNALS)} == wanted
    before = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig in STOP_SIGNALS:
        name = signal.Signals(sig).name
        with OperatorStop() as stop:
            stop.check()  # nothing yet
            signal.raise_signal(sig)  # (handled before it returns)
            assert stop.signal == name
            with pytest.raises(Stopped, match=name):
                stop.check()
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(sig)
        assert {s: signal.getsignal(s) for s in STOP_SIGNALS} == before  # restored

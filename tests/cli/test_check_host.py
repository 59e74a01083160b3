"""``rths-hil check-host`` (rths_hil.checkhost): the verdict's arithmetic, the measurement, the
host facts read back from the kernel, and the CLI with its cached verdict line in ``run``."""

from __future__ import annotations

import json
import os
import platform
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rths_hil.checkhost import Timing, host_facts, measure, verdict
from rths_hil.cli import main
from tests.helpers.cli import one_line_exit_2
from tests.helpers.procs import ROOT

# The verdict's arithmetic, the host facts and the CLI (its exit codes, its cached line, its
# operator stop within a bound of seconds) run with the parallel tests; the measurement's
# wake-ups, one per period, run apart from them (the "timing" marker, pyproject.toml; make test).

FS = 1024.0
P = 1.0 / FS
SPIN, THR, MAX_OVER = 3e-4, 0.5, 100
BUDGET = SPIN + THR * P  # 0.3 ms + 0.48828125 ms


def _timing(lat: np.ndarray) -> Timing:
    p50, p99, p999 = np.percentile(lat, [50, 99, 99.9])
    return Timing(P, lat.size * P, lat.size, p50, p99, p999, lat.max(), False, 0, -1, lat)


def test_verdict_holds_with_the_budget_over_p999_as_margin():
    lat = np.full(10_000, 10e-6)
    word, line, figs = verdict(_timing(lat), FS, SPIN, THR, MAX_OVER)
    assert word == "holds" and line.startswith("host holds 1024 Hz")
    assert figs["budget"] == pytest.approx(0.78828125e-3, rel=1e-12)
    assert figs["margin"] == pytest.approx(BUDGET / 10e-6)
    assert figs["over_fraction"] == 0.0


def test_verdict_marginal_and_cannot_hold():
    lat = np.full(10_000, 10e-6)
    lat[:20] = 2 * BUDGET  # 0.2 % of the wake-ups over the budget, short stalls
    word, _, figs = verdict(_timing(lat), FS, SPIN, THR, MAX_OVER)
    assert word == "marginal" and figs["over_fraction"] == pytest.approx(0.002)
    lat[:20] = 10e-6
    lat[5] = 0.6 * MAX_OVER * P  # one stall past half the overrun trip
    assert verdict(_timing(lat), FS, SPIN, THR, MAX_OVER)[0] == "marginal"
    lat[5] = MAX_OVER * P  # a stall as long as the trip: a paced run would stop itself
    assert verdict(_timing(lat), FS, SPIN, THR, MAX_OVER)[0] == "cannot hold"
    # at most 0.1 % over the budget and no long stall still holds
    lat[5] = 10e-6
    lat[:10] = 2 * BUDGET
    assert verdict(_timing(lat), FS, SPIN, THR, MAX_OVER)[0] == "holds"


@pytest.mark.timing  # one wake-up per 2 ms period
def test_measure_wakes_every_period_for_the_duration():
    t0 = time.perf_counter()
    t = measure(2e-3, 0.4, priority=0, cpu=0)
    wall = time.perf_counter() - t0
    assert t.wakeups == 200 and t.lateness.size == 200
    assert wall >= 0.4 - 2e-3  # it slept to absolute deadlines, it did not run ahead
    assert 0.0 <= t.p50 <= t.p99 <= t.p999 <= t.max == t.lateness.max()
    assert not t.fifo and t.priority == 0 and t.cpu == 0


def test_host_facts_match_the_kernel():
    f = host_facts()
    version = platform.uname().version
    rt = Path("/sys/kernel/realtime")
    assert f.preempt_rt == (
        "PREEMPT_RT" in version or (rt.exists() and rt.read_text().strip() == "1")
    )
    iso = Path("/sys/devices/system/cpu/isolated")
    assert f.isolated == (iso.read_text().strip() if iso.exists() else "")
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    assert str(soft) in f.rtprio_limit or soft == resource.RLIM_INFINITY
    assert f.cpus == os.cpu_count()


def test_cli_verdict_is_cached_and_shown_by_run(tmp_path, monkeypatch, capsys):
    env = dict(os.environ, RTHS_HIL_CACHE=str(tmp_path / "cache"))
    cmd = [sys.executable, "-m", "rths_hil"]
    proc = subprocess.run(
        [*cmd, "check-host", "--duration", "1s"],
        capture_output=True, text=True, timeout=60, cwd=ROOT, env=env,
    )  # fmt: skip
    assert proc.returncode in (0, 1), proc.stderr
    line = [ln for ln in proc.stdout.splitlines() if "host " in ln and " Hz:" in ln][-1]
    cached = json.loads((tmp_path / "cache" / "check-host.json").read_text())
    assert line.endswith(cached["line"]) and cached["fs"] == 1024.0
    assert (proc.returncode == 0) == (cached["word"] == "holds")
    # ``run`` in this process (its own main), reading the same cache
    monkeypatch.setenv("RTHS_HIL_CACHE", env["RTHS_HIL_CACHE"])
    capsys.readouterr()
    main(["run", "--duration", "0.5", "--no-plot", "--out", str(tmp_path / "r"),
          "--set=loop.console=0", "--set=safety.max_overruns=100000"])  # fmt: skip
    assert cached["line"] in capsys.readouterr().err


@pytest.mark.parametrize(
    ("args", "text"),
    [
        (["--duration", "0"], "--duration"),
        (["--duration", "1e-9"], "--duration"),  # one wake-up: no verdict (nor a cached one)
        (["--duration", "0.001s"], "--duration"),
        (["--set", "loop.cpu=999"], "loop.cpu = 999"),
    ],
)
def test_cli_bad_input(tmp_path, monkeypatch, capsys, args, text):
    monkeypatch.setenv("RTHS_HIL_CACHE", str(tmp_path / "cache"))
    one_line_exit_2(["check-host", *args], capsys, text)  # (in this process: refused at once)
    assert not (tmp_path / "cache" / "check-host.json").exists()


# one signal: every stop signal is caught by the same OperatorStop
# (test_loop_paced.py::test_every_stop_signal_is_the_operator_stop_and_a_second_one_interrupts)
@pytest.mark.parametrize("sig", [signal.SIGHUP])
def test_operator_stop_ends_the_measurement_with_130_and_keeps_no_verdict(tmp_path, sig):
    env = dict(os.environ, RTHS_HIL_CACHE=str(tmp_path / "cache"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "check-host", "--duration", "60s"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
    )  # fmt: skip
    assert "measuring" in proc.stderr.readline()  # started, the stop signals caught
    time.sleep(1.0)
    t = time.monotonic()
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert time.monotonic() - t < 10.0  # not the 60 s asked for
    assert f"operator stop ({sig.name})" in err
    assert "lateness p50" in out  # what was measured is printed …
    assert "host holds" not in out and "host marginal" not in out  # … but no verdict
    assert not (tmp_path / "cache" / "check-host.json").exists()

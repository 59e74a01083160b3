"""A stop signal after the test ended, while ``run`` writes the summary and the report: both
are written (they are the test's result), then the command exits 130 — not 143 with the
report lost."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest


@pytest.mark.parametrize("sig", [signal.SIGTERM])  # SIGHUP and SIGINT: the same handler
def test_a_signal_while_the_report_is_written(tmp_path, sig):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "run", "--lockstep", "--duration", "0.5",
         "--set", f"output.dir={run_dir}", "--set", "loop.console=0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    summary_file = run_dir / "summary.json"  # written first, then the report
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not summary_file.exists():
        time.sleep(0.002)
    assert summary_file.exists(), "the summary was not written"
    report = run_dir / "report.png"
    assert not report.exists()  # the signal comes before the report is written
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert f"{sig.name} while the summary and report were written" in err
    assert "Traceback" not in err
    assert report.is_file() and report.stat().st_size > 10_000
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["steps"] == 512

"""``rths-hil study robustness`` and ``study compensators`` stopped by the operator (Ctrl-C,
SIGTERM, SIGHUP): exit 130 soon, the trials that finished kept in ``trials.partial.csv`` (as
many rows as the progress bar had counted, at least), no worker process left behind."""

from __future__ import annotations

import csv
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

from tests.helpers.procs import ROOT

# other processes, bounded in seconds (the stop within 15 s, the workers gone within 10 s, the
# trials 1 s of simulated time each): they run with the parallel tests

CONFIG = str(ROOT / "examples" / "can.toml")


def _children(pid: int) -> set[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True)
    return {int(p) for p in out.stdout.split()}


def _alive(pids: set[int]) -> list[str]:
    """The command lines of the processes of ``pids`` still running (not zombies)."""
    alive = []
    for p in pids:
        try:
            stat = open(f"/proc/{p}/stat").read()
            cmd = open(f"/proc/{p}/cmdline").read().replace("\0", " ")
        except OSError:
            continue
        if stat.rsplit(")", 1)[1].split()[0] != "Z":
            alive.append(cmd)
    return alive


@pytest.mark.parametrize(
    ("study", "sig"),
    [("robustness", signal.SIGTERM), ("compensators", signal.SIGINT)],
)
def test_operator_stop_keeps_the_finished_trials(tmp_path, study, sig):
    out = tmp_path / "s"
    extra = ["--methods", "inverse,polynomial"] if study == "compensators" else []
    proc = subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "study", study, CONFIG, "--trials", "12",
         "--duration", "1s", "--workers", "2", "--no-plot", "--out", str(out), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT,
    )  # fmt: skip
    err = bytearray()

    def read() -> None:
        while chunk := proc.stderr.read1(4096):  # type: ignore[union-attr]
            err.extend(chunk)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()

    def counted() -> int:
        done = re.findall(rb"(\d+)/\d+ \[", bytes(err))
        return int(done[-1]) if done else 0

    end = time.monotonic() + 120
    while counted() < 2 and proc.poll() is None and time.monotonic() < end:
        time.sleep(0.05)
    assert proc.poll() is None, bytes(err).decode()
    seen = counted()
    workers = _children(proc.pid)
    assert workers  # the pool's processes
    t = time.monotonic()
    proc.send_signal(sig)
    proc.wait(timeout=30)
    reader.join(5)
    text = bytes(err).decode(errors="replace")
    assert proc.returncode == 130, text
    assert time.monotonic() - t < 15  # the runs under way are not awaited
    assert f"operator stop ({sig.name})" in text
    with (out / "trials.partial.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    total = 12 * (2 if study == "compensators" else 1)
    assert seen <= len(rows) < total, (seen, len(rows))
    assert all(r["status"] for r in rows)
    assert not (out / "trials.csv").exists()
    end = time.monotonic() + 10
    while time.monotonic() < end and _alive(workers):
        time.sleep(0.1)
    assert not _alive(workers), "workers left running"

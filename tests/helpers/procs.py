"""Helpers for tests that run the twin and the bridge as their own processes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from rths_hil.records.recorder import header_row_count
from tests.helpers.loop import LoopRun, run_loop

ROOT = Path(__file__).resolve().parents[2]
LATCH_LINE = "e-stop latched"


class ServedTwin:
    """``rths-hil twin serve`` in its own process; stderr lines are time-stamped on arrival."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rths_hil", "twin", "serve", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        line = self.proc.stdout.readline()
        if "connection" not in line:
            self.proc.kill()
            raise RuntimeError(f"twin serve did not start: {line!r} {self.proc.stderr.read()}")
        self.connection = json.loads(line.split("connection", 1)[1])
        self.lines: list[tuple[float, str]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append((time.monotonic(), line.rstrip()))

    def first(self, text: str, after: float = 0.0, timeout: float = 5.0) -> float | None:
        """Arrival time of the first stderr line containing ``text`` after ``after``."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for t, line in list(self.lines):
                if t >= after and text in line:
                    return t
            time.sleep(0.005)
        return None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def toml_table(d: dict) -> str:
    """A TOML inline table of strings, numbers, booleans and tables (for ``--set
    driver.connection=...``)."""

    def value(v):
        if isinstance(v, dict):
            return toml_table(v)
        if isinstance(v, bool):
            return "true" if v else "false"
        return json.dumps(v) if isinstance(v, str) else repr(v)

    return "{" + ", ".join(f"{k} = {value(v)}" for k, v in d.items()) + "}"


def bridge_overrides(driver: str, connection: dict) -> list[str]:
    """The configuration of a bridge to an external twin (``twin.enabled = false``): hardware
    to the bridge, so confirmed, and stepped by its commands (lockstep allowed)."""
    return [
        "twin.enabled=false",
        "driver.stepped=true",
        f"driver.name={driver}",
        f"driver.connection={toml_table(connection)}",
    ]


def bridge_cmd(driver: str, connection: dict, out: Path, *extra: str) -> list[str]:
    """``rths-hil run`` against an external twin, as its own process (:func:`bridge_overrides`)."""
    sets = [f"--set={s}" for s in bridge_overrides(driver, connection)]
    cmd = [sys.executable, "-m", "rths_hil", "run", "-q", "--no-plot", "--confirm-hardware"]
    return [*cmd, "--out", str(out), *sets, *extra]


def run_bridge(
    driver: str,
    connection: dict,
    out: Path,
    *overrides: str,
    config: Path | None = None,
    **loop_kwargs: Any,
) -> LoopRun:
    """The same bridge run in this process (no second interpreter to start where the bridge's
    own process is not the point): ``overrides`` after :func:`bridge_overrides`;
    ``loop_kwargs`` (``mode``, ``duration`` …) to :class:`rths_hil.hybrid.RTHSLoop`."""
    sets = [*bridge_overrides(driver, connection), "loop.confirm_hardware=true"]
    return run_loop(out, config, *sets, *overrides, **loop_kwargs)


def start_bridge(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT
    )


def wait_rows(out: Path, rows: int, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Wait until the run in ``out`` has flushed ``rows`` rows (the bridge is stepping)."""
    end = time.monotonic() + timeout
    rec = out / "record.npy"
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"the bridge ended early: {proc.stderr.read()}")
        if rec.exists():
            try:
                if header_row_count(rec) >= rows:
                    return
            except (OSError, ValueError, SyntaxError):
                pass
        time.sleep(0.02)
    raise TimeoutError(f"the bridge did not reach {rows} rows in {timeout} s")


def kill9(proc: subprocess.Popen) -> float:
    """SIGKILL ``proc``; return the monotonic time of the kill."""
    t = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return t

"""Stalls of the bridge itself in long paced runs on this machine, and what the loop did.

Two cases, each through ``rths-hil run`` as its own process, exactly as an operator starts it:

* **soak**: the default test (NEES-711 over the CAN twin, 1024 Hz, compensation, FEI, Kalman,
  every safety rule at its default) paced for ``--minutes`` (default 10) of wall-clock time,
  driven by the default record repeated end to end so the FEI windows stay valid;
* **hogs**: the default ``rths-hil run`` (30 s) beside ``--hogs`` (default 2) processes that
  each keep a CPU busy (a pure-Python busy loop) — on a 2-core machine every core is then
  wanted by someone else.

For each run it reads the run's own events: status (and the trip, if any), every ``stall``
event (step, length, what the loop did next), the ``end`` event's stall count, longest and
total, the overruns by cause, and the missed replies. The goal: a default paced run beside two
CPU hogs completes, and no stall of the bridge is blamed on a controller (no watchdog trip).

Usage: ``python benchmarks/soak_stalls.py [--minutes 10] [--hogs 2] [--no-write]``.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, write_results

from rths_hil.groundmotion import default_record
from rths_hil.units import G

HOG = "while True: pass"
LISTED = 0.010  # stalls at least this long (s) are listed one by one
BINS = [0.0, 0.005, 0.010, 0.050, 0.200, np.inf]  # the histogram of stall lengths (s)


def tiled_record(path: Path, duration: float) -> None:
    """The default record repeated end to end for ``duration`` s (CSV: time_s, accel_g)."""
    gm = default_record()
    reps = math.ceil(duration / gm.duration) + 1
    a = np.tile(gm.accel, reps) / G
    t = np.arange(a.size) * gm.dt
    np.savetxt(path, np.column_stack([t, a]), delimiter=",", header="time_s,accel_g", comments="")


def run(out: Path, extra: list[str]) -> tuple[int, float]:
    """``rths-hil run --paced`` into ``out``; return (exit code, wall seconds)."""
    cmd = [sys.executable, "-m", "rths_hil", "run", "--paced", "--out", str(out), "-q"]
    cmd += ["--set", "output.plot=false", *extra]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode not in (0, 3):
        sys.stderr.write(proc.stderr)
    return proc.returncode, time.monotonic() - t0


def events(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]


def describe(name: str, out: Path, code: int, wall: float) -> tuple[list, list]:
    """One summary row of a run and the rows of its stalls."""
    ev = events(out)
    end = next((e for e in ev if e["kind"] == "end"), {})
    trip = next((e for e in ev if e["kind"] == "trip"), None)
    stalls = [e for e in ev if e["kind"] == "stall"]
    st = end.get("stalls", {"count": 0, "longest": 0.0, "total": 0.0})
    causes = end.get("overrun_causes", {})
    row = [
        name,
        f"{wall:.0f}",
        end.get("step", "?"),
        end.get("status", "?") + (f" ({trip['rule']}: {trip['reason']})" if trip else ""),
        st["count"],
        f"{st['longest'] * 1e3:.1f}",
        f"{st['total'] * 1e3:.1f}",
        f"{causes.get('machine', 0)} / {causes.get('work', 0)}",
        end.get("missed_replies", "?"),
    ]
    rows = [
        [name, e["step"], f"{e['time']:.3f}", f"{e['length'] * 1e3:.1f}", e["action"]]
        for e in stalls
        if e["length"] >= LISTED
    ]
    lengths = np.array([e["length"] for e in stalls])
    counts = np.histogram(lengths, bins=BINS)[0] if lengths.size else [0] * (len(BINS) - 1)
    return row + [int(c) for c in counts], rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="soak length (10)")
    ap.add_argument("--hogs", type=int, default=2, help="CPU hogs beside the short run (2)")
    ap.add_argument("--no-write", action="store_true", help="do not write benchmarks/results")
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="soak_stalls_"))
    summary: list[list] = []
    stall_rows: list[list] = []

    # the default run beside CPU hogs
    hogs = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(args.hogs)]
    try:
        time.sleep(1.0)
        out = work / "hogs"
        code, wall = run(out, [])
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    row, rows = describe(f"default 30 s beside {args.hogs} CPU hogs", out, code, wall)
    summary.append(row)
    stall_rows += rows
    print(row, file=sys.stderr, flush=True)

    # the soak
    seconds = args.minutes * 60.0
    csv = work / "tiled.csv"
    tiled_record(csv, seconds)
    out = work / "soak"
    code, wall = run(
        out,
        [
            "--duration",
            f"{seconds:g}",
            "--set",
            f"ground_motion.record={csv}",
            "--set",
            "ground_motion.tail=0",
        ],
    )
    row, rows = describe(f"default, {args.minutes:g} min paced", out, code, wall)
    summary.append(row)
    stall_rows += rows
    print(row, file=sys.stderr, flush=True)

    table = markdown_table(
        [
            "run",
            "wall s",
            "steps",
            "status",
            "stalls",
            "longest ms",
            "total ms",
            "overruns machine / work",
            "missed replies",
            "stalls < 5 ms",
            "5–10 ms",
            "10–50 ms",
            "50–200 ms",
            "> 200 ms",
        ],
        summary,
    )
    table += (
        "\n\nEvery stall of 10 ms or more (`stall` events: step, loop time, length, what the "
        "loop did):\n\n"
    )
    table += (
        markdown_table(["run", "step", "t s", "length ms", "then"], stall_rows)
        if stall_rows
        else "none\n"
    )
    print(table)
    if not args.no_write:
        write_results(
            "soak_stalls",
            table,
            goals="a default paced run beside two CPU hogs completes; every stall of the "
            "bridge is a `stall` event (slip by default), none is a watchdog trip; a stall "
            "longer than safety.max_stall (0.2 s) trips on the stall rule",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

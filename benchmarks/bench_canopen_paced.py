"""Paced runs of the CANopen examples against the CAN driver in the same run.

Each mode is the default test (``examples/can.toml`` / ``examples/controllers/cia40x.toml``) run
paced at 1024 Hz by ``rths-hil run`` in its own process, the modes interleaved round by round
so that they share the machine's load. For each run the overruns are attributed by the runner
(:func:`rths_hil.hybrid.attribute_overruns`): ``work`` = the previous step's work (reply wait,
integration, evaluators, recorder) ran past the threshold; ``in work`` = it did so only because
the machine preempted the loop's thread inside that work (the thread's CPU clock, no voluntary
context switch); ``machine`` = the loop was ready but the wait returned late; the catch-up
steps after each are counted apart. Goal: work-caused overruns ≤ 0.01 % of the steps for a
CANopen axis. Every example is run as shipped (its twin served inline from the loop's thread
during the steps); the rows "twin on a thread" show the same tests with ``twin.inline = false``.

``--two-axes N`` adds N paced runs of ``examples/controllers/cia402_two_axes.toml`` at 512 Hz
(two axes on one bus, one SYNC per step) and reports their status and trips.

Usage: ``python benchmarks/bench_canopen_paced.py [--rounds 4] [--duration 10] [--two-axes 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: label → (example, extra arguments of ``rths-hil run``)
MODES: dict[str, tuple[str, list[str]]] = {
    "can (built-in)": ("examples/can.toml", []),
    "can (built-in), twin on a thread": ("examples/can.toml", ["--set", "twin.inline=false"]),
    "canopen CiA 402": ("examples/controllers/cia402.toml", []),
    "canopen CiA 408": ("examples/controllers/cia408.toml", []),
    "canopen CiA 402, twin on a thread": (
        "examples/controllers/cia402.toml",
        ["--set", "twin.inline=false"],
    ),
}
TWO_AXES = ("examples/controllers/cia402_two_axes.toml", ["--set", "loop.fs=512"])
GOAL = 1e-4  # work-caused overruns per step


def run(example: str, extra: list[str], duration: float, out: Path) -> dict:
    """One paced ``rths-hil run``; its ``summary.json``."""
    cli = "import sys; from rths_hil.cli import main; sys.exit(main(sys.argv[1:]))"
    cmd = [sys.executable, "-c", cli, "run", str(ROOT / example), "--paced",
           "--duration", f"{duration:g}", "--out", str(out), "--no-plot", "-q", *extra]  # fmt: skip
    if out.exists():
        raise RuntimeError(f"{out} exists: each run needs its own directory")
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    path = out / "summary.json"
    if not path.is_file():
        raise RuntimeError(f"{example}: no summary (exit {p.returncode}): {p.stderr[-500:]}")
    return json.loads(path.read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=4, help="runs per mode, interleaved")
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run")
    ap.add_argument("--two-axes", type=int, default=0, help="paced two-axis runs at 512 Hz")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench-canopen-paced-"))
    acc: dict[str, list[dict]] = {k: [] for k in MODES}
    for r in range(args.rounds):
        for m, (label, (example, extra)) in enumerate(MODES.items()):
            s = run(example, extra, args.duration, tmp / f"mode{m}-round{r}")
            acc[label].append(s)
            oc = s["overrun_causes"]
            print(f"{label:34s} round {r}: {s['status']}, {s['steps']} steps, work {oc['work']} "
                  f"(+{oc['work_backlog']}), machine in the work {oc['machine_in_work']}, "
                  f"machine {oc['machine']} (+{oc['machine_backlog']}), "
                  f"missed {s['missed_replies']}", flush=True)  # fmt: skip
    rows = []
    for label, runs in acc.items():
        steps = sum(s["steps"] for s in runs)
        work = sum(s["overrun_causes"]["work"] for s in runs)
        work_b = sum(s["overrun_causes"]["work_backlog"] for s in runs)
        mach = sum(s["overrun_causes"]["machine"] for s in runs)
        in_work = sum(s["overrun_causes"]["machine_in_work"] for s in runs)
        missed = sum(s["missed_replies"] for s in runs)
        share = work / steps if steps else float("nan")
        verdict = ""
        if label in ("canopen CiA 402", "canopen CiA 408"):
            verdict = f"≤ {GOAL * 100:g} %: {'met' if share <= GOAL else 'NOT met'}"
        per_run = ", ".join(
            str(s["overrun_causes"]["work"])
            + ("" if s["status"] == "completed" else f" ({s['status']})")
            for s in runs
        )
        rows.append([label, len(runs), steps, f"{work} (+{work_b})", f"{100 * share:.3f} %",
                     per_run, in_work, mach, missed, verdict])  # fmt: skip
    two = []
    for r in range(args.two_axes):
        s = run(*TWO_AXES, args.duration, tmp / f"two-{r}")
        trip = s.get("trip") or {}
        two.append([r, s["status"], s["steps"], s["overrun_causes"]["work"], s["missed_replies"],
                    (trip.get("reason") or trip.get("rule") or "") if isinstance(trip, dict)
                    else str(trip)])  # fmt: skip
        print("two axes 512 Hz", *two[-1], flush=True)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _results import markdown_table, write_results

    table = markdown_table(
        ["mode", "runs", "steps", "work-caused overruns (+catch-up)", "share", "per run",
         "machine in the work", "machine", "missed replies", "goal"],
        rows,
    )  # fmt: skip
    if two:
        table += "\n\n### Two CiA 402 axes on one bus, paced 512 Hz\n\n" + markdown_table(
            ["run", "status", "steps", "work-caused overruns", "missed replies", "trip"], two
        )
    for row in rows:
        print(f"{row[0]:34s} work-caused {row[3]} of {row[2]} steps = {row[4]} {row[9]}")
    write_results(
        "bench_canopen_paced",
        table,
        title="Paced 1024 Hz runs over CANopen against the CAN driver",
        goals="Work-caused overruns ≤ 0.01 % of the steps for a CANopen axis at 1024 Hz.",
        command=f"python benchmarks/bench_canopen_paced.py --rounds {args.rounds} --duration "
        f"{args.duration:g}" + (f" --two-axes {args.two_axes}" if args.two_axes else ""),
        notes="Each run: the example's default test through `rths-hil run --paced` in its own "
        "process, the modes interleaved round by round. Overruns attributed by the runner: "
        "`work` = the step's work ran past the threshold (a stall while waiting for the replies, "
        "or in a step where the loop's thread blocked, included); `machine in the work` = it did "
        "so only because the machine preempted the loop's thread inside the step (the thread's "
        "CPU clock from the send to the record; no voluntary context switch); `machine` = the "
        "loop was ready and the wait returned late. The CANopen examples as shipped serve their "
        "twin from the loop's thread during the steps (its own thread answers the SDO exchanges); "
        "the rows 'twin on a thread' set `twin.inline = false`. Load average at the end: "
        f"{os.getloadavg()[0]:.1f} (1 min) on {os.cpu_count()} cores.",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

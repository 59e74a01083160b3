"""Soak benchmark of the loop: a long lockstep run, its memory and the drift of the online FEI.

One run of ``--duration`` simulated seconds (default one hour) at ``--fs`` (default 4096 Hz)
in lockstep over the CAN driver and its in-process twin, driven by the default record repeated
end to end (so that the FEI windows stay valid for the whole run), exactly as ``rths-hil run``
does it: the loop, then the summary (``summary.json``) and the report (``report.png``) in the
same process. It reports

* the resident set size (RSS, from ``/proc/self/statm``) sampled every few seconds during the
  loop: at the start, at the end, and its growth per simulated hour (a leak shows as growth);
* the peak RSS of the whole process (``ru_maxrss``) after the loop, and after the summary and
  the report — the goal: ≤ 1 GB at the end of a one-hour run at 4096 Hz;
* FEI drift: the streaming online FEI (running sums updated every sample for an hour) against
  the exact cross-check (each window evaluated from scratch every ``exact_hop`` samples) in
  the first and the last tenth of the run. Accumulated rounding in the running sums would show
  as a difference that grows from the first tenth to the last;
* steps per second.

Usage: ``python benchmarks/soak_loop.py [--duration 3600] [--fs 4096] [--keep DIR]``. The run
directory (2.3 GB for one hour at 4096 Hz) is deleted unless ``--keep`` names where to put it.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import markdown_table, write_results

from rths_hil.config import load_config
from rths_hil.groundmotion import default_record
from rths_hil.hybrid import RTHSLoop
from rths_hil.report import plot_report, summarize
from rths_hil.units import G

_PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb() -> float:
    """Current resident set size (MB)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * _PAGE / 1e6


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


def tiled_record(path: Path, duration: float) -> None:
    """The default record repeated end to end for ``duration`` s, as a CSV (time_s, accel_g)."""
    gm = default_record()
    reps = math.ceil(duration / gm.duration) + 1
    a = np.tile(gm.accel, reps) / G
    t = np.arange(a.size) * gm.dt
    np.savetxt(path, np.column_stack([t, a]), delimiter=",", header="time_s,accel_g", comments="")


def drift(run_dir: Path, fs: float) -> list[list[object]]:
    """Streaming vs exact online FEI in the first and the last tenth of the record."""
    rec = np.load(run_dir / "record.npy", mmap_mode="r")
    n = len(rec)
    rows = []
    for label, lo, hi in (("first tenth", 0, n // 10), ("last tenth", n - n // 10, n)):
        part = np.array(rec[lo:hi][["fei_amplitude", "fei_delay", "fei_valid",
                                     "fei_exact_amplitude", "fei_exact_delay",
                                     "fei_exact_valid"]])  # fmt: skip
        ex = part["fei_exact_amplitude"]
        new = np.r_[False, np.diff(ex) != 0] & part["fei_exact_valid"] & part["fei_valid"]
        new &= np.isfinite(ex) & np.isfinite(part["fei_amplitude"])
        da = np.abs(part["fei_amplitude"][new] - ex[new])
        dd = np.abs(part["fei_delay"][new] - part["fei_exact_delay"][new])
        rows.append(
            [
                label,
                f"{lo / fs / 60:.1f}–{hi / fs / 60:.1f} min",
                int(new.sum()),
                f"{da.max():.2e}" if da.size else "—",
                f"{dd.max() * 1e6:.3f}" if dd.size else "—",
                f"{np.mean(part['fei_amplitude'][new]):.5f}" if da.size else "—",
                f"{np.mean(part['fei_delay'][new]) * 1e3:.4f}" if dd.size else "—",
            ]
        )
        del part
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3600.0, help="simulated seconds (3600)")
    ap.add_argument("--fs", type=float, default=4096.0, help="loop rate in Hz (4096)")
    ap.add_argument("--keep", metavar="DIR", help="keep the run directory here")
    ap.add_argument(
        "--wall-limit",
        type=float,
        default=0.0,
        metavar="S",
        help="stop the run (as an operator stop) after this many wall-clock seconds; the "
        "loop's buffers are still those of the whole --duration (0 = no limit)",
    )
    ap.add_argument("--no-write", action="store_true", help="do not write benchmarks/results")
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="soak_loop_"))
    run_dir = Path(args.keep) if args.keep else work / "run"
    csv = work / "tiled.csv"
    tiled_record(csv, args.duration)
    cfg = load_config(
        None,
        [
            f"ground_motion.record={csv}",
            "ground_motion.tail=0",
            f"loop.fs={args.fs}",
            # α in steps for the twin's ≈ 25 ms actuator lag at this rate (26.6 at 1024 Hz)
            f"compensation.alpha={1.0 + 0.025 * args.fs:g}",
            "loop.console=5",
        ],
    )
    samples: list[tuple[float, float]] = []
    holder: list[RTHSLoop] = []

    def live(status: dict) -> None:
        samples.append((status["t"], rss_mb()))
        if args.wall_limit and time.perf_counter() - t0 > args.wall_limit and holder:
            holder[0].runner.stop_signal = "wall-limit"  # the loop's own operator-stop path
        if len(samples) % 12 == 0:
            print(
                f"  t = {status['t']:7.0f} s, {status['rate']:6.0f} steps/s, "
                f"RSS {samples[-1][1]:.0f} MB",
                file=sys.stderr,
                flush=True,
            )

    print(
        f"soak: {args.duration:g} s lockstep at {args.fs:g} Hz into {run_dir}",
        file=sys.stderr,
        flush=True,
    )
    rss_before = rss_mb()
    t0 = time.perf_counter()
    loop = RTHSLoop(cfg, run_dir, live=live, mode="lockstep", duration=args.duration)
    holder.append(loop)
    result = loop.run()
    holder.clear()
    wall = time.perf_counter() - t0
    del loop
    result.lateness = result.ready = None
    peak_loop = peak_rss_mb()
    rss_after_loop = rss_mb()
    t1 = time.perf_counter()
    summary = summarize(run_dir)
    plot_report(run_dir)
    t_report = time.perf_counter() - t1
    peak_end = peak_rss_mb()
    size_gb = (run_dir / "record.npy").stat().st_size / 1e9

    sim_h = result.steps / args.fs / 3600.0
    done = result.steps / args.fs
    early = [r for t, r in samples if t <= 0.1 * done]
    late = [r for t, r in samples if t >= 0.9 * done]
    growth = (
        (np.mean(late) - np.mean(early)) / (0.8 * sim_h) if early and late and sim_h else math.nan
    )
    steps_s = result.steps / result.wall_time if result.wall_time else math.nan
    table = markdown_table(
        ["quantity", "value"],
        [
            ["planned", f"{args.duration:g} s at {args.fs:g} Hz (buffers sized for it)"],
            ["simulated", f"{result.steps / args.fs:.0f} s"],
            ["steps", result.steps],
            ["status", result.status + (f" ({result.trip.rule})" if result.trip else "")],
            ["record on disk", f"{size_gb:.2f} GB"],
            ["loop wall time", f"{wall:.0f} s ({steps_s:.0f} steps/s)"],
            ["RSS before the loop", f"{rss_before:.0f} MB"],
            ["RSS during the loop: first / last tenth (mean)",
             f"{np.mean(early):.0f} / {np.mean(late):.0f} MB" if early and late else "—"],
            ["RSS growth during the loop", f"{growth:+.1f} MB per simulated hour"],
            ["peak RSS after the loop", f"{peak_loop:.0f} MB"],
            ["RSS after the loop", f"{rss_after_loop:.0f} MB"],
            ["summary + report time", f"{t_report:.0f} s"],
            ["**peak RSS at the end** (loop + summary + report)", f"**{peak_end:.0f} MB**"],
        ],
    )  # fmt: skip
    fei_rows = drift(run_dir, args.fs)
    table += "\n\nOnline FEI drift: streaming vs exact cross-check (same windows)\n\n"
    table += markdown_table(
        ["part", "time", "exact windows", "max |ΔA|", "max |Δd| (µs)", "mean A", "mean d (ms)"],
        fei_rows,
    )
    fei_t = summary.get("fei_target") or {}
    table += (
        f"\n\nWhole-record FEI (measured vs target): A = {fei_t.get('amplitude', math.nan):.5f}, "
        f"d = {fei_t.get('delay', math.nan) * 1e3:.3f} ms"
    )
    print(table)
    if not args.no_write:
        out = write_results(
            "soak_loop",
            table,
            title="soak_loop: long lockstep run, memory and online FEI drift",
            goals="Peak RSS ≤ 1 GB at the end of a one-hour lockstep run at 4096 Hz (loop, "
            "summary and report in one process); RSS flat during the loop; the streaming FEI "
            "as close to the exact cross-check in the last tenth of the run as in the first.",
            command=f"python benchmarks/soak_loop.py --duration {args.duration:g} --fs {args.fs:g}"
            + (f" --wall-limit {args.wall_limit:g}" if args.wall_limit else ""),
        )
        print(f"wrote {out}", file=sys.stderr)
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    else:
        shutil.rmtree(csv, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""This machine's timing as ``rths-hil check-host`` measures it, for docs/realtime.md.

Wakes a thread every loop period (1024 Hz and 4096 Hz) for ``--duration`` seconds, with the
normal scheduler and with SCHED_FIFO (when permitted), on any CPU and pinned to the last CPU,
and writes the lateness percentiles, the longest stall and the verdict for the default loop
settings to ``benchmarks/results/check_host.md`` with the host facts (kernel, isolated CPUs,
governor, SMT, RLIMIT_RTPRIO).

    python benchmarks/check_host.py [--duration 10]
"""

from __future__ import annotations

import argparse
import os

from _results import markdown_table, write_results

from rths_hil.checkhost import facts_lines, host_facts, measure, verdict
from rths_hil.config import SCHEMA


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per case (10)")
    args = ap.parse_args()
    lp = SCHEMA["loop"]
    spin, thr = lp["spin"].default, lp["overrun_threshold"].default
    max_over = SCHEMA["safety"]["max_overruns"].default
    last = (os.cpu_count() or 1) - 1
    load0 = os.getloadavg()[0]
    rows = []
    for fs in (1024.0, 4096.0):
        for prio in (0, 10):
            for cpu in (-1, last):
                t = measure(1.0 / fs, args.duration, prio, cpu)
                word, _, figs = verdict(t, fs, spin, thr, max_over)
                rows.append([
                    f"{fs:g}",
                    f"SCHED_FIFO {t.priority}" if t.fifo else "normal",
                    "any" if cpu < 0 else str(cpu),
                    f"{t.p50 * 1e6:.0f}",
                    f"{t.p99 * 1e6:.0f}",
                    f"{t.p999 * 1e6:.0f}",
                    f"{t.max * 1e3:.2f}",
                    f"{figs['budget'] * 1e6:.0f}",
                    f"{100 * figs['over_fraction']:.3f}",
                    word,
                ])  # fmt: skip
                print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(
        ["fs (Hz)", "scheduler", "CPU", "p50 (µs)", "p99 (µs)", "p99.9 (µs)", "max (ms)",
         "budget (µs)", "over budget (%)", "verdict"],
        rows,
    )  # fmt: skip
    facts = "\n".join(f"- {ln}" for ln in facts_lines(host_facts()))
    facts += (
        f"\n- load average (1 min) at the start {load0:.2f}, at the end "
        f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs"
    )
    write_results(
        "check_host",
        f"### Host\n\n{facts}\n\n### Wake-up lateness, {args.duration:g} s per case\n\n{table}",
        title="check-host: wake-up lateness of a periodic thread",
        command=f"python benchmarks/check_host.py --duration {args.duration:g}",
        notes=(
            "Budget = loop.spin + loop.overrun_threshold periods (the lateness a wake-up may "
            "have before the step is an overrun); verdict as `rths-hil check-host` gives it "
            "(rths_hil/checkhost.py) for the default loop settings. Each case is one run on "
            "the machine as it was (other work included); the spread from run to run on a "
            "shared machine is large."
        ),
    )


if __name__ == "__main__":
    main()

"""``rths-hil check-host``: can this computer hold the loop's rate?

``rths-hil check-host [CONFIG.toml] [--duration 10s] [--set k=v]...``

Wakes a thread (SCHED_FIFO at ``loop.priority`` when permitted, pinned to ``loop.cpu``) every
loop period for the given time and reports the wake-up lateness percentiles and the longest
stall, the kernel (PREEMPT_RT or not), isolated CPUs, frequency governor, SMT and the
real-time priority limit, then a verdict for the configuration's rate with its margin
(:mod:`rths_hil.checkhost`). The verdict line is kept for ``rths-hil run`` to print at
start-up. Exit codes: 0 holds, 1 marginal or cannot hold, 2 bad input, 130 operator stop
(Ctrl-C, SIGTERM or SIGHUP: the figures measured so far are printed, no verdict is kept).
"""

from __future__ import annotations

import argparse
import os
import sys

from ..units import parse_time
from .options import add_command, add_config_arguments, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``check-host`` to the top-level parser."""
    p = add_command(
        sub,
        "check-host",
        __doc__,
        main,
        help="measure this computer's wake-up timing and judge it for the loop's rate",
    )
    add_config_arguments(p)
    p.add_argument("--duration", default="10s", help="measurement time (default 10s)")


def main(args: argparse.Namespace) -> int:
    """Measure and judge; return the exit code."""
    from ..checkhost import MIN_DURATION, facts_lines, host_facts, measure, save_verdict, verdict
    from ..errors import InputError
    from ..stopping import OperatorStop

    cfg = config_from_args(args)
    duration = parse_time(args.duration, "--duration")
    if not MIN_DURATION <= duration <= 3600:
        raise InputError(
            f"--duration must be in [{MIN_DURATION:g}, 3600] s (a verdict needs many "
            f"wake-ups), got {args.duration!r}"
        )
    lp = cfg["loop"]
    if lp["cpu"] >= (os.cpu_count() or 1):
        raise InputError(f"loop.cpu = {lp['cpu']}: this computer has no such CPU")
    with OperatorStop() as stop:
        print(
            f"rths-hil check-host: measuring {duration:g} s of wake-ups at {lp['fs']:g} Hz …",
            file=sys.stderr,
            flush=True,
        )
        t = measure(1.0 / lp["fs"], duration, lp["priority"], lp["cpu"], stop=lambda: stop.stopped)
    for ln in facts_lines(host_facts(), t):
        print(f"rths-hil check-host: {ln}")
    print(
        f"rths-hil check-host: lateness p50 {t.p50 * 1e6:.0f} µs, p99 {t.p99 * 1e6:.0f} µs, "
        f"p99.9 {t.p999 * 1e6:.0f} µs, max {t.max * 1e3:.3f} ms"
    )
    if stop.stopped:
        print(
            f"rths-hil check-host: operator stop ({stop.signal}) after {t.duration:.1f} s of "
            f"{duration:g} s; no verdict kept",
            file=sys.stderr,
        )
        return 130
    word, line, _ = verdict(
        t, lp["fs"], lp["spin"], lp["overrun_threshold"], cfg["safety"]["max_overruns"]
    )
    print(f"rths-hil check-host: {line}")
    save_verdict(line, word, lp["fs"])
    return 0 if word == "holds" else 1

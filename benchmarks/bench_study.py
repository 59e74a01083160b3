"""Benchmark of the robustness study on Dask.

Measured in one run on this machine:

1. **Throughput**: the same set of perturbed NEES-711 trials (``--trial-seconds`` of the record
   each, default perturbations) run in this process (no Dask), on a ``LocalCluster`` of one
   worker and on one of two workers (single-threaded worker processes over TCP on
   127.0.0.1). Each cluster is started and warmed up (every worker runs one trial) before the
   clock starts, so the figure is trials per second in steady state. Goal: two workers ≥ 1.8×
   one.
2. **A 200-trial study** of ``examples/nees711/nees711.toml`` (the whole 30 s record, the
   default benchmark-style perturbations) end to end as ``rths-hil study robustness`` runs it
   on a local cluster of two workers, cluster start-up included. Goal: ≤ 5 minutes.

The load average before and after each part is printed: on a machine shared with other work
the speed-up of two workers is bounded by the cores that are actually free.

Usage: ``python benchmarks/bench_study.py [--trials 40] [--trial-seconds 10] [--study-trials
200] [--skip-study]``
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import markdown_table, write_results  # noqa: E402

EXAMPLE = ROOT / "examples" / "nees711" / "nees711.toml"


def _load() -> str:
    return "{:.1f} / {:.1f} / {:.1f}".format(*os.getloadavg())


def _warm(spec) -> float:
    """Run one trial (imports, numba cache, FFT plans); return its wall time."""
    from rths_hil.studies import robustness_trial

    t = time.perf_counter()
    robustness_trial(spec)
    return time.perf_counter() - t


def _timed(spec) -> float:
    """Run one trial; return the CPU seconds the worker process spent on it."""
    from rths_hil.studies import robustness_trial

    t = time.process_time()
    robustness_trial(spec)
    return time.process_time() - t


def throughput(trials: int, seconds: float) -> list[list[object]]:
    """Trials per second in-process and on 1 and 2 Dask workers (same trials)."""
    from rths_hil import studies as study
    from rths_hil.config import load_config

    cfg = load_config(EXAMPLE)
    base = study.inline_twin(cfg)
    perts = study.default_perturbations(base)
    specs = study.plan_trials(base, perts, trials, seed=1, duration=seconds)
    warm = study.plan_trials(base, perts, 2, seed=99, duration=seconds)
    rows: list[list[object]] = []

    def row(name: str, dt: float, cpu: float, ratio: str, load: str) -> None:
        rows.append(
            [name, trials, f"{dt:.1f}", f"{trials / dt:.3f}", ratio, f"{cpu / trials:.2f}", load]
        )
        print(rows[-1], file=sys.stderr, flush=True)

    _warm(warm[0])
    load0 = _load()
    t = time.perf_counter()
    cpu = sum(_timed(s) for s in specs)
    row("in-process (no Dask)", time.perf_counter() - t, cpu, "–", load0)
    ref = None
    for n in (1, 2):
        with study.open_executor("local", n) as ex:
            client = ex._client
            # one warm-up trial on every worker before the clock starts
            for addr in client.scheduler_info()["workers"]:
                client.submit(_warm, warm[1], workers=[addr], pure=False).result()
            load0 = _load()
            t = time.perf_counter()
            cpu = sum(f.result() for f in [ex.submit(_timed, s) for s in specs])
            dt = time.perf_counter() - t
        ref = ref or trials / dt
        row(f"Dask, {n} worker(s)", dt, cpu, f"{trials / dt / ref:.2f}×", load0)
    return rows


def full_study(trials: int) -> tuple[float, str, str]:
    """The CLI's 200-trial study of the example; (wall time s, load before, load after)."""
    from rths_hil.cli import main

    load0 = _load()
    with tempfile.TemporaryDirectory(prefix="bench-study-") as tmp:
        t = time.perf_counter()
        rc = main(
            ["study", "robustness", str(EXAMPLE), "--trials", str(trials), "--out", tmp + "/o"]
        )
        dt = time.perf_counter() - t
        if rc != 0:
            raise SystemExit(f"study exited with {rc}")
    return dt, load0, _load()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=40, help="trials per throughput run")
    p.add_argument("--trial-seconds", type=float, default=10.0, help="record seconds per trial")
    p.add_argument("--study-trials", type=int, default=200)
    p.add_argument("--skip-study", action="store_true", help="throughput only")
    args = p.parse_args(argv)
    rows = throughput(args.trials, args.trial_seconds)
    table = "### Throughput\n\n" + markdown_table(
        [
            "executor",
            "trials",
            "wall (s)",
            "trials/s",
            "vs 1 worker",
            "CPU s per trial",
            "load avg 1/5/15 min",
        ],
        rows,
    )
    two = float(rows[2][3]) / float(rows[1][3])
    notes = [
        f"Throughput: {args.trials} trials of {args.trial_seconds:g} s of the NEES-711 record "
        "(CAN virtual bus, streaming FEI, Kalman and all safety rules on, lockstep), default "
        f"perturbations; two workers run {two:.2f}× the trials per second of one."
    ]
    if not args.skip_study:
        wall, l0, l1 = full_study(args.study_trials)
        table += "\n\n### 200-trial study\n\n" + markdown_table(
            ["study", "wall (s)", "load avg before", "load avg after"],
            [[f"{args.study_trials} trials × 30 s, local cluster of 2", f"{wall:.0f}", l0, l1]],
        )
        print(f"{args.study_trials}-trial study: {wall:.0f} s", file=sys.stderr)
    notes.append(
        "The load average (runnable processes, this machine has "
        f"{os.cpu_count()} logical cores) shows how much of the machine other work took "
        "during each measurement: above the core count the second worker shares a core. "
        "CPU s per trial is the worker process's CPU time per trial: when it stays put while "
        "the wall time per trial grows, the workers were waiting for a core."
    )
    path = write_results(
        "bench_study",
        table,
        title="bench_study: robustness trials on Dask",
        goals="- two workers ≥ 1.8× the trials per second of one\n"
        "- a 200-trial robustness study of `examples/nees711/nees711.toml` in ≤ 5 minutes",
        notes="\n\n".join(notes),
    )
    print(table)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

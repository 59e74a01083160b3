"""Per-step cost of each compensator: ``step`` plus, where the method learns from the reply,
``observe`` — the work the loop does per channel per step between the reply and the next send.

Each method runs 100 000 steps of a 1024 Hz loop (target: two sines with a little noise; the
measured reply: the command 20 ms earlier) after a warm-up, best of 5 repeats. References in the
same run: the same driver loop calling an identity ``step`` (the loop's own overhead, to
subtract) and inverse compensation (the method of the FEI paper's tests). Goal: ≤ 5 µs per
channel per step.

Run: ``.venv/bin/python benchmarks/bench_compensators.py``
"""

from __future__ import annotations

import time

import numpy as np
from _results import markdown_table, write_results

from rths_hil.compensators import BUILTIN, build_compensator
from rths_hil.compensators.base import Compensator
from rths_hil.config import load_config

FS = 1024.0
N = 100_000
REPEATS = 5
DELAY = 20


class Identity(Compensator):
    """The reference: command = target."""

    def step(self, target: float) -> float:
        return target


def _signals() -> tuple[list[float], list[float]]:
    t = np.arange(N) / FS
    x = 0.01 * np.sin(2 * np.pi * 0.8 * t) + 0.004 * np.sin(2 * np.pi * 2.1 * t)
    x += np.random.default_rng(0).normal(0, 1e-6, N)
    return x.tolist(), np.roll(x, DELAY).tolist()


def _time(comp: Compensator, x: list[float], m: list[float]) -> float:
    """Seconds per step (best of REPEATS) of the loop's per-channel compensation work."""
    step = comp.step
    observe = comp.observe if type(comp).observe is not Compensator.observe else None
    best = float("inf")
    for _ in range(REPEATS):
        comp.reset(0.0)
        t0 = time.perf_counter()
        if observe is None:
            for k in range(N):
                step(x[k])
        else:
            for k in range(N):
                c = step(x[k])
                observe(x[k], c, m[k])
        best = min(best, time.perf_counter() - t0)
    return best / N


def main() -> None:
    x, m = _signals()
    ref = _time(Identity(), x, m)
    rows = []
    results = {}
    for name in BUILTIN:
        cfg = load_config(None, [f"compensation.method={name}", "compensation.delay=20ms"])
        comp = build_compensator(cfg["compensation"], FS)
        per = _time(comp, x, m)
        results[name] = per
    inv = results["inverse"]
    for name, per in results.items():
        net = per - ref
        rows.append(
            [
                f"`{name}`",
                f"{per * 1e6:.2f}",
                f"{net * 1e6:.2f}",
                f"{per / inv:.2f}",
                "yes" if per <= 5e-6 else "**no**",
            ]
        )
    rows.append(["identity (reference)", f"{ref * 1e6:.2f}", "0", f"{ref / inv:.2f}", "-"])
    table = markdown_table(
        ["method", "µs / step", "µs / step above the identity", "× inverse", "≤ 5 µs"], rows
    )
    print(table)
    write_results(
        "bench_compensators",
        table,
        title="Per-step cost of the compensators",
        goals="≤ 5 µs per channel per step (step + observe), plain Python floats / numba.",
        notes=(
            "`µs / step` includes the Python loop and call overhead of the driver loop (the "
            "identity row); `ats` adds a numba-compiled `observe` every step (two 6th-order "
            "Butterworth filters) and rebuilds its 3×3 normal equations over the 64-row window "
            "every 16th step; `model` runs its second-order sections in plain Python floats."
        ),
    )


if __name__ == "__main__":
    main()

"""Online adaptive α against offline tuning on the NEES-711 twin (docs/tuning.md).

Both start from α = 15 (the FEI paper's under-compensated test). The loop's adaptive option
(``compensation.adaptive``, :class:`rths_hil.compensators.inverse.AdaptiveAlpha`) moves α during the
test from the streaming MWO delay estimate (window 3T = 3.9 s) with time constant T and rate
limit 5 /s; offline tuning (``rths-hil tune``) runs 15 s trials between tests. The balanced α
is the zero crossing of d(α) from two whole-record tests (α = 27 and 29).

Usage::

    python examples/nees711/adaptive.py [--out DIR] [--docs] [--set key=value]...

prints the comparison (markdown); ``--docs`` also writes ``docs/img/nees711_adaptive.png``.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from rths_hil.config import load_config
from rths_hil.fei import fei
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import read_run
from rths_hil.tuning import LoopTrials, sweep, tune

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "nees711.toml"
DOCS = HERE.parent.parent / "docs"
BAND = 1.5  # ± band around the balanced α (the acceptance band)
TIME_CONSTANTS = (2.0, 6.0, 12.0)


def settle_time(t: np.ndarray, alpha: np.ndarray, target: float, band: float) -> float:
    """First time after which α stays within ``target ± band`` to the end (NaN if never)."""
    out = np.abs(alpha - target) > band
    if out[-1]:
        return math.nan
    idx = np.flatnonzero(out)
    return float(t[idx[-1] + 1]) if idx.size else float(t[0])


def adaptive_run(cfg_over: list[str], out: Path, time_constant: float) -> dict:
    """One whole-record test with adaptive α from α = 15; its α history and evaluation."""
    cfg = load_config(
        CONFIG,
        [
            *cfg_over,
            "compensation.alpha=15",
            "compensation.adaptive=true",
            f"compensation.time_constant={time_constant}",
            "kalman.enabled=false",
            "loop.console=0",
        ],
    )
    run_dir = out / f"adaptive-T{time_constant:g}"
    RTHSLoop(cfg, run_dir, mode="lockstep").run()
    rec = read_run(run_dir).record
    whole = fei(rec["target"], rec["measured"], cfg["loop"]["fs"])
    return {"T": time_constant, "rec": rec, "whole": whole}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", help="directory for the runs (default: temporary)")
    p.add_argument("--docs", action="store_true", help="write docs/img/nees711_adaptive.png")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="nees711-adaptive-"))
    cfg = load_config(CONFIG, args.set)
    fs = cfg["loop"]["fs"]

    # the balanced α: zero crossing of d(α) from two whole-record tests
    ref = sweep(LoopTrials(cfg, out / "ref", duration=0.0, prefix="alpha"), [27.0, 29.0])
    a0 = ref.alpha

    # offline: rths-hil tune from α = 15 (15 s trials)
    cfg15 = load_config(CONFIG, [*args.set, "compensation.alpha=15"])
    off = tune(LoopTrials(cfg15, out / "offline", duration=15.0), alpha0=15.0, dt=1 / fs)
    tuned = sweep(LoopTrials(cfg, out / "tuned", duration=0.0, prefix="alpha"), [off.alpha])
    t_tuned = tuned.trials[0]

    runs = [adaptive_run(args.set, out, tc) for tc in TIME_CONSTANTS]
    lines = [
        f"Balanced α (zero crossing of whole-record d(α), α = 27 and 29): **{a0:.2f}**.",
        "",
        "| method | α history | seconds of shaking to reach α₀ ± 1.5 | overshoot of α above "
        "α₀ | α at the end | whole-record d (ms) | whole-record A |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    alphas = " → ".join(f"{t.alpha:.2f}" for t in off.trials)
    trial_s = sum(t.steps for t in off.trials) / fs
    over = max(t.alpha for t in off.trials) - a0
    lines.append(
        f"| offline `rths-hil tune` ({off.iterations} trials of 15 s, {off.stop}) | {alphas} | "
        f"{trial_s:.0f} (trials, before the test) | {max(over, 0.0):.2f} | {off.alpha:.2f} | "
        f"{1e3 * t_tuned.delay:+.2f} | {t_tuned.amplitude:.4f} |"
    )
    for r in runs:
        rec = r["rec"]
        t, al = rec["time"], rec["alpha"]
        ts = settle_time(t, al, a0, BAND)
        first = np.flatnonzero(np.abs(al - a0) <= BAND)
        t_in = float(t[first[0]]) if first.size else math.nan
        r.update(settle=ts, enter=t_in, overshoot=float(al.max() - a0), end=float(al[-1]))
        lines.append(
            f"| adaptive, T = {r['T']:g} s (rate ≤ 5 /s, window 3.9 s) | 15 → {al[-1]:.2f} | "
            f"{t_in:.1f} (first entry), {ts:.1f} (stays) | {max(r['overshoot'], 0):.2f} | "
            f"{al[-1]:.2f} | {1e3 * r['whole'].delay:+.2f} | {r['whole'].amplitude:.4f} |"
        )
    table = "\n".join(lines)
    print(table)
    print(f"\nruns in {out}", file=sys.stderr)
    if args.docs:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True, constrained_layout=True)
        ax = axes[0]
        ax.axhspan(a0 - BAND, a0 + BAND, color="C2", alpha=0.15, label=f"α₀ ± {BAND:g}")
        ax.axhline(a0, color="C2", lw=0.8)
        for i, r in enumerate(runs):
            rec = r["rec"]
            ax.plot(
                rec["time"],
                rec["alpha"],
                color=f"C{i}",
                lw=1.2,
                label=f"adaptive, T = {r['T']:g} s",
            )
            d = np.where(rec["fei_valid"], rec["fei_delay"], np.nan)
            axes[1].plot(
                rec["time"], 1e3 * d, color=f"C{i}", lw=1.0, label=f"adaptive, T = {r['T']:g} s"
            )
        ax.axhline(
            off.alpha,
            color="k",
            ls="--",
            lw=0.9,
            label=f"offline tune: α = {off.alpha:.2f} ({off.iterations} trials)",
        )
        ax.set_ylabel("α (steps)")
        ax.legend(loc="lower right", fontsize=8)
        axes[1].axhline(0, color="0.4", lw=0.6)
        axes[1].set_ylabel("online MWO d (ms)")
        axes[1].set_xlabel("time (s)")
        axes[1].legend(loc="upper right", fontsize=8)
        for ax in axes:
            ax.grid(True, alpha=0.3)
        fig.suptitle("NEES-711 twin: adaptive α during the test vs offline tuning, from α = 15")
        (DOCS / "img").mkdir(parents=True, exist_ok=True)
        fig.savefig(DOCS / "img" / "nees711_adaptive.png", dpi=100)
        plt.close(fig)
    return 0


if __name__ == "__main__":
    sys.exit(main())

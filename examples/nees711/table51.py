"""The FEI paper's Table 5.1 and Fig. 5.1/5.2 (NEES project 711) rebuilt on the twin: α = 15, 29,
45.

Runs the configuration of the FEI paper's Section 5 (``nees711.toml``: SDOF MRF with Bouc-Wen,
elastomeric damper as a Kelvin–Voigt specimen on a first-order servo-hydraulic twin, CR at
1024 Hz, Northridge 1994 MUL009 scaled to 0.322 m/s²) in lockstep for the three actuator-delay
estimates of the FEI paper, through the library's sweep (:func:`rths_hil.tuning.sweep`), and
evaluates each whole record (the FEI paper's Eq. 2.1–2.5) and its moving windows with overlap (MWO,
OL = N − 1, 3 natural periods = 3.9 s, the FEI paper's Fig. 5.2).

Usage::

    python examples/nees711/table51.py [--out DIR] [--docs] [--set key=value]...

prints the table next to the FEI paper's values; ``--docs`` also writes ``docs/nees711_table51.md``
and the figures ``docs/img/nees711_fig51.png`` (calculated, command and measured displacement)
and ``docs/img/nees711_fig52.png`` (MWO A(t), d(t)).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rths_hil.config import load_config
from rths_hil.fei import MovingFEIResult, moving_fei
from rths_hil.records.recorder import read_run
from rths_hil.tuning import LoopTrials, SweepResult, Trial, sweep

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "nees711.toml"
DOCS = HERE.parent.parent / "docs"
#: The FEI paper's Table 5.1: equivalent delay d (s) for each α_es.
PAPER_DELAY = {15: 12.3e-3, 29: -1.1e-3, 45: -16.2e-3}
#: The FEI paper's Section 5: "the amplitude errors for all three tests are less than 0.5 %".
PAPER_AMPLITUDE_ERROR = 0.005
ALPHAS = (15.0, 29.0, 45.0)


@dataclass
class Row:
    """One test of the table: its whole-record evaluation, MWO and time histories."""

    trial: Trial
    mwo: MovingFEIResult
    time: np.ndarray
    target: np.ndarray
    command: np.ndarray
    measured: np.ndarray

    @property
    def paper_delay(self) -> float:
        return PAPER_DELAY.get(round(self.trial.alpha), math.nan)

    def mwo_delay_median(self) -> float:
        d = self.mwo.delay[self.mwo.valid]
        return float(np.median(d)) if d.size else math.nan

    def mwo_delay_range(self) -> tuple[float, float]:
        d = self.mwo.delay[self.mwo.valid]
        return (
            (float(np.percentile(d, 5)), float(np.percentile(d, 95)))
            if d.size
            else (
                math.nan,
                math.nan,
            )
        )


def run_table(
    out_dir: str | Path,
    alphas: tuple[float, ...] = ALPHAS,
    overrides: list[str] | tuple[str, ...] = (),
    config: str | Path = CONFIG,
) -> tuple[list[Row], SweepResult]:
    """Run the tests (whole record, lockstep on the twin) and evaluate them.

    Returns the rows and the sweep over ``alphas`` (its zero crossing is the balanced α).
    """
    cfg = load_config(config, list(overrides))
    runner = LoopTrials(cfg, out_dir, duration=0.0, prefix="alpha")
    result = sweep(runner, alphas, factor=cfg["compensation"]["amplitude"])
    window = cfg.window_s
    rows = []
    for t in result.trials:
        rec = read_run(t.run_dir).record
        mwo = moving_fei(rec["target"], rec["measured"], runner.fs, window, hop=1)
        rows.append(Row(t, mwo, rec["time"], rec["target"], rec["command"], rec["measured"]))
    return rows, result


def markdown_table(rows: list[Row], result: SweepResult, note: str = "") -> str:
    """Table 5.1 next to the FEI paper's values (markdown)."""
    out = [
        "| α_es | paper d (ms) | twin d (ms) | twin − paper (ms) | paper A error | twin A | "
        "twin A error | MWO d median [5–95 %] (ms) | J1 (ms) | J2 (%) | f_eq (Hz) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        t = r.trial
        lo, hi = r.mwo_delay_range()
        out.append(
            f"| {t.alpha:g} | {1e3 * r.paper_delay:+.1f} | {1e3 * t.delay:+.2f} | "
            f"{1e3 * (t.delay - r.paper_delay):+.2f} | < {100 * PAPER_AMPLITUDE_ERROR:g} % | "
            f"{t.amplitude:.4f} | {100 * abs(t.amplitude - 1):.2f} % | "
            f"{1e3 * r.mwo_delay_median():+.2f} [{1e3 * lo:+.1f}, {1e3 * hi:+.1f}] | "
            f"{1e3 * t.j1:+.2f} | {t.j2:.2f} | {t.f_eq:.3f} |"
        )
    out.append("")
    if result.found:
        out.append(
            f"Zero crossing of d(α) through the three tests (linear interpolation): "
            f"α = {result.alpha:.2f}; the FEI paper (same interpolation of its Table 5.1): α = "
            f"{paper_zero_crossing():.2f}."
        )
    if note:
        out += ["", note]
    return "\n".join(out)


def paper_zero_crossing() -> float:
    """Zero crossing of the FEI paper's d(α), linear between α = 15 and 29."""
    from rths_hil.tuning import zero_crossing

    a = sorted(PAPER_DELAY)
    return float(zero_crossing(a, [PAPER_DELAY[k] for k in a]))


def plot_fig51(rows: list[Row], path: str | Path) -> Path:
    """The FEI paper's Fig. 5.1: calculated (target), command and measured displacement per α."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(rows),
        2,
        figsize=(11, 2.6 * len(rows)),
        constrained_layout=True,
        gridspec_kw={"width_ratios": [2.2, 1]},
    )
    axes = np.atleast_2d(axes)
    for r, (full, zoom) in zip(rows, axes, strict=True):
        k = int(np.argmax(np.abs(r.target)))
        t0 = r.time[k]
        sel = (r.time > t0 - 0.35) & (r.time < t0 + 0.35)
        for ax, s in ((full, slice(None)), (zoom, sel)):
            ax.plot(r.time[s], 1e3 * r.target[s], lw=1.0, color="k", label="calculated")
            ax.plot(r.time[s], 1e3 * r.command[s], lw=0.9, color="C0", ls="--", label="command")
            ax.plot(r.time[s], 1e3 * r.measured[s], lw=0.9, color="C3", label="measured")
            ax.grid(True, alpha=0.3)
        full.axvspan(t0 - 0.35, t0 + 0.35, color="C1", alpha=0.15)
        full.set_ylabel("displacement (mm)")
        full.set_title(
            f"α_es = {r.trial.alpha:g}: d = {1e3 * r.trial.delay:+.1f} ms "
            f"(FEI paper {1e3 * r.paper_delay:+.1f} ms), A = {r.trial.amplitude:.4f}",
            fontsize=10,
        )
        zoom.set_title(f"zoom at the peak (t = {t0:.2f} s)", fontsize=10)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    axes[-1, 1].set_xlabel("time (s)")
    out = Path(path)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def plot_fig52(rows: list[Row], path: str | Path, window_s: float) -> Path:
    """The FEI paper's Fig. 5.2: MWO amplitude A(t) and equivalent delay d(t) of the three tests."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True, constrained_layout=True)
    for i, r in enumerate(rows):
        m = r.mwo
        a = np.where(m.valid, m.amplitude, np.nan)
        d = np.where(m.valid, m.delay, np.nan)
        lab = f"α_es = {r.trial.alpha:g}"
        axes[0].plot(m.t_end, a, lw=1.0, color=f"C{i}", label=lab)
        axes[1].plot(m.t_end, 1e3 * d, lw=1.0, color=f"C{i}", label=lab)
        axes[1].axhline(1e3 * r.paper_delay, color=f"C{i}", ls=":", lw=0.9)
    axes[0].axhline(1.0, color="0.4", lw=0.6)
    axes[0].set_ylabel("A")
    axes[0].set_ylim(0.95, 1.05)
    axes[1].axhline(0.0, color="0.4", lw=0.6)
    axes[1].set_ylabel("d (ms)  (dotted: the FEI paper's Table 5.1)")
    axes[1].set_xlabel("window end time (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"MWO, window {window_s:.2f} s (3 natural periods), OL = N − 1")
    out = Path(path)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", help="directory for the three run directories (default: temporary)")
    p.add_argument("--docs", action="store_true", help="write the table and figures into docs/")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="nees711-"))
    rows, result = run_table(out, overrides=args.set)
    cfg = load_config(CONFIG, args.set)
    note = (
        "Twin: first-order servo-hydraulic lag T = 26.2 ms, static gain 0.996; Kelvin–Voigt "
        "damper k = 1.19e6 N/m, c = 2.46e5 N·s/m; Northridge 1994 Beverly Hills - Mulholland "
        "(RSN 953, MUL009) scaled to PGA 0.322 m/s², 30 s at 1024 Hz, lockstep "
        f"({cfg['driver']['name']} driver). Produced by examples/nees711/table51.py."
    )
    table = markdown_table(rows, result, note)
    print(table)
    print(f"\nrun directories in {out}", file=sys.stderr)
    if args.docs:
        (DOCS / "img").mkdir(parents=True, exist_ok=True)
        (DOCS / "nees711_table51.md").write_text(
            "# The FEI paper's Table 5.1 on the twin\n\n" + table + "\n", encoding="utf-8"
        )
        plot_fig51(rows, DOCS / "img" / "nees711_fig51.png")
        plot_fig52(rows, DOCS / "img" / "nees711_fig52.png", cfg.window_s)
        print(
            f"wrote {DOCS / 'nees711_table51.md'} and docs/img/nees711_fig51/52.png",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

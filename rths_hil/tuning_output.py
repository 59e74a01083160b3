"""Output of the compensator tuning (:mod:`rths_hil.tuning`): the trial table (console and
CSV), the tuned configuration, and the figures of a tuning run and of a sweep."""

from __future__ import annotations

import copy
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .config import Config, set_compensation, to_toml
from .tuning import SweepResult, Trial, TuneResult

__all__ = [
    "format_table",
    "plot_sweep",
    "plot_tuning",
    "tuned_config",
    "write_table_csv",
    "write_tuned_config",
]


def format_table(trials: Sequence[Trial], best: int = 0) -> str:
    """The iteration (or sweep) table: α, factor, A, d, J1, J2, f_eq, status."""
    head = (
        f"{'#':>3} {'alpha':>8} {'factor':>8} {'A':>8} {'d (ms)':>9} {'J1 (ms)':>9} "
        f"{'J2 (%)':>8} {'f_eq (Hz)':>9}  status"
    )
    lines = [head, "-" * len(head)]
    for t in trials:
        status = t.status if t.status != "completed" else ("invalid FEI" if not t.valid else "")
        mark = " *" if t.index == best else ""
        lines.append(
            f"{t.index:>3} {t.alpha:>8.3f} {t.factor:>8.4f} {t.amplitude:>8.4f} "
            f"{1e3 * t.delay:>9.2f} {1e3 * t.j1:>9.2f} {t.j2:>8.2f} {t.f_eq:>9.3f}  "
            f"{status}{mark}"
        )
    return "\n".join(lines)


TABLE_CSV_COLUMNS: tuple[tuple[str, str], ...] = (
    ("index", "index"),
    ("alpha", "alpha"),
    ("factor", "factor"),
    ("amplitude", "amplitude"),
    ("delay", "delay_s"),
    ("f_eq", "f_eq_Hz"),
    ("valid", "valid"),
    ("j1", "j1_s"),
    ("j2", "j2_percent"),
    ("status", "status"),
    ("steps", "steps"),
    ("pga", "pga_m_per_s2"),
    ("reason", "reason"),
    ("run_dir", "run_dir"),
)
"""(trial field, CSV column) of :func:`write_table_csv`: a quantity with a unit carries it in
its column name (``delay_s``, ``j2_percent``, ``pga_m_per_s2``); the others are
dimensionless (α, the amplitude factor, A) or not quantities."""


def write_table_csv(trials: Sequence[Trial], path: str | Path) -> Path:
    """Write the trials as CSV, SI units named in the columns (:data:`TABLE_CSV_COLUMNS`:
    ``delay_s``, ``j1_s``, ``f_eq_Hz``, ``j2_percent``, ``pga_m_per_s2``)."""
    out = Path(path)
    with out.open("w", encoding="utf-8") as fh:
        fh.write(",".join(name for _, name in TABLE_CSV_COLUMNS) + "\n")
        for t in trials:
            row = t.as_dict()
            vals = []
            for c, _ in TABLE_CSV_COLUMNS:
                v = row[c]
                if isinstance(v, float):
                    vals.append(repr(v))
                elif isinstance(v, str):
                    vals.append('"' + v.replace('"', "'") + '"' if ("," in v or '"' in v) else v)
                else:
                    vals.append(str(v))
            fh.write(",".join(vals) + "\n")
    return out


def tuned_config(cfg: Config, alpha: float, factor: float) -> Config:
    """A copy of ``cfg`` with the tuned compensation (adaptive left as configured)."""
    out = copy.deepcopy(cfg)
    out["compensation"]["enabled"] = True
    out["compensation"]["method"] = "inverse"
    set_compensation(out["compensation"], "alpha", alpha, out["loop"]["fs"])
    out["compensation"]["amplitude"] = float(factor)
    return out


def write_tuned_config(
    cfg: Config, path: str | Path, alpha: float, factor: float, note: str = ""
) -> Path:
    """Write ``cfg`` with the tuned α and amplitude factor as TOML.

    File paths in the configuration (ground-motion record, twin model file) are rewritten
    relative to the new file's directory so that the written file loads from where it is.
    """
    out = Path(path)
    new = tuned_config(cfg, alpha, factor)
    where = out.resolve().parent
    for section, key in (("ground_motion", "record"), ("twin", "model")):
        spec = new[section][key]
        if spec and spec != "default":
            p = cfg.resolve_path(spec)
            if p.is_file():
                rel = os.path.relpath(p.resolve(), where)
                new[section][key] = str(p.resolve()) if rel.startswith("..") else rel
    lines = ["# Configuration tuned by `rths-hil tune`"]
    lines += [f"# {line}" for line in note.splitlines() if line]
    lines.append(f"# from {cfg.source}")
    lines.append("")
    out.write_text("\n".join(lines) + to_toml(new), encoding="utf-8")
    return out


def plot_tuning(result: TuneResult, path: str | Path, title: str = "") -> Path:
    """α, d and A against iteration, with the tolerance bands (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = result.trials
    it = np.array([t.index for t in tr], dtype=float)
    fig, axes = plt.subplots(3, 1, figsize=(7, 7.5), sharex=True, constrained_layout=True)
    ax = axes[0]
    ax.plot(it, [t.alpha for t in tr], "o-", color="C0", label="α")
    ax.set_ylabel("α (steps)")
    ax2 = ax.twinx()
    ax2.plot(it, [t.factor for t in tr], "s--", color="C1", label="amplitude factor")
    ax2.set_ylabel("amplitude factor", color="C1")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="best")
    ax.grid(True, alpha=0.3)
    ax = axes[1]
    ax.axhspan(
        -1e3 * result.tol_delay, 1e3 * result.tol_delay, color="C2", alpha=0.15, label="tolerance"
    )
    ax.plot(it, [1e3 * t.delay for t in tr], "o-", color="C3")
    ax.axhline(0.0, color="0.4", lw=0.6)
    ax.set_ylabel("d (ms)")
    ax.legend(loc="upper right")
    ax.grid(True, alpha=0.3)
    ax = axes[2]
    ax.axhspan(1 - result.tol_amplitude, 1 + result.tol_amplitude, color="C2", alpha=0.15)
    ax.plot(it, [t.amplitude for t in tr], "o-", color="C4")
    ax.axhline(1.0, color="0.4", lw=0.6)
    ax.set_ylabel("A")
    ax.set_xlabel("iteration")
    ax.set_xticks(it)
    ax.grid(True, alpha=0.3)
    fig.suptitle(title or f"rths-hil tune: {result.stop}")
    from .plotting import save_figure

    return save_figure(fig, path, 110)


def plot_sweep(
    result: SweepResult,
    path: str | Path,
    tol_delay: float | None = None,
    tol_amplitude: float | None = None,
    title: str = "",
) -> Path:
    """d(α) and A(α) of a sweep with the zero crossing marked (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    use = [t for t in result.trials if t.valid and t.status == "completed"]
    a = np.array([t.alpha for t in use])
    fig, axes = plt.subplots(2, 1, figsize=(7, 6), sharex=True, constrained_layout=True)
    ax = axes[0]
    if tol_delay:
        ax.axhspan(-1e3 * tol_delay, 1e3 * tol_delay, color="C2", alpha=0.15, label="tolerance")
    ax.plot(a, [1e3 * t.delay for t in use], "o-", color="C3", label="d(α)")
    ax.axhline(0.0, color="0.4", lw=0.6)
    ax.set_ylabel("d (ms)")
    ax = axes[1]
    if tol_amplitude:
        ax.axhspan(1 - tol_amplitude, 1 + tol_amplitude, color="C2", alpha=0.15)
    ax.plot(a, [t.amplitude for t in use], "o-", color="C4", label="A(α)")
    ax.axhline(1.0, color="0.4", lw=0.6)
    ax.set_ylabel("A")
    ax.set_xlabel("α (steps)")
    for ax in axes:
        if result.found:
            ax.axvline(
                result.alpha,
                color="k",
                ls="--",
                lw=0.9,
                label=f"zero crossing α = {result.alpha:.2f}",
            )
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    fig.suptitle(title or "rths-hil tune --sweep")
    from .plotting import save_figure

    return save_figure(fig, path, 110)

"""Outputs of the diagnosis: ``report.json``, the augmented model file, the PNG, console lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rths_hil.sim_backends.modelfile import dump_model

from ..errors import InputError
from ..formats import json_text
from .workflow import Diagnosis

__all__ = ["plot_diagnosis", "summary_lines", "write_outputs"]


def _fmt_params(params: dict[str, float]) -> str:
    units = {
        "offset": ("mm", 1e3),
        "rate": ("mm/min", 6e4),
        "width": ("mm", 1e3),
        "limit": None,
        "center": ("mm", 1e3),
        "time_constant": ("ms", 1e3),
        "delay": ("ms", 1e3),
        "amplitude": ("ms", 1e3),
        "period": ("s", 1.0),
        "gain": ("", 1.0),
        "actuator_stiffness": ("N/m", 1.0),
        "specimen_stiffness": ("N/m", 1.0),
        "specimen_damping": ("N·s/m", 1.0),
    }
    out = []
    for k, v in params.items():
        u = units.get(k, ("", 1.0))
        if u is None:  # limit: m for strokes, m/s for speeds
            u = ("mm", 1e3) if abs(v) < 1.0 and "center" in params else ("m/s", 1.0)
        out.append(f"{k} {v * u[1]:.4g}{(' ' + u[0]) if u[0] else ''}")
    return ", ".join(out)


def summary_lines(dx: Diagnosis, model_path: str | None = None) -> list[str]:
    """The console summary: base gap, one line per named effect, the stop reason, the result."""
    b = dx.before
    lines = [
        f"base model ({dx.base_source}): J2 {b.j2:.3g} %, J3 {b.j3:.3g} %, "
        f"FEI A {b.fei_amplitude:.4f} d {1e3 * b.fei_delay:.3f} ms; "
        f"noise {1e6 * dx.final.noise:.3g} µm"
    ]
    for i, s in enumerate(dx.steps, 1):
        alt = f" (indistinguishable from {', '.join(s.alternatives)})" if s.alternatives else ""
        acts = s.where.get("acts", {})
        lines.append(
            f"{i}. {s.name}: {_fmt_params(s.params)}; ΔBIC {s.delta_bic:.4g}{alt}; "
            f"acts on {100 * acts.get('fraction', 0):.0f} % of the record; "
            f"J2 {s.before.j2:.3g} → {s.after.j2:.3g} %, J3 {s.before.j3:.3g} → {s.after.j3:.3g} %"
        )
    st = dx.stop
    if "best" in st:
        lines.append(
            f"{'answer: none' if not dx.steps else 'then nothing significant'} "
            f"(best remaining: {st['best']}, ΔBIC {st['delta_bic']:.3g} ≤ {st['threshold']:g})"
        )
    else:
        lines.append(f"stopped: {st.get('reason', '')}")
    a = dx.after
    tail = (
        f"gap J2 {b.j2:.3g} → {a.j2:.3g} %, J3 {b.j3:.3g} → {a.j3:.3g} %, "
        f"FEI A {a.fei_amplitude:.4f} d {1e3 * a.fei_delay:.3f} ms"
    )
    if model_path:
        tail += f"; model → {model_path}"
    lines.append(tail)
    return lines


def plot_diagnosis(dx: Diagnosis, path: str | Path, title: str = "") -> Path:
    """PNG: measured/base/augmented overlay, residuals before/after with the localised windows,
    moving-window FEI A(t) and d(t) before/after with their noise bands, the transfer-function
    ratio with coherence, and the residual against velocity (regime)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = dx.time - dx.time[0]
    fig = plt.figure(figsize=(12, 13), layout="constrained")
    gs = fig.add_gridspec(5, 2)
    ax0 = fig.add_subplot(gs[0, :])
    ax0.plot(t, 1e3 * dx.measured, color="0.6", lw=1.2, label="measured")
    ax0.plot(t, 1e3 * dx.base_pred, color="C0", lw=0.8, label="base model")
    ax0.plot(t, 1e3 * dx.pred, color="C3", lw=0.8, ls="--", label="augmented model")
    ax0.set_ylabel("displacement (mm)")
    ax0.legend(loc="upper right", fontsize=8)
    ax0.set_title(title or f"diagnosis: {dx.answer}")

    ax1 = fig.add_subplot(gs[1, :], sharex=ax0)
    r0 = dx.measured - dx.base_pred
    r1 = dx.measured - dx.pred
    for k, (a, b) in enumerate(dx.base_localisation.when["intervals_s"]):
        ax1.axvspan(
            a, b, color="C1", alpha=0.15, lw=0, label="outside noise band" if k == 0 else None
        )
    ax1.plot(t, 1e3 * r0, color="C0", lw=0.6, label=f"before (J2 {dx.before.j2:.3g} %)")
    ax1.plot(t, 1e3 * r1, color="C3", lw=0.6, label=f"after (J2 {dx.after.j2:.3g} %)")
    sig = 3e3 * dx.final.noise
    ax1.axhline(sig, color="k", lw=0.6, ls=":", label="±3σ noise")
    ax1.axhline(-sig, color="k", lw=0.6, ls=":")
    ax1.set_ylabel("residual (mm)")
    ax1.legend(loc="upper right", fontsize=8)

    ax2 = fig.add_subplot(gs[2, 0], sharex=ax0)
    ax3 = fig.add_subplot(gs[2, 1], sharex=ax0)
    for loc, color, label in (
        (dx.base_localisation, "C0", "before"),
        (dx.final, "C3", "after"),
    ):
        mv = loc.moving
        if mv is None or not len(mv):
            continue
        ax2.plot(mv.t_end, mv.amplitude, color=color, lw=0.8, label=label)
        ax3.plot(mv.t_end, 1e3 * mv.delay, color=color, lw=0.8, label=label)
        if "band_a" in loc.arrays and color == "C3":
            ba = loc.arrays["band_a"]
            bd = loc.arrays["band_d"]
            ax2.fill_between(mv.t_end, 1 - ba, 1 + ba, color="0.85", lw=0, label="noise band")
            ax3.fill_between(mv.t_end, -1e3 * bd, 1e3 * bd, color="0.85", lw=0, label="noise band")
    ax2.set_ylabel("moving FEI A")
    ax3.set_ylabel("moving FEI d (ms)")
    ax2.set_xlabel("time (s)")
    ax3.set_xlabel("time (s)")
    ax2.legend(fontsize=8)
    ax3.legend(fontsize=8)

    ax4 = fig.add_subplot(gs[3, 0])
    ax5 = fig.add_subplot(gs[3, 1])
    for loc, color, label in ((dx.base_localisation, "C0", "before"), (dx.final, "C3", "after")):
        a = loc.arrays
        if "f" not in a:
            continue
        use = a["use"]
        f = a["f"]
        ratio = np.where(use, a["ratio"], np.nan)
        ax4.plot(f, np.abs(ratio), color=color, lw=0.9, label=f"|H_meas/H_model| {label}")
        with np.errstate(divide="ignore", invalid="ignore"):
            ph_delay = -np.angle(ratio) / (2 * np.pi * f)
        ax5.plot(f, 1e3 * ph_delay, color=color, lw=0.9, label=f"phase delay {label}")
    a = dx.base_localisation.arrays
    if "f" in a and a["use"].any():
        fmax = float(a["f"][a["use"]].max()) * 1.5
        ax4.set_xlim(0, fmax)
        ax5.set_xlim(0, fmax)
        axc = ax4.twinx()
        axc.plot(a["f"], a["coherence"], color="0.5", lw=0.7, ls=":", label="coherence")
        axc.set_ylim(0, 1.05)
        axc.set_ylabel("coherence γ²")
    ax4.axhline(1.0, color="k", lw=0.5)
    ax5.axhline(0.0, color="k", lw=0.5)
    ax4.set_xlabel("frequency (Hz)")
    ax5.set_xlabel("frequency (Hz)")
    ax4.set_ylabel("amplitude ratio")
    ax5.set_ylabel("delay of measured vs model (ms)")
    ax4.legend(fontsize=8, loc="upper left")
    ax5.legend(fontsize=8)

    ax6 = fig.add_subplot(gs[4, 0])
    ax7 = fig.add_subplot(gs[4, 1])
    step = max(len(t) // 4000, 1)
    v = np.gradient(dx.base_pred) * dx.fs
    ax6.plot(1e3 * v[::step], 1e3 * r0[::step], ".", ms=1.5, color="C0", label="before")
    ax6.plot(1e3 * v[::step], 1e3 * r1[::step], ".", ms=1.5, color="C3", label="after")
    ax6.set_xlabel("model velocity (mm/s)")
    ax6.set_ylabel("residual (mm)")
    ax6.legend(fontsize=8, markerscale=5)
    ax7.plot(1e3 * dx.base_pred[::step], 1e3 * r0[::step], ".", ms=1.5, color="C0", label="before")
    ax7.plot(1e3 * dx.base_pred[::step], 1e3 * r1[::step], ".", ms=1.5, color="C3", label="after")
    ax7.set_xlabel("model displacement (mm)")
    ax7.set_ylabel("residual (mm)")
    ax7.legend(fontsize=8, markerscale=5)
    from ..plotting import save_figure

    return save_figure(fig, path, 90)


def write_outputs(
    dx: Diagnosis,
    out_dir: str | Path,
    record: str = "",
    plot: bool = True,
) -> dict[str, Path]:
    """Write ``report.json``, ``model.toml`` (augmented), ``base_model.toml`` (when the base was
    fitted to the record) and ``diagnose.png`` into ``out_dir``; return their paths."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create output directory ({exc.strerror})") from None
    paths: dict[str, Path] = {}
    header = f"augmented by rths-hil diagnose from {record}: {dx.answer}\n" + "\n".join(
        f"{s.name}: {_fmt_params(s.params)} (ΔBIC {s.delta_bic:.4g})" for s in dx.steps
    )
    paths["model"] = out / "model.toml"
    dump_model(dx.model, paths["model"], header=header)
    if dx.base_source.startswith("fitted"):
        paths["base_model"] = out / "base_model.toml"
        dump_model(dx.base, paths["base_model"], header=f"fitted by rths-hil diagnose to {record}")
    if plot:
        paths["plot"] = plot_diagnosis(dx, out / "diagnose.png", title=f"{record}: {dx.answer}")
    report = dx.report(str(paths["model"]))
    report["record_file"] = record
    if "base_model" in paths:
        report["base_model_file"] = str(paths["base_model"])
    if "plot" in paths:
        report["plot"] = str(paths["plot"])
    paths["report"] = out / "report.json"
    try:
        paths["report"].write_text(json_text(report), encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{paths['report']}: cannot write ({exc.strerror})") from None
    return paths

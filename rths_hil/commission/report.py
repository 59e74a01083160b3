"""The commissioning report: each channel's steps and traces, ``report.md`` and its plots."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .plant import PlantFit

__all__ = ["ChannelReport", "StepResult", "identified", "write_report"]


@dataclass
class StepResult:
    """One commissioning step: ``passed``, ``failed`` or ``skipped``, why, and its figures."""

    name: str
    status: str
    reason: str = ""
    figures: dict[str, Any] = field(default_factory=dict)


@dataclass
class ChannelReport:
    """The steps of one channel and the traces for its plots."""

    name: str
    driver: str
    target: str  # "twin" or "hardware"
    steps: list[StepResult] = field(default_factory=list)
    latency: np.ndarray = field(default_factory=lambda: np.zeros(0))
    motion: tuple[np.ndarray, np.ndarray] | None = None
    chirp: tuple[np.ndarray, np.ndarray] | None = None
    plant: PlantFit | None = None
    #: longest time between two replies of the latency step (s), NaN when not measured
    reply_gap: float = math.nan
    #: the controller's heartbeat timeout when known (s), else 0
    controller_watchdog: float = 0.0
    plot: str = ""

    @property
    def failed(self) -> list[StepResult]:
        """The failed steps."""
        return [s for s in self.steps if s.status == "failed"]

    def step(self, name: str) -> StepResult | None:
        """The step called ``name``, or None."""
        return next((s for s in self.steps if s.name == name), None)

    def result(self, name: str, why: str, figures: dict[str, Any] | None = None) -> None:
        """Add the step ``name``: failed with the reason ``why``, passed when it is empty."""
        self.steps.append(StepResult(name, "failed" if why else "passed", why, figures or {}))

    def passed(self, name: str) -> bool:
        """Whether the step called ``name`` passed."""
        s = self.step(name)
        return s is not None and s.status == "passed"


def identified(reports: list[ChannelReport]) -> bool:
    """Whether every channel's ``plant`` step passed (the tuned fragment is written)."""
    return bool(reports) and all(r.plant is not None and r.passed("plant") for r in reports)


def write_report(reports: list[ChannelReport], plan: Any, out: Path) -> Path:
    """``report.md`` and, unless ``output.plot`` is false, one PNG per channel in ``out``;
    return the report's path."""
    draw = bool(plan.cfg["output"]["plot"])
    if draw:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    lines = [
        "# Commissioning report",
        "",
        f"Configuration: `{plan.cfg.source}`; loop rate {plan.fs:g} Hz.",
        "",
    ]
    verdict = "PASSED" if not any(r.failed for r in reports) else "FAILED"
    lines += [f"**{verdict}**", ""]
    if identified(reports):
        lines += [
            "The identified plants are in `tuned.toml`: add "
            '`include = ["<this directory>/tuned.toml"]` to the test\'s configuration.',
            "",
        ]
    for rep in reports:
        name = rep.name or "actuator"
        png = f"{name}.png"
        if draw:
            fig, axes = plt.subplots(1, 3, figsize=(15, 3.8), constrained_layout=True)
            if rep.latency.size:
                axes[0].hist(rep.latency * 1e3, bins=50, color="C0")
            axes[0].set_xlabel("round trip (ms), actuator disabled")
            axes[0].set_ylabel("replies")
            axes[0].set_title(f"{name}: latency at {plan.fs:g} Hz")
            for ax, trace, title in (
                (axes[1], rep.motion, "ramp–hold–ramp"),
                (axes[2], rep.chirp, "chirp and fitted model"),
            ):
                if trace is not None:
                    cmd, meas = trace
                    t = np.arange(cmd.size) / plan.fs
                    ax.plot(t, 1e3 * cmd, lw=1.0, label="command")
                    ax.plot(t, 1e3 * meas, lw=0.8, label="measured")
                    if ax is axes[2] and rep.plant is not None:
                        ax.plot(t, 1e3 * rep.plant.model, lw=0.8, ls="--", label="model")
                    ax.legend(loc="upper right")
                ax.set_xlabel("time (s)")
                ax.set_ylabel("displacement (mm)")
                ax.set_title(f"{name}: {title}")
            fig.savefig(out / png, dpi=90)
            plt.close(fig)
            rep.plot = png
        lines += [
            f"## {name} ({rep.driver}, {rep.target})",
            "",
            "| step | result | why | figures |",
            "|---|---|---|---|",
        ]
        for s in rep.steps:
            figs = ", ".join(f"{k} = {_fmt(v)}" for k, v in s.figures.items())
            lines.append(f"| {s.name} | {s.status} | {s.reason or '—'} | {figs or '—'} |")
        lines += ["", f"![{name}]({png})", ""] if draw else [""]
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)

"""Compensators compared on the same perturbed plants (``rths-hil study compensators``).

The robustness study's machinery (:mod:`rths_hil.studies`): perturbed twins are drawn once
(:func:`rths_hil.studies.plan_trials`), then every method runs on every draw, each trial in
lockstep through the full chain (:func:`rths_hil.studies.robustness_trial`: J1–J9 with the
paper's numbering and as the RTHS benchmark's script computes them, whole-record FEI A and d,
the online FEI extremes, trips). Outputs: ``trials.csv`` (one line per method × trial),
``comparison.csv`` and ``comparison.md`` (median, 5th and 95th percentiles per method and
criterion, per channel) and ``compensators_box.png`` (box plots per criterion, one colour per
method). See ``docs/compensation.md``.
"""

from __future__ import annotations

import copy
import csv
import math
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import studies as study
from ..compensators import compensator_class
from ..errors import InputError
from ..records.columns import column_name
from . import robustness as rob

__all__ = [
    "COMPARISON_METRICS",
    "CompensatorComparison",
    "compensator_study",
    "floors_trial",
    "plan_method_trials",
    "write_comparison",
]

#: Criteria compared per method (and per channel).
COMPARISON_METRICS: tuple[str, ...] = (
    "fei_amplitude",
    "fei_delay",
    *(f"J{i}" for i in range(1, 10)),
    *(f"bench_J{i}" for i in range(1, 10)),
)
#: Criteria drawn as box plots.
BOX_METRICS: tuple[str, ...] = ("fei_amplitude", "fei_delay", "J2", "bench_J1", "bench_J2", "J4")


def plan_method_trials(
    cfg,
    methods: Sequence[str],
    perturbations: Sequence[study.Perturbation],
    trials: int,
    seed: int = 0,
    duration: float | None = None,
) -> list[tuple[str, study.TrialSpec]]:
    """(method, trial) pairs: the same drawn plants for every method.

    The method is set on every channel (``compensation.method`` at the top level and in each
    ``[[actuators]]`` entry); every other compensation key stays as configured.
    """
    if not methods:
        raise InputError("--methods: no method given")
    for m in methods:
        try:
            compensator_class(m)
        except InputError as exc:
            raise InputError(f"--methods: {exc}") from None
    if len(set(methods)) != len(methods):
        raise InputError("--methods: a method is given more than once")
    base = study.inline_twin(cfg)
    specs = study.plan_trials(base, perturbations, trials, seed, None, duration)
    out = []
    for m in methods:
        for s in specs:
            c = copy.deepcopy(s.cfg)
            c["compensation"]["method"] = m
            c["compensation"]["enabled"] = True
            c["compensation"]["adaptive"] = c["compensation"]["adaptive"] and m == "inverse"
            for entry in c.get("actuators") or []:
                comp = entry.setdefault("compensation", {})
                comp["method"] = m
                comp["enabled"] = True
                if m != "inverse":
                    comp["adaptive"] = False
            out.append((m, replace(s, cfg=c)))
    return out


def method_trial(method: str, spec: study.TrialSpec) -> dict[str, Any]:
    """One trial of one method: the robustness trial's row with ``method`` first.

    A structure of several DOFs tested by one actuator on DOF 1 (the RTHS benchmark's
    partition) runs :func:`floors_trial`, which adds the upper floors' J5/J6/J8/J9 (paper) and
    J6–J9 (benchmark script); anything else runs :func:`rths_hil.studies.robustness_trial`.
    """
    row = floors_trial(spec) if _floors_case(spec.cfg) else study.robustness_trial(spec)
    return {"method": method, **row}


def _floors_case(cfg) -> bool:
    """One ``[[actuators]]`` entry on DOF 1 of a numerical structure given by matrices."""
    chans = cfg.get("actuators") or []
    if len(chans) != 1 or cfg["structure"]["kind"] not in ("matrices", "shear_building"):
        return False
    entry = chans[0]
    return "transform" not in entry and int(entry.get("dof", 1)) == 1


#: Reference responses of the drawn plants already run in this process, by trial key: the
#: reference (ideal actuator) does not depend on the compensator, so the methods of one draw
#: share it. Bounded (128 entries, 256 MB): the oldest entries go first.
_REFERENCES: dict[tuple[str, float | None], np.ndarray] = {}
_REFERENCES_MAX = 128
_REFERENCES_BYTES = 256e6


def _reference_floors(cfg, n: int, tmp: str, key: tuple[str, float | None]) -> np.ndarray:
    """(n, floors ≤ 3) displacements of the reference: the same test with an ideal actuator."""
    from ..records.recorder import read_run

    ref = _REFERENCES.get(key)
    if ref is None or ref.shape[0] < n:
        study.reference_by_loop(cfg, n, tmp)  # writes <tmp>/reference
        rec = read_run(Path(tmp) / "reference").record
        ref = _floor_columns(rec)
        _REFERENCES[key] = ref
        while len(_REFERENCES) > 1 and (
            len(_REFERENCES) > _REFERENCES_MAX
            or sum(r.nbytes for r in _REFERENCES.values()) > _REFERENCES_BYTES
        ):
            _REFERENCES.pop(next(iter(_REFERENCES)))
    return ref[:n]


def _reference_key(spec: study.TrialSpec) -> tuple[str, float | None]:
    """What the reference depends on: the trial's configuration without its compensation."""
    import hashlib
    import json

    c = copy.deepcopy(dict(spec.cfg))
    c.pop("compensation", None)
    for entry in c.get("actuators") or []:
        entry.pop("compensation", None)
    text = json.dumps(c, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest(), spec.duration


def _floor_columns(rec: np.ndarray) -> np.ndarray:
    """``u_1 … u_3`` of a record (floors above three are not judged by J1–J9)."""
    names = [f"u_{i}" for i in (1, 2, 3) if f"u_{i}" in (rec.dtype.names or ())]
    return np.column_stack([np.asarray(rec[c], dtype=float) for c in names])


def floors_trial(spec: study.TrialSpec) -> dict[str, Any]:
    """One lockstep trial of a one-actuator MDOF test, J1–J9 over all (≤ 3) floors.

    The row has the columns of :func:`rths_hil.studies.robustness_trial` (one channel). The
    reference (:func:`rths_hil.studies.reference_by_loop`: the same test with an ideal
    actuator) gives every floor, so the upper floors' criteria are computed too: the paper's
    J5, J6, J8, J9 and the benchmark script's J6–J9 (Silva et al. 2020,
    :func:`rths_hil.metrics.criteria` and :func:`rths_hil.metrics.benchmark_criteria` with the
    numerical floors ``u_1 … u_3``; ``u_1`` is the actuator's target).
    """
    import os
    import tempfile

    from ..fei import fei
    from ..hybrid import run
    from ..metrics import benchmark_criteria, criteria
    from ..records.recorder import read_run

    rob._sweep_dead_scratch()
    key = _reference_key(spec)
    scratch = tempfile.TemporaryDirectory(prefix=f"{rob._SCRATCH_PREFIX}{os.getpid()}-")
    with rob._TRIAL_LOCK, scratch as tmp:
        cfg = copy.deepcopy(spec.cfg)
        if spec.record is not None:
            path = Path(tmp) / Path(spec.record[0]).name
            path.write_bytes(spec.record[1])
            cfg["ground_motion"]["record"] = str(path)
        try:
            res = run(cfg, run_dir=Path(tmp) / "run", mode="lockstep", duration=spec.duration)
            rec = read_run(Path(tmp) / "run").record
            reference = _reference_floors(cfg, res.planned_steps, tmp, key)
        except InputError as exc:  # e.g. a drawn plant that is unstable
            return rob._invalid_row(spec, str(exc))
    fs = float(cfg["loop"]["fs"])
    comp = cfg["actuators"][0].get("compensation", {})
    alpha = comp.get("alpha", cfg["compensation"]["alpha"])
    row = rob._trial_row(spec, alpha, res)
    target = np.asarray(rec["target"], dtype=float)
    measured = np.asarray(rec["measured"], dtype=float)
    n = target.size
    floors = _floor_columns(rec)[:n]
    ref = reference[:n]
    nan = math.nan
    whole = fei(target, measured, fs) if n >= 8 else None
    row["fei_amplitude"] = whole.amplitude if whole is not None else nan
    row["fei_delay"] = whole.delay if whole is not None else nan
    row["fei_f_eq"] = whole.f_eq if whole is not None else nan
    valid = np.asarray(rec["fei_valid"], dtype=bool)
    a_lo, a_hi = rob._extremes(np.asarray(rec["fei_amplitude"], dtype=float), valid)
    d_lo, d_hi = rob._extremes(np.asarray(rec["fei_delay"], dtype=float), valid)
    row["mwo_amplitude_min"], row["mwo_amplitude_max"] = a_lo, a_hi
    row["mwo_delay_min"], row["mwo_delay_max"] = d_lo, d_hi
    ok = n >= study.BENCHMARK_MIN_STEPS
    num = np.column_stack([target, floors[:, 1:]])  # column 0: the actuator's target
    paper = criteria(num, measured, fs, ref) if ok else {}
    bench = benchmark_criteria(num, measured, fs, ref) if ok else {}
    for i in range(1, 10):
        row[f"J{i}"] = float(paper.get(f"J{i}", nan))
        row[f"bench_J{i}"] = float(bench.get(f"J{i}", nan))
    row["peak_target"] = float(np.max(np.abs(target))) if n else nan
    row["peak_reference"] = float(np.max(np.abs(ref[:, 0]))) if n else nan
    row["peak_force"] = float(np.max(np.abs(rec["force"]))) if n else nan
    return row


@dataclass
class CompensatorComparison(rob.TrialRows):
    """Outcome of :func:`compensator_study`: :class:`~rths_hil.studies.robustness.TrialRows`
    grouped by method.

    Attributes
    ----------
    methods : list of str
    """

    group_key = "method"
    metrics = COMPARISON_METRICS

    rows: list[dict[str, Any]]
    methods: list[str]
    keys: list[str]
    suffixes: list[str]
    seed: int

    @property
    def columns(self) -> list[str]:
        """``trials.csv`` columns in order."""
        return ["method", "trial", "alpha", *self.keys, *study.trial_columns(self.suffixes)]

    @property
    def groups(self) -> list[str]:
        """The methods."""
        return self.methods


def compensator_study(
    cfg,
    methods: Sequence[str],
    perturbations: Sequence[study.Perturbation] | None = None,
    trials: int = 100,
    *,
    seed: int = 0,
    duration: float | None = None,
    executor: Executor | None = None,
    progress: bool = True,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> CompensatorComparison:
    """Every method on the same ``trials`` perturbed plants (see the module docstring).

    ``on_row`` is called with each trial's row as it completes (e.g. to keep them on an
    operator stop).
    """
    base = study.inline_twin(cfg)
    perts = list(perturbations) if perturbations is not None else study.default_perturbations(base)
    cases = plan_method_trials(base, list(methods), perts, trials, seed, duration)
    rows = study.run_cases(
        method_trial,
        cases,
        executor,
        progress,
        "trials",
        None if on_row is None else (lambda _i, row: on_row(row)),
    )
    return CompensatorComparison(
        rows, list(methods), [p.key for p in perts], study.channel_suffixes(base), int(seed)
    )


def _md_table(res: CompensatorComparison) -> str:
    summ = res.summary()
    lines = []
    for ch in (sfx[1:] for sfx in res.suffixes):  # the channel of suffix ``_<ch>``
        if ch:
            lines += [f"### Channel {ch}", ""]
        head = ["criterion", *(f"{m} median" for m in res.methods)]
        head += [f"{m} 95 %" for m in res.methods]
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "---|" * len(head))
        for metric in COMPARISON_METRICS:
            cells = [f"`{metric}`"]
            by = {r["method"]: r for r in summ if r["metric"] == column_name(metric, ch)}
            scale = 1e3 if metric == "fei_delay" else 1.0
            cells += [f"{scale * by[m]['median']:.4g}" for m in res.methods]
            cells += [f"{scale * by[m]['p95']:.4g}" for m in res.methods]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    trip = {r["method"]: r["share_tripped"] for r in summ}
    n = {r["method"]: r["trials"] for r in summ}
    lines.append(
        "Trials stopped by a safety rule: "
        + ", ".join(f"{m} {100 * trip[m]:.1f} % of {n[m]}" for m in res.methods)
        + ". `fei_delay` in ms; J1 (paper) in s, `bench_J1` in ms (as the benchmark's script)."
    )
    return "\n".join(lines)


def write_comparison(
    out_dir: str | Path, res: CompensatorComparison, plot: bool = True
) -> list[str]:
    """Write trials.csv, comparison.csv, comparison.md and (``plot``) compensators_box.png."""
    out = Path(out_dir)
    study.write_trials_csv(out / "trials.csv", res)
    summ = res.summary()
    scols = ["method", "metric", "median", "p5", "p95", "n", "trials", "share_tripped"]
    with (out / "comparison.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(scols)
        for r in summ:
            w.writerow([study.exact_text(r[c]) for c in scols])
    n = len(res.rows) // max(1, len(res.methods))
    md = [
        "# Compensators on the same perturbed plants",
        "",
        f"{n} perturbed plants (seed {res.seed}; varied: {', '.join(res.keys) or 'none'}), "
        f"every method on each: median and 95th percentile of each criterion.",
        "",
        _md_table(res),
        "",
    ]
    (out / "comparison.md").write_text("\n".join(md), encoding="utf-8")
    written = ["trials.csv", "comparison.csv", "comparison.md"]
    if plot:
        written.append(_plot(out, res).name)
    return written


def _plot(out: Path, res: CompensatorComparison) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(m, sfx[1:]) for sfx in res.suffixes for m in BOX_METRICS]
    ncol = len(BOX_METRICS)
    nrow = len(res.suffixes)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.0 * ncol, 3.2 * nrow), squeeze=False)
    for ax, (metric, ch) in zip(axes.ravel(), panels, strict=True):
        scale = 1e3 if metric == "fei_delay" else 1.0
        col = column_name(metric, ch)
        data = []
        for m in res.methods:
            v = np.array([r.get(col, math.nan) for r in res.rows if r["method"] == m])
            data.append(scale * v[np.isfinite(v)])
        box = ax.boxplot(data, patch_artist=True, showfliers=True)
        for i, patch in enumerate(box["boxes"]):
            patch.set_facecolor(f"C{i}")
            patch.set_alpha(0.6)
        ax.set_xticks(range(1, len(res.methods) + 1), res.methods, rotation=30, fontsize=8)
        unit = " (ms)" if metric == "fei_delay" else ""
        ax.set_title(f"{metric}{unit}{' ' + ch if ch else ''}", fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    path = out / "compensators_box.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

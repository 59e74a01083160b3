"""Confusion matrix of ``rths-hil diagnose`` over generated records with hidden effects.

Each case is :func:`rths_hil.diagnose.synthetic.make_case`: an SDOF response to a bundled
ground motion drives a twin (delay + gain actuator, Kelvin-Voigt specimen, sensor noise) with
hidden effects of random size drawn from ``EFFECT_RANGES``; :func:`rths_hil.diagnose.diagnose`
gets only the record (time, command, measured, force) and the base model. Cases are seeded
(``--seed``), so the table is reproducible.

Sets (``--sets``, comma-separated):

* ``single``: ``--per`` cases of each catalogue effect and of no effect, model file given;
* ``pairs``: ``--pairs`` random pairs of different effects, model file given;
* ``nomodel``: ``--per-nomodel`` single-effect cases (all kinds and none), no model file (base
  fitted to the record);
* ``short``: offset and drift (``--per-short`` each) on records of ``--short-duration`` s;
* ``unreached``: stroke and velocity limits drawn without scaling the drive to reach them.

Usage::

    python benchmarks/confusion_diagnose.py --per 8 --jobs 2 --csv confusion.csv
    python benchmarks/confusion_diagnose.py --per 8 --scheduler tcp://host:8786   # a Dask cluster
"""

from __future__ import annotations

import argparse
import csv
import multiprocessing as mp
import sys
import time
from collections import Counter, defaultdict

import numpy as np
from _results import write_results
from rths_hil.sim_backends.effects import EFFECTS

from rths_hil.diagnose import CANDIDATES, diagnose
from rths_hil.diagnose.candidates import EFFECT_ORDER
from rths_hil.diagnose.synthetic import make_case
from rths_hil.errors import InputError
from rths_hil.metrics import j2_nrms

KINDS = list(EFFECTS)
#: The parameter that sizes each effect.
MAIN = {
    "offset": "offset",
    "drift": "rate",
    "backlash": "width",
    "velocity_limit": "limit",
    "stroke_limit": "limit",
    "servo_lag": "time_constant",
    "time_varying_delay": "amplitude",
    "force_feedback": "actuator_stiffness",
}


def _unreached_case(kind: str, seed: int, duration: float):
    """A stroke/velocity limit drawn from its range with the drive drawn independently."""
    rng = np.random.default_rng(seed)
    from rths_hil.sim_backends.effects import draw_effect_params

    params = draw_effect_params(kind, rng)
    return make_case([kind], seed, duration=duration, params={kind: params})


def run_case(job: tuple) -> dict:
    """Generate one case, diagnose it, score it."""
    set_name, kinds, seed, duration, with_model = job
    kinds = tuple(sorted(kinds, key=lambda k: EFFECT_ORDER[k]))  # the twin's order
    if set_name == "unreached":
        case = _unreached_case(kinds[0], seed, duration)
    else:
        case = make_case(list(kinds), seed, duration=duration)
    t0 = time.perf_counter()
    try:
        dx = diagnose(
            case.time,
            case.command,
            case.measured,
            case.force,
            model=case.base if with_model else None,
        )
    except InputError as exc:  # e.g. a record too short to decide: counted as refused
        return {
            "set": set_name,
            "seed": seed,
            "true": "+".join(kinds) if kinds else "none",
            "named": "refused",
            "first": "refused",
            "exact": False,
            "refused": str(exc),
            "duration_s": duration,
            "runtime_s": time.perf_counter() - t0,
        }
    runtime = time.perf_counter() - t0
    named = dx.names
    # a limit the drive never reaches leaves no trace: the right answer is then without it
    expected = [k for k in kinds if case.info["effect_rms"][k] > 0]
    truth_before = j2_nrms(case.truth, dx.base_pred) if case.hidden else 0.0
    truth_after = j2_nrms(case.truth, dx.pred) if case.hidden else 0.0
    rms = case.info["effect_rms"]
    rel = None
    if len(kinds) == 1 and named == list(kinds):
        h = case.hidden[0].params[MAIN[kinds[0]]]
        rel = abs(dx.steps[0].params[MAIN[kinds[0]]] - h) / abs(h)
    return {
        "set": set_name,
        "seed": seed,
        "true": "+".join(kinds) if kinds else "none",
        "named": "+".join(named) if named else "none",
        "first": named[0] if named else "none",
        "expected": "+".join(expected) if expected else "none",
        "exact": sorted(named) == sorted(expected),
        "gap_before": dx.before.j2,
        "gap_after": dx.after.j2,
        "halved": dx.after.j2 <= 0.5 * dx.before.j2,
        "truth_j2_before": truth_before,
        "truth_j2_after": truth_after,
        "truth_halved": (truth_after <= 0.5 * truth_before) if case.hidden else True,
        "alternatives": ";".join(",".join(s.alternatives) for s in dx.steps),
        "delta_bic": ";".join(f"{s.delta_bic:.4g}" for s in dx.steps),
        "param_rel_err": rel,
        "snr": min((rms[k] for k in kinds), default=0.0) / case.info["noise"],
        "noise_um": 1e6 * case.info["noise"],
        "fn": case.info["fn"],
        "peak_mm": 1e3 * case.info["peak"],
        "ground_motion": case.info["ground_motion"],
        "hidden": ";".join(f"{e.kind}:{e.params}" for e in case.hidden),
        "fitted": ";".join(f"{s.name}:{s.params}" for s in dx.steps),
        "runtime_s": runtime,
        "duration_s": duration,
    }


def jobs_for(args: argparse.Namespace) -> list[tuple]:  # noqa: C901
    rng = np.random.default_rng(args.seed)
    out = []
    sets = args.sets.split(",")

    def seed() -> int:
        return int(rng.integers(2**31))

    kinds = args.kinds.split(",") if args.kinds else ["none", *KINDS]
    if "single" in sets:
        for kind in kinds:
            for _ in range(args.per):
                out.append(
                    ("single", () if kind == "none" else (kind,), seed(), args.duration, True)
                )
    if "pairs" in sets:
        for _ in range(args.pairs):
            a, b = rng.choice(len(KINDS), 2, replace=False)
            out.append(("pairs", (KINDS[a], KINDS[b]), seed(), args.duration, True))
    if "nomodel" in sets:
        for kind in ["none", *KINDS]:
            for _ in range(args.per_nomodel):
                out.append(
                    ("nomodel", () if kind == "none" else (kind,), seed(), args.duration, False)
                )
    if "short" in sets:
        for kind in ("offset", "drift"):
            for _ in range(args.per_short):
                out.append(("short", (kind,), seed(), args.short_duration, True))
    if "unreached" in sets:
        for kind in ("stroke_limit", "velocity_limit"):
            for _ in range(args.per_unreached):
                out.append(("unreached", (kind,), seed(), args.duration, True))
    return out


def confusion_table(rows: list[dict], title: str) -> str:
    """Markdown true × first-named table, with exact-answer and gap-halving counts."""
    cols = ["none", *CANDIDATES, "refused"]
    trues = sorted({r["true"] for r in rows}, key=lambda k: (k != "none", k))
    order = {k: i for i, k in enumerate(["none", *KINDS])}
    trues.sort(key=lambda k: order.get(k, 99))
    counts: dict[str, Counter] = defaultdict(Counter)
    for r in rows:
        counts[r["true"]][r["first"]] += 1
    used = [c for c in cols if any(counts[t][c] for t in trues)]
    head = (
        "| true \\ named | "
        + " | ".join(used)
        + " | n | unreached | exact | +extra | J2 halved | truth J2 halved |"
    )
    sep = "|---" * (len(used) + 7) + "|"
    lines = [f"**{title}**", "", head, sep]
    for t in trues:
        rs = [r for r in rows if r["true"] == t]
        exact = sum(r["exact"] for r in rs)
        unreached = sum(r.get("expected", r["true"]) != r["true"] for r in rs)
        extra = sum(
            len(r["named"].split("+")) > len(t.split("+")) and r["named"] != "none" for r in rs
        )
        halved = sum(r.get("halved", False) for r in rs) if t != "none" else "–"
        th = sum(r.get("truth_halved", False) for r in rs) if t != "none" else "–"
        cells = [str(counts[t][c]) if counts[t][c] else "·" for c in used]
        lines.append(
            f"| {t} | "
            + " | ".join(cells)
            + f" | {len(rs)} | {unreached} | {exact} | {extra} | {halved} | {th} |"
        )
    return "\n".join(lines)


def pairs_table(rows: list[dict], title: str) -> str:
    """Markdown list of (hidden pair → named set) with counts."""
    counts = Counter((r["true"], r["named"], r["exact"]) for r in rows)
    lines = [f"**{title}**", "", "| hidden (twin order) | named | n | exact |", "|---|---|---|---|"]
    for (t, nm, ok), c in sorted(counts.items()):
        lines.append(f"| {t} | {nm} | {c} | {'yes' if ok else 'no'} |")
    exact = sum(r["exact"] for r in rows)
    halved = sum(r.get("truth_halved", False) for r in rows)
    lines += ["", f"{exact} of {len(rows)} exact; truth J2 halved in {halved} of {len(rows)}."]
    return "\n".join(lines)


def accuracy_table(rows: list[dict]) -> str:
    """Median and worst relative error of each effect's main parameter (correct cases)."""
    errs: dict[str, list[float]] = defaultdict(list)
    for r in rows:
        if r.get("param_rel_err") is not None and r["exact"]:
            errs[r["true"]].append(r["param_rel_err"])
    lines = ["| effect | parameter | median rel. error | worst |", "|---|---|---|---|"]
    for k in KINDS:
        if errs[k]:
            e = np.array(errs[k])
            lines.append(f"| {k} | {MAIN[k]} | {np.median(e):.2%} | {e.max():.2%} |")
    return "\n".join(lines)


def _without_csv(argv: list[str]) -> list[str]:
    """The arguments without ``--csv FILE`` (a local path: not part of the reproduction)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--csv":
            skip = True
        elif not a.startswith("--csv="):
            out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sets", default="single,pairs,nomodel,short,unreached")
    p.add_argument("--per", type=int, default=8, help="cases per effect kind (single)")
    p.add_argument("--kinds", help="comma-separated kinds for the single set (default: all)")
    p.add_argument("--pairs", type=int, default=16)
    p.add_argument("--per-nomodel", type=int, default=3)
    p.add_argument("--per-short", type=int, default=6)
    p.add_argument("--short-duration", type=float, default=6.0)
    p.add_argument("--per-unreached", type=int, default=4)
    p.add_argument("--duration", type=float, default=30.0, help="record length (s)")
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument(
        "--scheduler",
        metavar="local|ADDRESS",
        help="run the cases on Dask: 'local' (--jobs worker processes on 127.0.0.1, at least 2) "
        "or a scheduler address, e.g. tcp://host:8786",
    )
    p.add_argument("--csv", help="write every case here")
    args = p.parse_args(argv)
    jobs = jobs_for(args)
    print(f"{len(jobs)} cases, {args.jobs} process(es)", file=sys.stderr)
    t0 = time.perf_counter()
    rows = []
    if args.scheduler:
        from rths_hil.studies import open_executor

        with open_executor(args.scheduler, max(2, args.jobs)) as ex:
            for i, r in enumerate(ex.map(run_case, jobs), 1):
                rows.append(r)
                print(
                    f"{i:4d} {r['set']:9s} {r['true']:32s} → {r['named']:32s} "
                    f"{r['runtime_s']:.1f} s",
                    file=sys.stderr,
                    flush=True,
                )
    elif args.jobs > 1:
        with mp.get_context("fork").Pool(args.jobs) as pool:
            for i, r in enumerate(pool.imap(run_case, jobs), 1):
                rows.append(r)
                print(
                    f"{i:4d} {r['set']:9s} {r['true']:32s} → {r['named']:32s} "
                    f"{r['runtime_s']:.1f} s",
                    file=sys.stderr,
                    flush=True,
                )
    else:
        for i, job in enumerate(jobs, 1):
            r = run_case(job)
            rows.append(r)
            print(
                f"{i:4d} {r['set']:9s} {r['true']:32s} → {r['named']:32s} {r['runtime_s']:.1f} s",
                file=sys.stderr,
                flush=True,
            )
    wall = time.perf_counter() - t0
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            names = list(dict.fromkeys(k for r in rows for k in r))
            w = csv.DictWriter(fh, fieldnames=names)
            w.writeheader()
            w.writerows(rows)
    report: list[str] = []

    def emit(text: str = "") -> None:
        print(text)
        report.append(text)

    for set_name, title in (
        ("single", f"one hidden effect, model file given ({args.duration:g} s records)"),
        ("nomodel", "one hidden effect, no model file (delay + gain fitted to the record)"),
        ("short", f"short records ({args.short_duration:g} s)"),
        ("unreached", "limits drawn without scaling the drive to reach them"),
    ):
        rs = [r for r in rows if r["set"] == set_name]
        if rs:
            emit(confusion_table(rs, title))
            emit()
    rs = [r for r in rows if r["set"] == "pairs"]
    if rs:
        emit(pairs_table(rs, "two hidden effects, model file given"))
        emit()
    rs = [r for r in rows if r["set"] == "single"]
    if rs:
        emit("**parameter accuracy (single, correctly named)**\n")
        emit(accuracy_table(rs))
        emit()
    rt = np.array([r["runtime_s"] for r in rows if r["named"] != "refused"])
    emit(
        f"{len(rows)} cases in {wall:.0f} s wall; diagnose runtime median {np.median(rt):.2f} s, "
        f"max {rt.max():.2f} s per case"
    )
    misses = [r for r in rows if not r["exact"]]
    if misses:
        emit("\nnot exact:")
        for r in misses:
            if r["named"] == "refused":
                emit(f"- {r['set']} seed {r['seed']}: true {r['true']} → refused: {r['refused']}")
                continue
            emit(
                f"- {r['set']} seed {r['seed']}: true {r['true']} → {r['named']} "
                f"(alternatives {r['alternatives'] or '-'}, ΔBIC {r['delta_bic'] or '-'}, "
                f"SNR {r['snr']:.3g}, fn {r['fn']:.2f} Hz; hidden {r['hidden']}; "
                f"fitted {r['fitted']})"
            )
    write_results(
        "confusion_diagnose",
        "\n".join(report),
        title="Confusion matrix of the discrepancy diagnosis",
        command=" ".join(
            ["python benchmarks/confusion_diagnose.py", *_without_csv(argv or sys.argv[1:])]
        ),
        notes="Cases are seeded (`--seed`): the tables are reproducible; runtimes depend on the "
        "machine and its load.",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

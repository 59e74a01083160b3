"""Does the stability indicator see a runaway coming? Perturbed plants past the compensator's reach.

On the NEES-711 example (``examples/nees711/nees711.toml``: the SDOF Bouc-Wen frame, inverse
compensation α = 29 for the twin's 26.2 ms lag) and the RTHS benchmark example
(``examples/benchmark/benchmark.toml``: the 3-storey linear structure, the benchmark's plant,
inverse compensation of 23.7 ms), trials draw plants the compensator does not cover: an extra
transport delay of the actuator and a stiffer specimen (NEES-711: also a less damped one, down
to the nearly elastic specimen of the reproducible runaway case). Trial 0 of each example is the
example as it is (nominal plant).

Each trial runs in lockstep through the whole chain (structure → compensation → CAN twin →
evaluators → rules → record) with the displacement limit as the only stopping rule (the force,
velocity, FEI and Kalman rules off, ``safety.stability = "warn"``), so the run shows where the
displacement limit would stop it. From its record:

* **indicator**: the first step at which the loop's windowed ratio ``S`` (the ``stability``
  column, :mod:`rths_hil.stability`) exceeded ``safety.stability_warn`` (a ``stability``
  event) and ``safety.stability_limit`` (where ``"trip"`` would stop the test);
* **FEI rule**: where :class:`rths_hil.safety.FEIRule` with the example's tolerances
  (``safety.fei_delay_tol``, ``fei_amplitude_tol``, ``fei_consecutive``) would have tripped,
  fed the loop's streaming FEI windows (the ``fei_*`` columns) as the loop feeds it;
* **displacement limit**: the trip of the run.

Lead = time of the displacement limit − time of the rule. Goal: on every trial that runs away
(reaches the displacement limit) the indicator's limit fires before the displacement limit,
with a median lead ≥ 1 s; no stability trip on the nominal trials.

Usage: ``python benchmarks/bench_stability.py [--trials 14] [--duration 20] [--workers 2]``;
``--figure docs/img/stability_case.png`` draws the reproducible case and its bounded sibling
(displacement and S against time) for ``docs/stability.md`` instead
(about 3 minutes on two workers of a busy 2-core machine; deterministic: lockstep, seeded
draws and sensor noise).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import markdown_table, write_results  # noqa: E402

EXAMPLES: dict[str, Path | None] = {
    "default": None,  # the embedded default configuration (NEES-711 with El Centro)
    "NEES-711": ROOT / "examples" / "nees711" / "nees711.toml",
    "benchmark": ROOT / "examples" / "benchmark" / "benchmark.toml",
}
#: Fixed trials of the default test after its nominal one: the reproducible runaway (no
#: compensation, a stiff and nearly elastic specimen) and its bounded sibling.
FIXED = {
    "default": [
        {"delay": 0.0, "stiffness": 3e7, "damping": 114.6, "compensation": False},
        {"delay": 0.0, "stiffness": 1.2e7, "damping": 114.6, "compensation": False},
    ]
}
#: Overrides of every trial: the displacement limit is the only stopping rule; the indicator
#: warns (its events and column are what the table reads); no exact FEI, no Kalman (speed).
COMMON = {
    "safety.fei_delay_tol": 0,
    "safety.fei_amplitude_tol": 0,
    "safety.force_limit": 0,
    "safety.velocity_limit": 0,
    "safety.kf_delay_max": 0,
    "safety.stability": "warn",
    "kalman.enabled": False,
    "fei.exact_hop": 0,
}


def draw(example: str, n: int, seed: int) -> list[dict]:
    """The trials of ``example``: trial 0 nominal, then ``n − 1`` drawn plants."""
    rng = np.random.default_rng(seed)
    nan = math.nan
    trials: list[dict] = [{"delay": 0.0, "stiffness": nan, "damping": nan}]
    trials += FIXED.get(example, [])
    while len(trials) < n:
        if example in ("default", "NEES-711"):
            trials.append(
                {
                    "delay": float(rng.uniform(0.0, 0.040)),
                    "stiffness": float(np.exp(rng.uniform(np.log(1.19e6), np.log(3e7)))),
                    "damping": float(np.exp(rng.uniform(np.log(114.6), np.log(2.46e5)))),
                }
            )
        else:
            trials.append(
                {
                    "delay": float(rng.uniform(0.0, 0.020)),
                    "stiffness": float(rng.uniform(1.19e6, 3.0e6)),
                    "damping": nan,
                }
            )
    return trials


def _overrides(example: str, trial: dict) -> dict:
    ov = dict(COMMON)
    if trial["delay"] > 0:
        ov["twin.actuator.delay"] = trial["delay"]
    if not math.isnan(trial["stiffness"]):
        ov["twin.specimen.stiffness"] = trial["stiffness"]
        ov["structure.k_specimen"] = trial["stiffness"]
    if not math.isnan(trial["damping"]):
        ov["twin.specimen.damping"] = trial["damping"]
    if not trial.get("compensation", True):
        ov["compensation.enabled"] = False
    return ov


def _first(mask: np.ndarray, t: np.ndarray) -> float:
    i = np.flatnonzero(mask)
    return float(t[i[0]]) if len(i) else math.nan


def run_trial(args: tuple[str, int, dict, float]) -> dict:
    """One trial: run it, read its record and events, time each rule."""
    import rths_hil
    from rths_hil.safety import FEIRule

    example, index, trial, duration = args
    path = EXAMPLES[example]
    cfg = rths_hil.configure(path, _overrides(example, trial))
    base = rths_hil.configure(path)  # the example's own FEI rule and stability levels
    sb = base["safety"]
    with tempfile.TemporaryDirectory(prefix="bench-stab-") as tmp:
        t0 = time.perf_counter()
        res = rths_hil.run(
            cfg, mode="lockstep", duration=duration, run_dir=Path(tmp) / "run", summary=False
        )
        wall = time.perf_counter() - t0
        run = rths_hil.open_run(res.run_dir)
        rec = run.record
        t = rec["time"]
        s = rec["stability"]
        warn_level = float(cfg["safety"]["stability_warn"])
        limit = float(cfg["safety"]["stability_limit"])
        events = [e for e in run.events if e.get("kind") == "stability"]
        fei = FEIRule(
            sb["fei_amplitude_tol"] or math.inf,
            sb["fei_delay_tol"] or math.inf,
            sb["fei_consecutive"],
        )
        warm = round(float(sb["warmup"]) * run.fs)
        fei_t = math.nan
        a, d, v = rec["fei_amplitude"], rec["fei_delay"], rec["fei_valid"]
        for k in range(warm, len(t)):
            if fei.check(float(a[k]), float(d[k]), bool(v[k])) is not None:
                fei_t = float(t[k])
                break
        ok = np.isfinite(s)
        disp_t = (
            float(res.trip.time)
            if res.trip is not None and res.trip.rule == "displacement"
            else math.nan
        )
        return {
            "example": example,
            "trial": index,
            **trial,
            "status": res.status,
            "end": float(t[-1]) if len(t) else 0.0,
            "s_median": float(np.median(s[ok])) if ok.any() else math.nan,
            "s_peak": float(np.max(s[ok])) if ok.any() else math.nan,
            "warn": _first(ok & (s > warn_level), t),
            "warn_event": float(events[0]["time"]) if events else math.nan,
            "limit": _first(ok & (s > limit), t),
            "fei": fei_t,
            "displacement": disp_t,
            "peak_mm": float(np.max(np.abs(rec["target"]))) * 1e3,
            "wall": wall,
        }


def figure(path: Path, duration: float = 12.0) -> Path:
    """The reproducible case and its bounded sibling: displacement and S against time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import rths_hil
    from rths_hil.plotting import save_figure

    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 6), sharex=True, constrained_layout=True)
    for i, (trial, color) in enumerate(zip(FIXED["default"], ("C3", "C0"), strict=True)):
        label = f"{trial['stiffness'] / 1e6:g} MN/m"
        cfg = rths_hil.configure(None, _overrides("default", trial))
        with tempfile.TemporaryDirectory(prefix="bench-stab-") as tmp:
            res = rths_hil.run(
                cfg, mode="lockstep", duration=duration, run_dir=Path(tmp) / "r", summary=False
            )
            rec = rths_hil.open_run(res.run_dir).record
        t = rec["time"]
        ax.plot(t, rec["target"] * 1e3, lw=0.8, color=color, label=label)
        bx.plot(t, rec["stability"], lw=1.2, color=color, label=label)
        limit = float(cfg["safety"]["stability_limit"])
        hit = np.flatnonzero(rec["stability"] > limit)
        if len(hit):
            bx.axvline(t[hit[0]], color=color, lw=0.8, ls=":")
            ax.axvline(t[hit[0]], color=color, lw=0.8, ls=":")
        if res.trip is not None and res.trip.rule == "displacement":
            ax.axvline(res.trip.time, color=color, lw=1.2)
            ax.annotate(
                f"displacement limit {res.trip.time:.2f} s",
                (res.trip.time, 45),
                xytext=(-4, 0),
                textcoords="offset points",
                ha="right",
                fontsize=8,
                color=color,
            )
        if len(hit):
            bx.annotate(
                f"S > {limit:g} at {t[hit[0]]:.2f} s",
                (t[hit[0]], limit),
                xytext=(4, 4 + 12 * i),
                textcoords="offset points",
                fontsize=8,
                color=color,
            )
    lim = 0.05
    ax.axhline(lim * 1e3, color="0.4", lw=0.6, ls="--")
    ax.axhline(-lim * 1e3, color="0.4", lw=0.6, ls="--")
    ax.set_ylabel("target (mm)")
    ax.set_title(
        "default test, no compensation, nearly elastic specimen: the runaway and its bounded "
        "sibling"
    )
    ax.legend(loc="upper left", fontsize=8)
    bx.axhline(1.0, color="0.4", lw=0.6, ls="--")
    bx.axhline(1.5, color="0.2", lw=0.8)
    bx.set_ylabel("stability indicator S")
    bx.set_xlabel("time (s)")
    bx.set_title("S (valid after a whole 3.9 s window of motion); dashed: warning, solid: limit")
    bx.legend(loc="upper left", fontsize=8)
    save_figure(fig, path, 90)
    plt.close(fig)
    return path


def _ms(x: float) -> str:
    return "—" if math.isnan(x) else f"{x * 1e3:.1f}"


def _s(x: float) -> str:
    return "—" if math.isnan(x) else f"{x:.2f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=14, help="trials per example (with the nominal)")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of record per trial")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--figure", type=Path, help="write the reproducible case's figure and stop")
    args = ap.parse_args(argv)
    if args.figure:
        print(f"wrote {figure(args.figure)}")
        return 0

    jobs = [
        (ex, i, tr, args.duration)
        for ex in EXAMPLES
        for i, tr in enumerate(draw(ex, args.trials, args.seed))
    ]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(run_trial, jobs))
    wall = time.perf_counter() - t0

    head = [
        "example",
        "trial",
        "extra delay (ms)",
        "k_e (MN/m)",
        "c_e (kN·s/m)",
        "S median",
        "S peak",
        "warn (s)",
        "limit (s)",
        "FEI rule (s)",
        "displacement limit (s)",
        "lead S (s)",
        "lead FEI (s)",
        "peak (mm)",
    ]
    body = []
    for r in rows:
        body.append(
            [
                r["example"],
                str(r["trial"]),
                _ms(r["delay"]) + ("" if r.get("compensation", True) else ", no comp."),
                "nominal" if math.isnan(r["stiffness"]) else f"{r['stiffness'] / 1e6:.2f}",
                "—" if math.isnan(r["damping"]) else f"{r['damping'] / 1e3:.3g}",
                _s(r["s_median"]),
                _s(r["s_peak"]),
                _s(r["warn"]),
                _s(r["limit"]),
                _s(r["fei"]),
                _s(r["displacement"]),
                _s(r["displacement"] - r["limit"]),
                _s(r["displacement"] - r["fei"]),
                f"{r['peak_mm']:.1f}",
            ]
        )
    table = markdown_table(head, body)

    lines = []
    for ex in EXAMPLES:
        rs = [r for r in rows if r["example"] == ex]
        run_away = [r for r in rs if not math.isnan(r["displacement"])]
        bounded = [r for r in rs if math.isnan(r["displacement"])]
        before = [r for r in run_away if r["limit"] < r["displacement"]]
        fei_before = [r for r in run_away if r["fei"] < r["displacement"]]
        leads = [r["displacement"] - r["limit"] for r in before]
        fei_leads = [r["displacement"] - r["fei"] for r in fei_before]
        nominal = rs[0]
        lines.append(
            [
                ex,
                str(len(rs)),
                str(len(run_away)),
                f"{len(before)} / {len(run_away)}",
                _s(float(np.median(leads))) if leads else "—",
                f"{len(fei_before)} / {len(run_away)}",
                _s(float(np.median(fei_leads))) if fei_leads else "—",
                str(sum(1 for r in bounded if not math.isnan(r["limit"]))),
                str(sum(1 for r in bounded if not math.isnan(r["warn"]))),
                "yes" if math.isnan(nominal["warn"]) else f"no (S {nominal['s_peak']:.2f})",
            ]
        )
    away = [r for r in rows if not math.isnan(r["displacement"])]
    caught = [r for r in away if r["limit"] < r["displacement"]]
    fei_caught = [r for r in away if r["fei"] < r["displacement"]]
    nominal_ok = all(math.isnan(r["warn"]) for r in rows if r["trial"] == 0)
    lines.append(
        [
            "**all**",
            str(len(rows)),
            str(len(away)),
            f"{len(caught)} / {len(away)}",
            _s(float(np.median([r["displacement"] - r["limit"] for r in caught])))
            if caught
            else "—",
            f"{len(fei_caught)} / {len(away)}",
            _s(float(np.median([r["displacement"] - r["fei"] for r in fei_caught])))
            if fei_caught
            else "—",
            str(sum(1 for r in rows if math.isnan(r["displacement"]) and r["limit"] == r["limit"])),
            str(sum(1 for r in rows if math.isnan(r["displacement"]) and r["warn"] == r["warn"])),
            "yes" if nominal_ok else "no",
        ]
    )
    summary = markdown_table(
        [
            "example",
            "trials",
            "ran away",
            "S limit before the displacement limit",
            "median lead S (s)",
            "FEI rule before",
            "median lead FEI (s)",
            "bounded trials over the S limit",
            "bounded trials over the S warning",
            "nominal: no warning",
        ],
        lines,
    )
    agree = [
        r
        for r in rows
        if not (math.isnan(r["warn"]) and math.isnan(r["warn_event"]))
        and not math.isclose(r["warn"], r["warn_event"], abs_tol=1e-9)
    ]
    text = (
        "## Summary\n\n"
        + summary
        + "\n\n## Trials\n\n"
        + table
        + f"\n\n{len(rows)} trials of {args.duration:g} s in {wall:.0f} s on {args.workers} "
        f"workers; the `stability` events agree with the column on "
        f"{len(rows) - len(agree)} of {len(rows)} trials.\n"
    )
    print(text)
    if not args.no_write:
        path = write_results(
            "bench_stability",
            text,
            title="Stability indicator on perturbed plants",
            goals="On every trial that runs away, the indicator's limit fires before the "
            "displacement limit, with a median lead ≥ 1 s; no stability trip (nor warning) on "
            "the nominal trials.",
            command=f"python benchmarks/bench_stability.py --trials {args.trials} "
            f"--duration {args.duration:g} --seed {args.seed}",
            notes="Lockstep, so deterministic. Levels are the configuration's defaults "
            "(`safety.stability_warn`, `safety.stability_limit`, window `stability_window`). "
            "'Bounded' trials did not reach the displacement limit in the trial's duration. On "
            "the default test and NEES-711 those over the S limit are held by the yielding of "
            "the frame (a limit cycle fed by the interface, docs/stability.md); the benchmark's "
            "structure is linear, and its one such trial (12) reaches the displacement limit at "
            "20.10 s of the whole record, just past the trial.",
        )
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

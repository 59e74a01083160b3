"""Runtime of ``rths-hil diagnose`` on a 60 s record at 1024 Hz (goal: < 30 s on 2 cores).

Measured in one run, on records from :func:`rths_hil.diagnose.synthetic.make_case` (61 440
samples, SDOF response to a bundled ground motion, twin with hidden effects and sensor noise):

* the workflow as shipped (:func:`rths_hil.diagnose.diagnose`), with the model file and without
  (base fitted to the record), one and two hidden effects, then writing the report, model file
  and PNG;
* one screening (every candidate fitted once on the base model) as shipped;
* the naive reference for that screening: every candidate fitted by a generic optimiser
  (:func:`scipy.optimize.minimize`, Nelder-Mead from the middle of its realistic range,
  ``--naive-maxfev`` evaluations) on the step path (the twin's per-sample ``step`` of the
  actuator and of each effect, as a Python loop).

Usage::

    python benchmarks/bench_diagnose.py [--naive-maxfev 60] [--skip-naive] [--png FILE]
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import time

import numpy as np
from _results import markdown_table, write_results
from rths_hil.sim_backends.effects import EFFECT_RANGES, make_effect
from rths_hil.sim_backends.models import make_model
from scipy import optimize

from rths_hil.diagnose import CANDIDATES, diagnose, write_outputs
from rths_hil.diagnose.candidates import Data, Model, fit_candidate, specimen_from_record
from rths_hil.diagnose.synthetic import make_case
from rths_hil.errors import InputError

FS = 1024.0
DURATION = 60.0


def _step_path(spec, effects, command, dt):
    """Prediction by stepping the actuator model and each effect sample by sample."""
    a = spec.actuator
    act = make_model(a.model, dt, delay=a.delay, gain=a.gain, **a.params)
    chain = [make_effect(e.kind, dt, **e.params) for e in effects]
    act.reset()
    out = np.empty(len(command))
    for i, c in enumerate(command.tolist()):
        x = act.step(c)
        for e in chain:
            x = e.step(x)
        out[i] = x
    return out


def naive_screening(case, maxfev: int) -> tuple[float, dict[str, float]]:
    """Every candidate fitted by Nelder-Mead on the step path; returns (seconds, RSS by name)."""
    dt = 1.0 / FS
    y = case.measured
    base = case.base
    k_s, c_s = case.info["specimen_stiffness"], case.info["specimen_damping"]
    out = {}
    t0 = time.perf_counter()
    for name in CANDIDATES:
        if name in ("delay", "gain"):
            v0 = [base.actuator.delay if name == "delay" else base.actuator.gain]

            def rss(v, name=name):
                spec = _with(base, **{name: float(v[0])})
                r = y - _step_path(spec, [], case.command, dt)
                return float(r @ r)

        else:
            ranges = EFFECT_RANGES[name]
            free = [
                p for p in ranges if not (name == "force_feedback" and p != "actuator_stiffness")
            ]
            v0 = [
                math.sqrt(ranges[p].low * ranges[p].high)
                if ranges[p].low > 0
                else 0.5 * ranges[p].high
                for p in free
            ]

            def rss(v, name=name, free=free):
                params = dict(zip(free, (float(x) for x in v), strict=True))
                if name == "force_feedback":
                    params.update(specimen_stiffness=k_s, specimen_damping=c_s)
                try:
                    eff = _Eff(name, params)
                    r = y - _step_path(base, [eff], case.command, dt)
                except InputError:  # an invalid trial point (e.g. a negative width)
                    return 1e9
                return float(r @ r)

        res = optimize.minimize(rss, v0, method="Nelder-Mead", options={"maxfev": maxfev})
        out[name] = float(res.fun)
    return time.perf_counter() - t0, out


class _Eff:
    def __init__(self, kind, params):
        self.kind, self.params = kind, params
        make_effect(kind, 1.0 / FS, **params)  # validate


def _with(spec, **actuator):
    import copy

    s = copy.deepcopy(spec)
    for k, v in actuator.items():
        setattr(s.actuator, k, v)
    return s


def shipped_screening(case) -> tuple[float, dict[str, float]]:
    d = Data(case.command, case.measured, FS, case.force)
    m = Model(case.base, d)
    d.specimen = specimen_from_record(d, case.base)
    t0 = time.perf_counter()
    out = {}
    for name in CANDIDATES:
        f = fit_candidate(name, m, d)
        out[name] = getattr(f, "rss", float("nan"))
    return time.perf_counter() - t0, out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--naive-maxfev", type=int, default=60)
    p.add_argument("--skip-naive", action="store_true")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--png", help="also write the figure of the two-effect case here")
    args = p.parse_args(argv)
    print(f"record: {DURATION:g} s at {FS:g} Hz ({int(DURATION * FS)} samples)")
    rows = []
    for kinds, with_model in (
        (["backlash"], True),
        (["backlash"], False),
        (["servo_lag", "velocity_limit"], True),
        (["servo_lag", "velocity_limit"], False),
        ([], True),
    ):
        case = make_case(kinds, args.seed, duration=DURATION, fs=FS)
        t0 = time.perf_counter()
        dx = diagnose(
            case.time,
            case.command,
            case.measured,
            case.force,
            model=case.base if with_model else None,
        )
        t_dx = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            paths = write_outputs(dx, tmp, record="bench.csv")
            t_out = time.perf_counter() - t0
            if args.png and len(kinds) == 2 and with_model:
                shutil.copy(paths["plot"], args.png)
        label = f"{'+'.join(kinds) or 'none'} ({'model file' if with_model else 'no model'})"
        rows.append((label, dx.answer, t_dx, t_out))
        print(
            f"{label:45s} → {dx.answer:28s} diagnose {t_dx:6.2f} s, "
            f"report+model+PNG {t_out:5.2f} s, total {t_dx + t_out:6.2f} s",
            flush=True,
        )
    worst = max(r[2] + r[3] for r in rows)
    print(f"worst total {worst:.2f} s (goal < 30 s)")
    case = make_case(["backlash"], args.seed, duration=DURATION, fs=FS)
    t_ship, rss_ship = shipped_screening(case)
    print(f"one screening of the {len(CANDIDATES)} candidates, as shipped: {t_ship:.2f} s")
    lines = [
        markdown_table(
            ["record", "answer", "diagnose (s)", "report + model + PNG (s)", "total (s)"],
            [
                [label, f"`{answer}`", f"{t_dx:.2f}", f"{t_out:.2f}", f"{t_dx + t_out:.2f}"]
                for label, answer, t_dx, t_out in rows
            ],
        ),
        "",
        f"Worst total {worst:.2f} s (goal < 30 s). One screening of the {len(CANDIDATES)} "
        f"candidates on the base model, as shipped: {t_ship:.2f} s.",
    ]
    if not args.skip_naive:
        t_naive, rss_naive = naive_screening(case, args.naive_maxfev)
        best_ship = min(rss_ship, key=rss_ship.get)
        best_naive = min(rss_naive, key=rss_naive.get)
        print(
            f"naive reference (Nelder-Mead, {args.naive_maxfev} evaluations per candidate, "
            f"step path): {t_naive:.1f} s ({t_naive / t_ship:.0f}× slower); best candidate "
            f"{best_naive} (shipped: {best_ship}); RSS of the best "
            f"{rss_naive[best_naive]:.4g} vs {rss_ship[best_ship]:.4g} m²"
        )
        lines.append(
            f"Naive reference (Nelder-Mead, {args.naive_maxfev} evaluations per candidate, on the "
            f"step path): {t_naive:.1f} s, {t_naive / t_ship:.0f}× the shipped screening; its best "
            f"candidate `{best_naive}` (shipped: `{best_ship}`), RSS of the best "
            f"{rss_naive[best_naive]:.4g} m² vs {rss_ship[best_ship]:.4g} m²."
        )
    write_results(
        "bench_diagnose",
        "\n".join(lines),
        title="Runtime of the discrepancy diagnosis",
        goals="A 60 s record at 1024 Hz diagnosed, with report, model file and PNG, in < 30 s.",
        command="python benchmarks/bench_diagnose.py"
        + (" --skip-naive" if args.skip_naive else f" --naive-maxfev {args.naive_maxfev}")
        + f" --seed {args.seed}",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Cost of the twin models, the effects catalogue and the Kalman delay/gain estimator.

Measured in one run, each beside a naive reference:

1. Kalman per-sample cost of :class:`rths_hil.estimation.DelayGainEstimator` (3-state EKF,
   ``backend="fast"``) vs the same filter on filterpy's ExtendedKalmanFilter
   (``backend="filterpy"``) and the linear first-order-regression KF on filterpy's
   KalmanFilter. Goal: well below 100 µs per sample (a 1024 Hz step is 977 µs).
2. Per-step cost of the benchmark plant (5-state discrete state space, preallocated
   ``np.dot(out=)``) vs the obvious ``x = A @ x + B * u`` (allocating), and of a full
   TwinPlant (benchmark model + backlash + offset + specimen + noise + quantisation).
3. Vectorised ``simulate`` of every catalogue effect on a 60 s record at 1024 Hz (61 440
   samples; the diagnosis workflow evaluates these thousands of times) vs stepping the same
   effect sample by sample in Python.

Run: ``.venv/bin/python benchmarks/bench_models.py``
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _results import markdown_table, write_results
from rths_hil.sim_backends.effects import EFFECTS, make_effect
from rths_hil.sim_backends.modelfile import load_plant
from rths_hil.sim_backends.models import BenchmarkServo
from scipy import signal

from rths_hil.estimation import DelayGainEstimator, LinearDelayGainKF

FS = 1024.0
DT = 1.0 / FS
DATA = Path(__file__).resolve().parents[1] / "rths_hil" / "data" / "ground_motions"

#: Representative parameters (mid-range of EFFECT_RANGES) for the effect timings.
EFFECT_PARAMS = {
    "offset": {"offset": 5e-4},
    "drift": {"rate": 2e-3 / 60},
    "backlash": {"width": 2e-4},
    "velocity_limit": {"limit": 0.05},
    "stroke_limit": {"limit": 0.015},
    "servo_lag": {"time_constant": 0.008},
    "time_varying_delay": {"delay": 0.015, "amplitude": 0.003, "period": 10.0},
    "force_feedback": {
        "actuator_stiffness": 5e7,
        "specimen_stiffness": 1e6,
        "specimen_damping": 5e4,
    },
}


def sdof_record(duration: float = 60.0, fn: float = 1.0, peak: float = 0.02) -> np.ndarray:
    """SDOF (fn, 2 %) response to El Centro, repeated to ``duration`` s, peak ``peak`` m."""
    d = np.loadtxt(DATA / "el_centro_1940_NS_chopra_0p02.csv", delimiter=",", skiprows=1)
    t = np.arange(0.0, d[-1, 0], DT)
    ag = np.interp(t, d[:, 0], d[:, 1] * 9.80665)
    w = 2 * np.pi * fn
    _, x, _ = signal.lsim(([-1.0], [1.0, 2 * 0.02 * w, w * w]), ag, t)
    n = int(duration * FS)
    x = np.resize(x, n)
    return x * peak / np.max(np.abs(x))


def best_of(fn: Callable[[], object], repeat: int = 5) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_kalman(u: np.ndarray, y: np.ndarray) -> str:
    n = len(u)
    rows = []
    for label, make in (
        ("EKF fast (default)", lambda: DelayGainEstimator(FS)),
        (
            "EKF on filterpy ExtendedKalmanFilter",
            lambda: DelayGainEstimator(FS, backend="filterpy"),
        ),
        ("linear KF on filterpy KalmanFilter", lambda: LinearDelayGainKF(FS)),
    ):
        per = best_of(lambda make=make: make().run(u, y), repeat=3) / n
        rows.append((label, per))
    print(f"\n1. Kalman delay/gain estimator, per sample ({n} samples, best of 3)")
    for label, per in rows:
        print(f"   {label:40s} {per * 1e6:8.1f} µs  ({100 * per * FS:5.2f} % of a 1024 Hz step)")
    print(f"   speed-up of the fast path over filterpy: {rows[1][1] / rows[0][1]:.1f}x")
    table = markdown_table(
        ["estimator", "µs per sample", "% of a 1024 Hz step"],
        [[label, f"{per * 1e6:.1f}", f"{100 * per * FS:.2f}"] for label, per in rows],
    )
    return (
        f"### Kalman delay/gain estimator, per sample ({n} samples, best of 3)\n\n{table}\n\n"
        f"Fast path over filterpy's EKF: {rows[1][1] / rows[0][1]:.1f}×."
    )


def bench_plant(u: np.ndarray) -> str:
    n = 20000
    cmd = u[:n].tolist()
    m = BenchmarkServo(DT)

    def ours() -> None:
        m.reset()
        step = m.step
        for c in cmd:
            step(c)

    a, b, c_, d = m.A, m.B[:, 0], m.C[0], float(m.D[0, 0])

    def naive() -> None:
        x = np.zeros(m.order)
        for c in cmd:
            float(c_ @ x + d * c)
            x = a @ x + b * c

    plant = load_plant(
        {
            "actuator": {
                "model": "benchmark",
                "delay": 0.002,
                "effects": [
                    {"kind": "backlash", "width": 2e-4},
                    {"kind": "offset", "offset": 5e-4},
                ],
            },
            "sensor": {
                "displacement_noise": 1.6e-5,
                "force_noise": 2.0,
                "displacement_resolution": 1e-6,
                "force_resolution": 0.1,
            },
        },
        DT,
    )

    def twin() -> None:
        plant.reset()
        step = plant.step
        for c in cmd:
            step(c)

    print(f"\n2. Plant step ({n} steps, best of 5)")
    t_ours = best_of(ours) / n
    t_naive = best_of(naive) / n
    t_twin = best_of(twin) / n
    print(f"   benchmark servo, preallocated np.dot(out=)   {t_ours * 1e6:8.2f} µs/step")
    print(f"   benchmark servo, naive x = A @ x + B * u      {t_naive * 1e6:8.2f} µs/step")
    print(
        f"   TwinPlant (benchmark+backlash+offset+specimen+noise+quantisation) "
        f"{t_twin * 1e6:6.2f} µs/step"
    )
    t_vec = best_of(lambda: plant.simulate(u))
    print(
        f"   TwinPlant.simulate, 60 s record               {t_vec * 1e3:8.2f} ms "
        f"({t_vec / len(u) * 1e6:.3f} µs/sample)"
    )
    table = markdown_table(
        ["path", "cost"],
        [
            ["benchmark servo step, preallocated `np.dot(out=)`", f"{t_ours * 1e6:.2f} µs"],
            ["benchmark servo step, naive `x = A @ x + B * u`", f"{t_naive * 1e6:.2f} µs"],
            [
                "TwinPlant step (benchmark + backlash + offset + specimen + noise + quantisation)",
                f"{t_twin * 1e6:.2f} µs",
            ],
            [
                "TwinPlant.simulate, 60 s record",
                f"{t_vec * 1e3:.2f} ms ({t_vec / len(u) * 1e6:.3f} µs/sample)",
            ],
        ],
    )
    return f"### Plant step ({n} steps, best of 5)\n\n{table}"


def bench_effects(u: np.ndarray) -> str:
    print(f"\n3. Effects on a 60 s record at 1024 Hz ({len(u)} samples), best of 5")
    print(f"   {'effect':20s} {'simulate':>12s} {'step loop':>12s} {'speed-up':>9s}  max |diff|")
    xs = u.tolist()
    rows = []
    for kind in EFFECTS:
        eff = make_effect(kind, DT, **EFFECT_PARAMS[kind])
        t_vec = best_of(lambda eff=eff: eff.simulate(u))

        def loop(eff=eff) -> np.ndarray:
            eff.reset()
            step = eff.step
            return np.array([step(v) for v in xs])

        t_loop = best_of(loop, repeat=3)
        diff = float(np.max(np.abs(eff.simulate(u) - loop())))
        print(
            f"   {kind:20s} {t_vec * 1e3:9.2f} ms {t_loop * 1e3:9.1f} ms {t_loop / t_vec:8.1f}x"
            f"  {diff:.1e}"
        )
        rows.append(
            [
                kind,
                f"{t_vec * 1e3:.2f}",
                f"{t_loop * 1e3:.1f}",
                f"{t_loop / t_vec:.1f}×",
                f"{diff:.1e}",
            ]
        )
    table = markdown_table(
        ["effect", "simulate (ms)", "step loop (ms)", "speed-up", "max abs diff (m)"], rows
    )
    return f"### Effects on a 60 s record at 1024 Hz ({len(u)} samples), best of 5\n\n{table}"


def main() -> None:
    u = sdof_record()
    y = load_plant(
        {
            "actuator": {"delay": 0.012, "gain": 0.97},
            "sensor": {"displacement_noise": 2e-5, "displacement_resolution": 1e-6},
        },
        DT,
    ).simulate(u)[0]
    print("bench_models: twin models, effects catalogue, Kalman estimator")
    sections = [
        bench_kalman(u[: int(20 * FS)], y[: int(20 * FS)]),
        bench_plant(u),
        bench_effects(u),
    ]
    write_results(
        "bench_models",
        "\n\n".join(sections),
        title="Twin models, effects catalogue and Kalman estimator",
        goals="Kalman estimator well below 100 µs per sample (a 1024 Hz step is 977 µs); "
        "each effect's vectorised `simulate` equal to stepping it (max abs diff at round-off).",
    )


if __name__ == "__main__":
    main()

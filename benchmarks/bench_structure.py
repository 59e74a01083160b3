"""Cost of one SDOF integrator step and of a 60 s record at 1024 Hz (rths_hil.structure).

Goal (issue 3): ≤ 20 µs per CR step of an SDOF with Bouc-Wen, i.e. ≤ 2 % of a 1024 Hz step.
References measured in the same run: a naive Newmark written the obvious way (numpy scalars,
lists grown by append, Bouc-Wen by explicit Euler sub-steps) and scipy.integrate.solve_ivp (RK45
on the state [x, v, z] with linear interpolation of the ground motion).

Run: ``.venv/bin/python benchmarks/bench_structure.py``
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.integrate import solve_ivp

from rths_hil.groundmotion import default_record
from rths_hil.structure import BoucWenParams, CRStepper, NewmarkStepper, simulate_sdof

FS = 1024.0
FN = 1.0
ZETA = 0.02


def _per_step(stepper, ag: np.ndarray, repeat: int = 3) -> float:
    best = math.inf
    ag_list = ag.tolist()
    for _ in range(repeat):
        stepper.reset()
        step = stepper.step
        t0 = time.perf_counter()
        for a in ag_list:
            step(a, 0.0)
        best = min(best, (time.perf_counter() - t0) / len(ag_list))
    return best


def _naive_newmark_bw(ag: np.ndarray, fs: float) -> np.ndarray:
    """Newmark average acceleration + Bouc-Wen, the way one would first write it."""
    p = BoucWenParams()
    k = p.k_a
    m = k / (2 * np.pi * FN) ** 2
    c = 2 * ZETA * np.sqrt(k * m)
    dt = 1 / fs
    xs, vs, as_, zs = [np.float64(0)], [np.float64(0)], [-ag[0]], [np.float64(0)]
    for i in range(1, len(ag)):
        x = xs[-1] + dt * vs[-1] + dt**2 / 4 * as_[-1]
        for _ in range(20):
            z = zs[-1]
            dx = x - xs[-1]
            for _ in range(10):  # explicit Euler sub-steps on z
                s = p.beta + p.gamma * np.sign(dx * z)
                z = z + dx / 10 * (1 - s * np.abs(z) ** p.q) / p.x_y
            r = p.eta * k * x + (1 - p.eta) * k * p.x_y * z
            kt = k * (1 - np.abs(z) ** p.q)
            a = 4 / dt**2 * (x - xs[-1]) - 4 / dt * vs[-1] - as_[-1]
            v = 2 / dt * (x - xs[-1]) - vs[-1]
            res = m * a + c * v + r + m * ag[i]
            dxn = -res / (m * 4 / dt**2 + c * 2 / dt + kt)
            x = x + dxn
            if np.abs(dxn) < 1e-12:
                break
        xs.append(x)
        vs.append(v)
        as_.append(a)
        zs.append(z)
    return np.array(xs)


def _solve_ivp_bw(ag: np.ndarray, fs: float) -> np.ndarray:
    p = BoucWenParams()
    k = p.k_a
    m = k / (2 * np.pi * FN) ** 2
    c = 2 * ZETA * np.sqrt(k * m)
    t = np.arange(ag.size) / fs

    def rhs(tt, y):
        x, v, z = y
        a_g = np.interp(tt, t, ag)
        r = p.eta * k * x + (1 - p.eta) * k * p.x_y * z
        s = p.beta + p.gamma * np.sign(v * z)
        return [v, -a_g - (c * v + r) / m, v * (1 - s * abs(z) ** p.q) / p.x_y]

    sol = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0, 0.0], t_eval=t, rtol=1e-8, atol=1e-10)
    return sol.y[0]


def main() -> None:
    gm = default_record().scaled("0.3g").resampled(FS)
    ag = gm.padded(60.0 - gm.duration - 1 / FS).accel  # 60 s at 1024 Hz
    n = ag.size
    dt = 1 / FS
    k = BoucWenParams().k_a
    m = k / (2 * np.pi * FN) ** 2
    print(f"SDOF fn = {FN} Hz, ζ = {ZETA}, El Centro 0.3 g, {n} steps = {n / FS:.1f} s at {FS} Hz")
    print(f"{'stepper':<34}{'µs/step':>10}{'% of 1/fs':>11}")
    rows = [
        ("CR linear", CRStepper(m, ZETA, k, dt)),
        ("CR Bouc-Wen", CRStepper(m, ZETA, k, dt, bouc_wen=True)),
        ("Newmark linear", NewmarkStepper(m, ZETA, k, dt)),
        ("Newmark Bouc-Wen (Newton)", NewmarkStepper(m, ZETA, k, dt, bouc_wen=True)),
    ]
    for name, st in rows:
        us = _per_step(st, ag) * 1e6
        print(f"{name:<34}{us:>10.2f}{us * 1e-6 * FS * 100:>10.2f}%")

    print(f"\n{'offline, 60 s record':<34}{'s':>10}{'x vs CR':>11}")
    t0 = time.perf_counter()
    x_cr = simulate_sdof(ag, FS, FN, ZETA, bouc_wen=True)
    t_cr = time.perf_counter() - t0
    print(f"{'simulate_sdof CR Bouc-Wen':<34}{t_cr:>10.3f}{'—':>11}")
    t0 = time.perf_counter()
    x_lin = simulate_sdof(ag, FS, FN, ZETA)
    print(f"{'simulate_sdof CR linear':<34}{time.perf_counter() - t0:>10.3f}{'—':>11}")
    del x_lin
    for name, fn in (
        (
            "simulate_sdof Newmark Bouc-Wen",
            lambda: simulate_sdof(ag, FS, FN, ZETA, bouc_wen=True, method="newmark"),
        ),
        ("naive Newmark Bouc-Wen", lambda: _naive_newmark_bw(ag, FS)),
        ("solve_ivp RK45 Bouc-Wen", lambda: _solve_ivp_bw(ag, FS)),
    ):
        t0 = time.perf_counter()
        x = fn()
        dt_run = time.perf_counter() - t0
        rel = np.max(np.abs(x - x_cr)) / np.max(np.abs(x_cr))
        print(f"{name:<34}{dt_run:>10.3f}{rel:>10.1e}")
    print(f"\npeak displacement {np.max(np.abs(x_cr)) * 1e3:.1f} mm (x_y = 10 mm)")


if __name__ == "__main__":
    main()

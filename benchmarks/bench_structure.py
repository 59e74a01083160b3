"""Cost of one integrator step (SDOF and MDOF) and of a 60 s record at 1024 Hz.

Goal: ≤ 20 µs per CR step of an SDOF with Bouc-Wen, i.e. ≤ 2 % of a 1024 Hz step.
MDOF (rths_hil.structures.mdof.MDOFCRStepper, shear buildings of n = 1, 3 and 10 storeys, linear and
Bouc-Wen): µs per step with a specimen force vector, as a ratio to the SDOF CRStepper step
measured in the same run.
References measured in the same run: a naive Newmark written the obvious way (numpy scalars,
lists grown by append, Bouc-Wen by explicit Euler sub-steps) and scipy.integrate.solve_ivp (RK45
on the state [x, v, z] with linear interpolation of the ground motion).

Run: ``.venv/bin/python benchmarks/bench_structure.py``
"""

from __future__ import annotations

import math
import time

import numpy as np
from _results import markdown_table, write_results
from scipy.integrate import solve_ivp

from rths_hil.groundmotion import default_record
from rths_hil.structures.mdof import MDOFCRStepper, shear_building
from rths_hil.structures.sdof import BoucWenParams, CRStepper, NewmarkStepper, simulate_sdof

FS = 1024.0
FN = 1.0
ZETA = 0.02


def _per_step(stepper, ag_list: list[float], force=0.0) -> float:
    stepper.reset()
    step = stepper.step
    t0 = time.perf_counter()
    for a in ag_list:
        step(a, force)
    return (time.perf_counter() - t0) / len(ag_list)


def _per_step_interleaved(rows, ag: np.ndarray, repeat: int = 5) -> list[float]:
    """Best time per step of each stepper, the cases interleaved round by round (noisy VM)."""
    ag_list = ag.tolist()
    best = [math.inf] * len(rows)
    for _ in range(repeat):
        for i, (_, st, force) in enumerate(rows):
            best[i] = min(best[i], _per_step(st, ag_list, force))
    return best


def _mdof_cases(dt: float) -> list[tuple[str, MDOFCRStepper, np.ndarray]]:
    """Shear buildings with the fundamental period of the SDOF (1 Hz), 2 % on modes 1 and 2."""
    cases = []
    for n in (1, 3, 10):
        m = np.full(n, 1.0e4)
        # uniform storeys: k chosen so that mode 1 is at FN
        k1 = shear_building(m, np.ones(n)).frequencies[0]
        k = np.full(n, (FN / k1) ** 2)
        for bw in (None, True):
            model = shear_building(m, k, zeta=ZETA, bouc_wen=bw)
            st = MDOFCRStepper(model, dt, transforms=np.eye(n)[:1], k_specimen=[1e5])
            name = f"MDOF CR n = {n} {'Bouc-Wen' if bw else 'linear'}"
            cases.append((name, st, np.zeros(n)))
    return cases


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
    print(f"{'stepper':<34}{'µs/step':>10}{'% of 1/fs':>11}{'× SDOF CR':>11}")
    rows = [
        ("CR linear", CRStepper(m, ZETA, k, dt), 0.0),
        ("CR Bouc-Wen", CRStepper(m, ZETA, k, dt, bouc_wen=True), 0.0),
        ("Newmark linear", NewmarkStepper(m, ZETA, k, dt), 0.0),
        ("Newmark Bouc-Wen (Newton)", NewmarkStepper(m, ZETA, k, dt, bouc_wen=True), 0.0),
        *_mdof_cases(dt),
    ]
    table = []
    ref = None
    for (name, _, _), t in zip(rows, _per_step_interleaved(rows, ag), strict=True):
        us = t * 1e6
        ref = ref or us
        print(f"{name:<34}{us:>10.2f}{us * 1e-6 * FS * 100:>10.2f}%{us / ref:>10.1f}×")
        table.append([name, f"{us:.2f}", f"{us * 1e-6 * FS * 100:.2f} %", f"{us / ref:.1f}×"])
    steps_md = markdown_table(
        ["stepper", "µs/step", "% of a 1024 Hz step", "× SDOF CR linear"], table
    )

    print(f"\n{'offline, 60 s record':<34}{'s':>10}{'x vs CR':>11}")
    t0 = time.perf_counter()
    x_cr = simulate_sdof(ag, FS, FN, ZETA, bouc_wen=True)
    t_cr = time.perf_counter() - t0
    print(f"{'simulate_sdof CR Bouc-Wen':<34}{t_cr:>10.3f}{'—':>11}")
    offline = [["simulate_sdof CR Bouc-Wen", f"{t_cr:.3f}", "—"]]
    t0 = time.perf_counter()
    x_lin = simulate_sdof(ag, FS, FN, ZETA)
    t_lin = time.perf_counter() - t0
    print(f"{'simulate_sdof CR linear':<34}{t_lin:>10.3f}{'—':>11}")
    offline.append(["simulate_sdof CR linear", f"{t_lin:.3f}", "—"])
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
        offline.append([name, f"{dt_run:.3f}", f"{rel:.1e}"])
    peak = np.max(np.abs(x_cr)) * 1e3
    print(f"\npeak displacement {peak:.1f} mm (x_y = 10 mm)")
    header = (
        f"SDOF fn = {FN} Hz, ζ = {ZETA}, El Centro scaled to 0.3 g, {n} steps = {n / FS:.1f} s "
        f"at {FS:g} Hz. MDOF: uniform shear buildings (10 t floors) with mode 1 at {FN} Hz, "
        f"ζ = {ZETA} on modes 1 and 2, one actuator on floor 1 (k_specimen in α), a force "
        "vector passed every step."
    )
    offline_md = markdown_table(
        ["offline, 60 s record", "s", "max abs(x − x_CR) / max abs(x_CR)"], offline
    )
    path = write_results(
        "bench_structure",
        f"{header}\n\n### One step\n\n{steps_md}\n\n### Whole record\n\n{offline_md}\n\n"
        f"Peak displacement (CR Bouc-Wen) {peak:.1f} mm (x_y = 10 mm).",
        title="Structure integrators: cost per step",
        goals=(
            "- SDOF CR step with Bouc-Wen ≤ 20 µs (≤ 2 % of a 1024 Hz step).\n"
            "- MDOF CR step (n = 3 and 10) small against the 977 µs step of a 1024 Hz loop; "
            "reported as a ratio to the SDOF CR step measured in the same run."
        ),
        command="python benchmarks/bench_structure.py",
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

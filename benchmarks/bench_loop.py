"""Benchmark of the real-time loop (issue 5).

Prints, measured in one run on this machine:

1. the step-path breakdown: cost per call of each piece the loop calls once per step, in
   isolation (median over repeated batches), and the whole loop without a transport (an
   in-process direct driver) — what the loop itself costs;
2. the raw request/reply round trip of each driver + twin (no loop);
3. lockstep steps/s through the full chain over each driver (goal ≥ 10 000 over CAN virtual);
4. paced runs at 1024 Hz through each driver and at 4096 Hz over CAN virtual: lateness
   p50/p99/p99.9/max and the overrun count (goals: ≤ 0.01 % of steps for CAN and serial,
   ≤ 0.1 % for Modbus TCP at 1024 Hz, ≤ 0.1 % at 4096 Hz over CAN).

Usage: ``python benchmarks/bench_loop.py [--duration 60] [--priority 0] [--skip-paced]``.
Paced runs take their duration in wall time each (4 × 60 s by default).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drivers.base import Driver, Feedback
from drivers.registry import create_driver
from rths_hil.compensation import InverseCompensator
from rths_hil.config import load_config
from rths_hil.estimation import DelayGainEstimator
from rths_hil.loop import RTHSLoop, _ExactFEI, _StreamingFEI
from rths_hil.recorder import COLUMNS, Recorder
from rths_hil.safety import SafetyMonitor, StuckRule, WatchdogRule
from rths_hil.structure import BoucWenParams, CRStepper
from sim_backends.modelfile import load_plant
from sim_backends.twin import default_plant, start_twin

FS = 1024.0
DRIVERS = ("can", "modbus", "serial")


def per_call(fn, n: int = 5000, repeat: int = 7) -> float:
    """Median over ``repeat`` batches of the mean cost of ``fn()`` in µs."""
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        out.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(out)


class DirectDriver(Driver):
    """No transport: send steps the plant in the caller, receive returns its answer."""

    name = "direct"

    def __init__(self, plant) -> None:
        super().__init__()
        self.plant = plant
        self.fb = None

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def send(self, seq, displacement, enable=True) -> None:
        x, f = self.plant.step(displacement)
        self.fb = Feedback(seq, x, f, 1)

    def receive(self, timeout):
        fb, self.fb = self.fb, None
        return fb

    def estop(self) -> None:
        pass


class DirectLoop(RTHSLoop):
    def _open_transport(self, stack):
        self.driver = DirectDriver(self.plant)
        return self.driver


def breakdown() -> None:
    print("\n## 1. Step-path breakdown (µs per call, median of 7 batches)")
    dt = 1 / FS
    k = 503400 * (2 * math.pi * 0.77) ** 2
    st = CRStepper(503400, 0.02, k, dt, bouc_wen=BoucWenParams(k_a=k), k_specimen=1.19e6)
    rng = np.random.default_rng(0)
    ag = (rng.standard_normal(100_000) * 0.3).tolist()
    it = iter(range(10**9))
    rows = []
    rows.append(
        ("CR step + Bouc-Wen (structure)", per_call(lambda: st.step(ag[next(it) % 100_000], 1e3)))
    )
    plant = load_plant(
        {
            "actuator": {"model": "first_order", "time_constant": 0.02, "delay": 0.005},
            "sensor": {"displacement_noise": 2e-6},
        },
        dt,
    )
    rows.append(
        (
            "twin plant step (first order + delay + specimen + noise)",
            per_call(lambda: plant.step(0.001)),
        )
    )
    comp = InverseCompensator(26.6)
    rows.append(("inverse compensation", per_call(lambda: comp.step(0.001))))
    mon = SafetyMonitor(dt, 0.05, 0.5, 1e5, watchdog=WatchdogRule(3), stuck=StuckRule(50, 1e-4))
    x = [0.0]

    def safety():
        x[0] += 1e-7
        mon.check_feedback(0.0, 1, True, 1, 1, 1, x[0], x[0], 10.0)
        mon.check_command(0.0, 1, x[0], 0.01, x[0])

    rows.append(("safety: check_feedback + check_command", per_call(safety)))
    sf = _StreamingFEI(FS, 3 / 0.77)
    ph = [0.0]

    def stream():
        ph[0] += 0.0047
        sf.push(math.sin(ph[0]), math.sin(ph[0] - 0.1))

    for _ in range(5000):
        stream()
    rows.append(("streaming FEI push (one window per sample)", per_call(stream)))
    ex = _ExactFEI(FS, 3 / 0.77, 256, background=False)

    def exact():
        ph[0] += 0.0047
        ex.push(math.sin(ph[0]), math.sin(ph[0] - 0.1))

    for _ in range(5000):
        exact()
    rows.append(
        ("exact FEI, hop 256 (amortised per sample; in lockstep only)", per_call(exact, n=2560))
    )
    kal = DelayGainEstimator(FS, delay0=0.025)

    def kalman():
        ph[0] += 0.0047
        kal.update(math.sin(ph[0]) * 0.01, math.sin(ph[0] - 0.12) * 0.01)

    rows.append(("Kalman delay/gain EKF update", per_call(kalman)))
    with tempfile.TemporaryDirectory() as d:
        rec = Recorder(Path(d) / "r", FS)
        vals = [0 if c[1] == "<i8" else (False if c[1] == "|b1" else 0.1) for c in COLUMNS]
        rows.append(
            ("recorder append (flush every 51 rows amortised)", per_call(lambda: rec.append(*vals)))
        )
        rec.close()
    for name, us in rows:
        print(f"| {name:<62} | {us:7.2f} |")
    cfg = load_config(
        None, ["loop.mode=lockstep", "loop.console=0", "loop.duration=20", "output.plot=false"]
    )
    for label, over in (
        ("whole loop, no transport (full chain)", []),
        ("whole loop, no transport, Kalman off", ["kalman.enabled=false"]),
        (
            "whole loop, no transport, FEI + Kalman off",
            ["kalman.enabled=false", "fei.enabled=false"],
        ),
    ):
        best = math.inf
        for _ in range(3):
            with tempfile.TemporaryDirectory() as d:
                c = load_config(
                    None,
                    [
                        "loop.mode=lockstep",
                        "loop.console=0",
                        "loop.duration=10",
                        "output.plot=false",
                        *over,
                    ],
                )
                r = DirectLoop(c, Path(d) / "r").run()
                best = min(best, r.wall_time / r.steps * 1e6)
        print(f"| {label:<62} | {best:7.2f} |")
    del cfg


def round_trips(n: int = 5000) -> None:
    print("\n## 2. Raw driver + twin round trip (send + receive, no loop), µs")
    print("| driver | median | p99 | max | round trips/s |")
    print("|---|---|---|---|---|")
    for name in DRIVERS:
        with (
            start_twin(name, default_plant()) as twin,
            create_driver(name, **twin.connection) as drv,
        ):
            ts = np.empty(n)
            for k in range(n):
                t0 = time.perf_counter()
                drv.send(k, 1e-3 * math.sin(k / 100), True)
                drv.receive(1.0)
                ts[k] = time.perf_counter() - t0
            ts = ts[200:] * 1e6
            print(
                f"| {name} | {np.median(ts):.0f} | {np.percentile(ts, 99):.0f} | "
                f"{ts.max():.0f} | {1e6 / ts.mean():.0f} |"
            )


def lockstep(duration: float) -> None:
    print(f"\n## 3. Lockstep through the full chain ({duration:g} s simulated, best of 3)")
    print("| driver | steps/s | µs/step |")
    print("|---|---|---|")
    for name in DRIVERS:
        best = 0.0
        for _ in range(3):
            with tempfile.TemporaryDirectory() as d:
                cfg = load_config(
                    None,
                    [
                        f"driver.name={name}",
                        "loop.mode=lockstep",
                        "loop.console=0",
                        f"loop.duration={duration}",
                        "output.plot=false",
                    ],
                )
                r = RTHSLoop(cfg, Path(d) / "r").run()
                assert r.status == "completed", r.trip
                best = max(best, r.steps_per_second)
        print(f"| {name} | {best:.0f} | {1e6 / best:.1f} |")


def steal_ticks() -> int:
    """Hypervisor steal time so far (USER_HZ ticks, all CPUs) from /proc/stat."""
    try:
        with open("/proc/stat") as fh:
            return int(fh.readline().split()[8])
    except (OSError, IndexError, ValueError):
        return 0


def floor(duration: float, priority: int, fs: float = 1024.0, spin: float = 3e-4) -> None:
    """The machine's own timing floor: the paced wait (sleep, then spin) with no work at all."""
    print(
        f"\n## 0. Machine floor: an empty paced loop at {fs:g} Hz for {duration:g} s "
        f"(sleep until {spin * 1e3:g} ms before each deadline, then spin)"
    )
    old = None
    if priority:
        with contextlib.suppress(OSError, AttributeError):
            old = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    sys.setswitchinterval(1e-4)
    perf = time.perf_counter
    dt = 1 / fs
    n = int(duration * fs)
    lat = np.empty(n)
    st0 = steal_ticks()
    t0 = perf() + 0.1
    for k in range(n):
        d = t0 + k * dt
        r = d - perf() - spin
        if r > 0:
            time.sleep(r)
        now = perf()
        while now < d:
            now = perf()
        lat[k] = now - d
    sys.setswitchinterval(0.005)
    if old is not None:
        os.sched_setscheduler(0, old[0], old[1])
    p50, p99, p999 = np.percentile(lat, [50, 99, 99.9]) * 1e6
    late = int((lat > 0.5 * dt).sum())
    print(
        f"p50 {p50:.0f} µs, p99 {p99:.0f} µs, p99.9 {p999:.0f} µs, max {lat.max() * 1e6:.0f} µs, "
        f"steps later than half a period: {late} ({100 * late / n:.3f} %), hypervisor steal "
        f"{(steal_ticks() - st0) / os.sysconf('SC_CLK_TCK'):.2f} CPU-s"
    )


def paced(duration: float, priority: int) -> None:
    print(f"\n## 4. Paced runs ({duration:g} s each, SCHED_FIFO priority {priority or 'off'})")
    print(
        "| driver | fs (Hz) | steps | p50 (µs) | p99 (µs) | p99.9 (µs) | max (µs) | overruns "
        "| overrun % | missed replies | status |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    cases = [(n, 1024.0) for n in DRIVERS] + [("can", 4096.0)]
    for name, fs in cases:
        with tempfile.TemporaryDirectory() as d:
            over = [
                f"driver.name={name}",
                f"loop.fs={fs}",
                "loop.mode=paced",
                "loop.console=0",
                f"loop.duration={duration}",
                "output.plot=false",
                f"loop.priority={priority}",
                "ground_motion.tail=60",
                "safety.max_overruns=1000000",
                "safety.watchdog_missed=1000000",
            ]
            if fs > 2048:
                over += [f"compensation.alpha={1 + 0.025 * fs}", "fei.exact_hop=1024"]
            cfg = load_config(None, over)
            st0 = steal_ticks()
            r = RTHSLoop(cfg, Path(d) / "r").run()
            steal = (steal_ticks() - st0) / os.sysconf("SC_CLK_TCK")
            s = r.lateness_stats()
            print(
                f"| {name} | {fs:g} | {r.steps} | {s['p50'] * 1e6:.0f} | {s['p99'] * 1e6:.0f} "
                f"| {s['p99.9'] * 1e6:.0f} | {s['max'] * 1e6:.0f} | {s['overruns']} | "
                f"{100 * s['overruns'] / max(r.steps, 1):.3f} | {r.missed_replies} | "
                f"{r.status} | {steal:.2f} |",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="paced run length (s)")
    ap.add_argument("--lockstep-duration", type=float, default=20.0)
    ap.add_argument(
        "--priority", type=int, default=10, help="SCHED_FIFO priority for paced (0 = off)"
    )
    ap.add_argument("--skip-paced", action="store_true")
    args = ap.parse_args()
    print(
        f"# bench_loop — {time.strftime('%Y-%m-%d %H:%M')}, python {sys.version.split()[0]}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    )
    if not args.skip_paced:
        floor(min(args.duration, 20.0), args.priority)
    breakdown()
    round_trips()
    lockstep(args.lockstep_duration)
    if not args.skip_paced:
        paced(args.duration, args.priority)
    print(f"\nload average at the end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        main()

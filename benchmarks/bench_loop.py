"""Benchmark of the real-time loop.

Prints, measured in one run on this machine:

0. the machine's floor: an empty paced loop (:func:`rths_hil.hybrid.paced_floor`, the loop's
   own wait code with no work) with and without SCHED_FIFO, and the hypervisor steal;
1. the step-path breakdown: cost per call of each piece the loop calls once per step, in
   isolation (median over repeated batches), and the whole loop without a transport (an
   in-process direct driver) — what the loop itself costs;
2. the raw request/reply round trip of each driver + twin (no loop);
3. lockstep steps/s through the full chain over each driver (goal ≥ 10 000 over CAN virtual);
4. paced runs at 1024 Hz through each driver and at 4096 Hz over CAN virtual: lateness
   p50/p99/p99.9/max and the overrun count (goals: ≤ 0.01 % of steps for CAN and serial,
   ≤ 0.1 % for Modbus TCP at 1024 Hz, ≤ 0.1 % at 4096 Hz over CAN), each run between two
   empty-loop floors at the same rate and scheduling, with the steal during each, and the
   overruns attributed (:func:`rths_hil.hybrid.attribute_overruns`) to the machine (the wait
   returned late although the loop was ready) or to the loop's work, each with its catch-up;
5. (``--profile DRIVER@FS`` only) the per-phase cost of one paced run: every per-step call
   timed, p50/p99/p99.9/max.

Usage: ``python benchmarks/bench_loop.py [--duration 60] [--floor 15] [--priority 10]
[--paced-only] [--cases can@1024,can@4096] [--lock /work/notes/bench.lock]`` or
``python benchmarks/bench_loop.py --profile can@4096 --duration 20``. Paced runs take their
duration in wall time each, plus two floors; ``--lock`` takes the shared bench lock around each
measurement (one paced case with its floors at a time) instead of around the whole script.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rths_hil.drivers.base import Driver, Feedback
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.modelfile import load_plant
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.compensators.inverse import InverseCompensator
from rths_hil.config import load_config
from rths_hil.estimation import DelayGainEstimator
from rths_hil.hybrid import (
    WORK,
    WORK_BACKLOG,
    RTHSLoop,
    attribute_overruns,
    count_causes,
    paced_floor,
)
from rths_hil.hybrid.channel import Channel
from rths_hil.hybrid.evaluators import ExactFEI, StreamingFEI
from rths_hil.hybrid.runner import Runner
from rths_hil.records.recorder import COLUMNS, Recorder
from rths_hil.safety import SafetyMonitor, StuckRule, WatchdogRule
from rths_hil.structures.sdof import BoucWenParams, CRStepper

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import write_results

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
        if not enable:  # arming / hold: no plant step
            self.fb = Feedback(seq, 0.0, 0.0, 0)
            return
        x, f = self.plant.step(displacement)
        self.fb = Feedback(seq, x, f, 1)

    def receive(self, timeout):
        fb, self.fb = self.fb, None
        return fb

    def estop(self) -> None:
        pass


class DirectRunner(Runner):
    """The runner with each channel's driver replaced by a :class:`DirectDriver`."""

    def open_channel(self, ch, stack):
        ch.bind(DirectDriver(ch.plan.plant))
        if ch.stream_fei is not None and ch.plan.exact_hop > 0:
            ch.exact_fei = ExactFEI(self.plan.fs, ch.plan.window_s, ch.plan.exact_hop, False)


class DirectLoop(RTHSLoop):
    runner_class = DirectRunner


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
    sf = StreamingFEI(FS, 3 / 0.77)
    ph = [0.0]

    def stream():
        ph[0] += 0.0047
        sf.push(math.sin(ph[0]), math.sin(ph[0] - 0.1))

    for _ in range(5000):
        stream()
    rows.append(("streaming FEI push (one window per sample)", per_call(stream)))
    ex = ExactFEI(FS, 3 / 0.77, 256, background=False)

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


def steal_s(t0: int) -> float:
    """CPU-seconds of steal since ``t0`` (ticks of :func:`steal_ticks`)."""
    return (steal_ticks() - t0) / os.sysconf("SC_CLK_TCK")


@contextlib.contextmanager
def bench_lock(path: str | None):
    """Hold ``flock(path)`` (the shared bench lock) for one measurement, if a path is given."""
    if not path:
        yield
        return
    import fcntl

    with open(path, "a") as fh:
        t = time.monotonic()
        fcntl.flock(fh, fcntl.LOCK_EX)
        waited = time.monotonic() - t
        if waited > 1:
            print(f"(waited {waited:.0f} s for {path})", flush=True)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def pct(x: int, n: int) -> str:
    return f"{100 * x / max(n, 1):.3f}"


def floor_case(fs: float, duration: float, priority: int) -> dict:
    """One empty paced loop (:func:`rths_hil.hybrid.paced_floor`): overrun share and steal."""
    st0 = steal_ticks()
    lat, ready = paced_floor(fs, duration, spin=3e-4, priority=priority)
    steal = steal_s(st0)
    over = int((lat > 0.5 / fs).sum())
    causes = count_causes(attribute_overruns(lat, ready, 0.5 / fs))
    return {
        "n": lat.size,
        "over": over,
        "steal": steal,
        "p999": float(np.percentile(lat, 99.9)),
        "max": float(lat.max()),
        "causes": causes,
    }


def floor(duration: float, priority: int, fs: float = 1024.0) -> None:
    """The machine's own timing floor: the paced wait (sleep, then spin) with no work at all."""
    print(
        f"\n## 0. Machine floor: an empty paced loop at {fs:g} Hz for {duration:g} s "
        "(sleep until 0.3 ms before each deadline, then spin; same code as the loop's wait)"
    )
    print("| scheduling | p99.9 (µs) | max (µs) | steps > ½ period late | steal (CPU-s) |")
    print("|---|---|---|---|---|")
    for prio in sorted({priority, 0}, reverse=True):
        f = floor_case(fs, duration, prio)
        print(
            f"| {'SCHED_FIFO ' + str(prio) if prio else 'default (CFS)'} | {f['p999'] * 1e6:.0f} "
            f"| {f['max'] * 1e6:.0f} | {f['over']} ({pct(f['over'], f['n'])} %) "
            f"| {f['steal']:.2f} |",
            flush=True,
        )


def paced_config(name: str, fs: float, duration: float, priority: int, extra=()):
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
        "safety.displacement_limit=0.3",
        "safety.velocity_limit=2.0",
        "safety.watchdog_missed=1000000",
        *extra,
    ]
    if fs > 2048:
        over += [f"compensation.alpha={1 + 0.025 * fs}", "fei.exact_hop=1024"]
    return load_config(None, over)


def paced(
    duration: float,
    priority: int,
    floor_s: float,
    lock: str | None,
    cases: list[tuple[str, float]],
) -> None:
    print(
        f"\n## 4. Paced runs ({duration:g} s each, SCHED_FIFO priority {priority or 'off'}), "
        f"each between two {floor_s:g} s empty-loop floors (same rate and scheduling)"
    )
    print(
        "Overrun = command left > ½ period after its deadline. Cause (rths_hil.hybrid."
        "attribute_overruns): machine = the wait returned late although the loop was ready in "
        "time (an empty loop suffers the same); work = the previous step's work ran past the "
        "threshold (includes stalls that hit during the work); +b = catch-up steps after one."
    )
    print(
        "| driver | fs (Hz) | steps | p50 / p99 / p99.9 / max (µs) | overruns | overrun % "
        "| floor before % | floor after % | machine (+b) | work (+b) | missed replies "
        "| steal run / floors (CPU-s) | load |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, fs in cases:
        with bench_lock(lock), tempfile.TemporaryDirectory() as d:
            cfg = paced_config(name, fs, duration, priority)
            f0 = floor_case(fs, floor_s, priority)
            st0 = steal_ticks()
            r = RTHSLoop(cfg, Path(d) / "r").run()
            steal = steal_s(st0)
            f1 = floor_case(fs, floor_s, priority)
            load = os.getloadavg()[0]
        s = r.lateness_stats()
        c = r.overrun_causes()
        print(
            f"| {name} | {fs:g} | {r.steps} | {s['p50'] * 1e6:.0f} / {s['p99'] * 1e6:.0f} / "
            f"{s['p99.9'] * 1e6:.0f} / {s['max'] * 1e6:.0f} | {s['overruns']} | "
            f"{pct(s['overruns'], r.steps)} | {pct(f0['over'], f0['n'])} | "
            f"{pct(f1['over'], f1['n'])} | {c['machine']} (+{c['machine_backlog']}) | "
            f"{c['work']} (+{c['work_backlog']}) | {r.missed_replies} | "
            f"{steal:.2f} / {f0['steal']:.2f}, {f1['steal']:.2f} | {load:.1f} |",
            flush=True,
        )


# ---- per-phase profile of one paced run -------------------------------------------------------


class _Phases:
    """Per-call durations of the step path's pieces (a wrapper around each bound method)."""

    def __init__(self) -> None:
        self.d: dict[str, list[float]] = {}

    def wrap(self, name: str, fn):
        buf = self.d.setdefault(name, [])
        perf = time.perf_counter
        add = buf.append

        def timed(*a):
            t = perf()
            r = fn(*a)
            add(perf() - t)
            return r

        return timed


class _Proxy:
    """Forwards attribute reads to ``obj``; the methods in ``timed`` are wrapped."""

    def __init__(self, obj, ph: _Phases, timed: dict[str, str]) -> None:
        self.__dict__["_obj"] = obj
        for meth, label in timed.items():
            self.__dict__[meth] = ph.wrap(label, getattr(obj, meth))

    def __getattr__(self, name):
        return getattr(self._obj, name)

    def __setattr__(self, name, value):
        setattr(self._obj, name, value)


class ProfiledRunner(Runner):
    """The runner with every per-step call timed (≈ 0.3 µs overhead per call)."""

    ph: _Phases

    def open_channel(self, ch, stack):
        super().open_channel(ch, stack)
        w = self.ph.wrap
        ch.send = w("driver send", ch.send)
        ch.receive = w("driver receive (+ inline twin pump)", ch.receive)
        ch.compensate = w("compensation", ch.compensate)

    def run(self):
        # ``evaluate`` is a method of the slotted Channel: timed on the class for this run
        self.ph = _Phases()
        evaluate = Channel.evaluate
        Channel.evaluate = self.ph.wrap("evaluators (streaming + exact FEI, Kalman)", evaluate)
        try:
            return super().run()
        finally:
            Channel.evaluate = evaluate

    def _loop(self, rec, *args):
        w = self.ph.wrap
        st = self.plan.structure
        st.step = w("structure (CR step)", st.step)
        for name in ("feedback", "command", "evaluators", "timing"):
            setattr(self.safety, name, w("safety", getattr(self.safety, name)))
        rec.append = w("recorder append (+ flush)", rec.append)
        return super()._loop(rec, *args)


class ProfiledLoop(RTHSLoop):
    runner_class = ProfiledRunner

    @property
    def ph(self):
        return self.runner.ph


def profile(name: str, fs: float, duration: float, priority: int, lock: str | None) -> None:
    print(
        f"\n## 5. Per-phase profile: one paced run, {name} at {fs:g} Hz, {duration:g} s "
        "(every per-step call wrapped with timestamps; µs per call)"
    )
    with bench_lock(lock), tempfile.TemporaryDirectory() as d:
        loop = ProfiledLoop(paced_config(name, fs, duration, priority), Path(d) / "r")
        st0 = steal_ticks()
        r = loop.run()
        steal = steal_s(st0)
    print(
        f"steps {r.steps}, overruns {r.overruns} ({pct(r.overruns, r.steps)} %), causes "
        f"{r.overrun_causes()}, steal {steal:.2f} CPU-s"
    )
    print("| phase | calls/step | p50 | p99 | p99.9 | max | calls > 100 µs |")
    print("|---|---|---|---|---|---|---|")
    for ph, v in loop.ph.d.items():
        if not v:
            continue
        a = np.asarray(v) * 1e6
        p50, p99, p999 = np.percentile(a, [50, 99, 99.9])
        print(
            f"| {ph} | {a.size / r.steps:.3f} | {p50:.1f} | {p99:.1f} | {p999:.1f} | "
            f"{a.max():.0f} | {int((a > 100).sum())} |"
        )
    # the whole work of a step: from its send to the moment the loop was ready for the next
    lat, ready, dt = r.lateness, r.ready, 1 / fs
    work = (ready[1:] + dt - lat[:-1]) * 1e6
    p50, p99, p999 = np.percentile(work, [50, 99, 99.9])
    print(
        f"| **whole step work (send → ready)** | 1 | {p50:.1f} | {p99:.1f} | {p999:.1f} | "
        f"{work.max():.0f} | {int((work > 100).sum())} |"
    )
    # which piece of the previous step was slow when a step was late because of the work
    cause = attribute_overruns(lat, ready, r.overrun_threshold)
    origins = np.flatnonzero(cause == WORK)
    origins = origins[origins > 0]
    if origins.size:
        once = {ph: np.asarray(v) for ph, v in loop.ph.d.items() if len(v) == r.steps}
        print(
            f"\nwork-late steps: {origins.size}; previous step's work p50 "
            f"{np.median(work[origins - 1]):.0f} µs; the previous step's slowest piece:"
        )
        names = list(once)
        slow = np.stack([once[ph][origins - 1] for ph in names]) * 1e6
        top = np.argmax(slow - np.stack([np.median(once[ph]) * 1e6 for ph in names])[:, None], 0)
        for i, ph in enumerate(names):
            hit = top == i
            if hit.any():
                print(
                    f"- {ph}: {int(hit.sum())} ({100 * hit.mean():.0f} %), its median there "
                    f"{np.median(slow[i, hit]):.0f} µs"
                )


# ----------------------------------------------------------------------------------------------
# 6. channels


def channels_config(n: int, extra=()) -> list[str]:
    """``n`` actuators over CAN virtual (one bus, nodes 1..n) on an n-storey shear building."""
    m = ", ".join(["2.0e5"] * n)
    k = ", ".join(["1.0e8"] * n)
    over = [
        "structure.kind=shear_building",
        f"structure.masses=[{m}]",
        f"structure.stiffnesses=[{k}]",
        "structure.bouc_wen=false",
        "ground_motion.pga=1.0",
        "driver.connection={interface='virtual', channel='bench-channels'}",
        "twin.actuator={model='delay_gain', delay=0.01, gain=1.0}",
        "compensation.alpha=11.24",
        "loop.console=0",
        "output.plot=false",
        "safety.max_overruns=1000000",
        "safety.displacement_limit=0.3",
        "safety.velocity_limit=2.0",
        *extra,
    ]
    return over


def _channels_toml(n: int) -> str:
    return "\n".join(
        f'[[actuators]]\nname = "a{i + 1}"\ndof = {i + 1}\n'
        f"driver = {{ connection = {{ node = {i + 1} }} }}\n"
        for i in range(n)
    )


def run_channels(n: int, mode: str, duration: float, extra=()):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.toml"
        p.write_text(_channels_toml(n))
        cfg = load_config(p, channels_config(n, extra))
        return RTHSLoop(cfg, Path(d) / "r", mode=mode, duration=duration).run()


#: One lockstep run of the default configuration, printing its steps/s and the loop thread's
#: CPU time per step in µs (``time.thread_time`` around the step loop: on a shared machine the
#: time the thread was not running does not count). A revision from before the loop moved to
#: ``rths_hil.hybrid`` imports it from ``rths_hil.loop``.
_BASELINE_SNIPPET = (
    "import sys, tempfile, time; from pathlib import Path; from rths_hil.config import load_config"
    "\ntry:\n from rths_hil.hybrid import RTHSLoop\nexcept ImportError:\n"
    " from rths_hil.loop import RTHSLoop\n"
    "try:\n from rths_hil.hybrid.runner import Runner as C\n"
    "except ImportError:\n C = RTHSLoop\n"
    "cpu = [0.0]\norig = C._loop\n"
    "def timed(self, *a):\n t0 = time.thread_time()\n try: return orig(self, *a)\n"
    " finally: cpu[0] = time.thread_time() - t0\n"
    "C._loop = timed\n"
    "cfg = load_config(None, ['loop.console=0', 'output.plot=false']); d = tempfile.mkdtemp()\n"
    "r = RTHSLoop(cfg, Path(d) / 'r', mode='lockstep', duration=float(sys.argv[1])).run()\n"
    "print(r.steps_per_second, cpu[0] / r.steps * 1e6)\n"
)


#: Python bytecodes executed per step of the same lockstep run (``sys.settrace`` with opcode
#: events on the loop's frames and everything they call): deterministic, so it shows a change
#: of the Python work per step that the wall clock of this machine cannot resolve; it does not
#: see time spent inside numpy or numba kernels.
_OPCODES_SNIPPET = (
    "import sys, tempfile; from pathlib import Path; from rths_hil.config import load_config;"
    "\ntry:\n from rths_hil.hybrid import RTHSLoop\nexcept ImportError:\n"
    " from rths_hil.loop import RTHSLoop\n"
    "try:\n from rths_hil.hybrid.runner import Runner as C\n"
    "except ImportError:\n C = RTHSLoop\n"
    "n = [0]\n"
    "def local(f, e, a):\n if e == 'opcode': n[0] += 1\n return local\n"
    "def tracer(f, e, a):\n f.f_trace_opcodes = True\n return local\n"
    "orig = C._loop\n"
    "def traced(self, *a):\n sys.settrace(tracer)\n try: return orig(self, *a)\n"
    " finally: sys.settrace(None)\n"
    "C._loop = traced\n"
    "cfg = load_config(None, ['loop.console=0', 'output.plot=false'])\n"
    "r = RTHSLoop(cfg, Path(tempfile.mkdtemp()) / 'r', mode='lockstep',"
    " duration=float(sys.argv[1])).run()\n"
    "print(n[0] / r.steps)\n"
)


@contextlib.contextmanager
def baseline_tree(rev: str):
    """``rev`` checked out in a temporary git worktree (removed afterwards); yields its path."""
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        wt = Path(tmp) / "baseline"
        subprocess.run(
            ["git", "-C", str(root), "worktree", "add", "--detach", "-f", str(wt), rev],
            check=True,
            capture_output=True,
        )
        # drivers/ and sim_backends/ install as rths_hil.drivers and rths_hil.sim_backends
        # (package-dir): link them into the baseline's package so that its own copies are
        # imported, not this tree's through the editable install
        for sub in ("drivers", "sim_backends"):
            if (wt / sub).is_dir() and not (wt / "rths_hil" / sub).exists():
                (wt / "rths_hil" / sub).symlink_to(wt / sub, target_is_directory=True)
        try:
            yield wt
        finally:
            subprocess.run(
                ["git", "-C", str(root), "worktree", "remove", "--force", str(wt)],
                capture_output=True,
            )


def _run_in(tree: Path, args: list[str], pin: list[str] | None = None) -> list[float]:
    """Run ``args`` (``-c`` snippet and its arguments) with ``tree`` first on the path; the
    numbers of its last output line."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    with tempfile.TemporaryDirectory() as cwd:
        r = subprocess.run(
            [*(pin or []), sys.executable, *args],
            env=env,
            cwd=cwd,
            capture_output=True,
            text=True,
        )
    if r.returncode:
        raise RuntimeError(f"a run in {tree} failed:\n{r.stderr[-2000:]}")
    return [float(v) for v in r.stdout.strip().splitlines()[-1].split()]


def one_channel_vs_baseline(
    rev: str, rounds: int, duration: float, cpu: int | None = None, wt: Path | None = None
) -> tuple[list, str]:
    """Lockstep steps/s of the default single-actuator test: this tree vs ``rev``.

    ``rev`` is checked out in a temporary git worktree (or ``wt`` is that checkout); the two
    run alternately in fresh processes (``rounds`` each) so that both see the same machine
    load. With ``cpu`` both are pinned to that CPU (``taskset``), so that neither gains from
    landing on a quieter core.
    """
    if wt is None:
        with baseline_tree(rev) as tree:
            return one_channel_vs_baseline(rev, rounds, duration, cpu, tree)
    pin = ["taskset", "-c", str(cpu)] if cpu is not None else []
    root = Path(__file__).resolve().parents[1]
    new, old, cpu_new, cpu_old = [], [], [], []
    for _ in range(rounds):
        for tree, out, cpu_out in ((root, new, cpu_new), (wt, old, cpu_old)):
            rate, cpu_us = _run_in(tree, ["-c", _BASELINE_SNIPPET, str(duration)], pin)
            out.append(rate)
            cpu_out.append(cpu_us)
    # deterministic: one traced run each
    ops = [_run_in(tree, ["-c", _OPCODES_SNIPPET, "2.0"])[0] for tree in (root, wt)]
    ratios = [a / b for a, b in zip(new, old, strict=True)]
    med = statistics.median(ratios)
    cpu_med = statistics.median(a / b for a, b in zip(cpu_new, cpu_old, strict=True))
    row = (
        f"| 1 channel (default config) vs `{rev}` | {statistics.median(new):.0f} vs "
        f"{statistics.median(old):.0f} steps/s | median ratio {med:.3f} (range "
        f"{min(ratios):.2f}–{max(ratios):.2f}) over {rounds} alternations (goal ≥ 0.95); "
        f"loop CPU time per step {statistics.median(cpu_new):.1f} vs "
        f"{statistics.median(cpu_old):.1f} µs (median ratio {cpu_med:.3f}); "
        f"Python bytecodes per step {ops[0]:.0f} vs {ops[1]:.0f} ({ops[0] / ops[1]:.3f}) |"
    )
    return ratios, row


#: One run of section 6's ``n``-channel test (``argv``: n, mode, duration) in whichever tree is
#: first on the path, with the configuration of :func:`channels_config` and
#: :func:`_channels_toml` (their source is put before it): steps/s, the loop thread's CPU time
#: per step in µs (``time.thread_time`` around the step loop; lockstep serves the twins inline,
#: in that thread), Python bytecodes per step (``trace`` as the last argument: a traced run),
#: overruns, work-caused overruns (paced), steps and 1 if the run completed (a paced run may
#: trip on a stall of a loaded machine).
_CHANNELS_SNIPPET = (
    "import sys, tempfile, time; from pathlib import Path; from rths_hil.config import load_config"
    "\ntry:\n from rths_hil.hybrid import RTHSLoop, attribute_overruns, WORK, WORK_BACKLOG\n"
    "except ImportError:\n"
    " from rths_hil.loop import RTHSLoop, attribute_overruns, WORK, WORK_BACKLOG\n"
    "from rths_hil.hybrid.runner import Runner as C\n"
    "n, mode, dur = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])\n"
    "trace = sys.argv[4:] == ['trace']\n"
    "cpu = [0.0]; ops = [0]; orig = C._loop\n"
    "def local(f, e, a):\n if e == 'opcode': ops[0] += 1\n return local\n"
    "def tracer(f, e, a):\n f.f_trace_opcodes = True\n return local\n"
    "def timed(self, *a):\n t0 = time.thread_time()\n if trace: sys.settrace(tracer)\n"
    " try: return orig(self, *a)\n"
    " finally:\n  sys.settrace(None); cpu[0] = time.thread_time() - t0\n"
    "C._loop = timed\n"
    "d = Path(tempfile.mkdtemp()); p = d / 'c.toml'; p.write_text(_channels_toml(n))\n"
    "extra = ('fei.exact_hop=256',) if mode == 'paced' else ()\n"
    "cfg = load_config(p, channels_config(n, extra))\n"
    "r = RTHSLoop(cfg, d / 'r', mode=mode, duration=dur).run()\n"
    "assert r.status == 'completed' or mode == 'paced', r.trip\n"
    "work = 0\n"
    "if mode == 'paced':\n"
    " c = attribute_overruns(r.lateness, r.ready, r.overrun_threshold)\n"
    " work = int(((c == WORK) | (c == WORK_BACKLOG)).sum())\n"
    "print(r.steps_per_second, cpu[0] / r.steps * 1e6, ops[0] / r.steps, r.overruns, work,"
    " r.steps, int(r.status == 'completed'))\n"
)


def channels_vs_baseline(
    rev: str, wt: Path, rounds: int, paced_runs: int, paced_s: float, n: int = 4
) -> list[str]:
    """Section 6's ``n``-channel test, this tree vs the checkout ``wt`` of ``rev``, alternated.

    Lockstep (10 s simulated): steps/s and the loop thread's CPU time per step, ``rounds``
    alternations, and Python bytecodes per step (one traced run each). Paced at 1024 Hz:
    ``paced_runs`` alternations of ``paced_s`` s each, overruns and those caused by the work.
    The baseline runs this script's section-6 configuration with its own package.
    """
    import inspect

    root = Path(__file__).resolve().parents[1]
    snippet = "\n".join(
        [inspect.getsource(channels_config), inspect.getsource(_channels_toml), _CHANNELS_SNIPPET]
    )
    trees = (("this tree", root), (f"`{rev}`", wt))
    lock = {t: [] for t, _ in trees}
    for _ in range(rounds):
        for t, tree in trees:
            lock[t].append(_run_in(tree, ["-c", snippet, str(n), "lockstep", "10"]))
    ops = {
        t: _run_in(tree, ["-c", snippet, str(n), "lockstep", "2", "trace"])[2] for t, tree in trees
    }
    paced = {t: [] for t, _ in trees}
    for _ in range(paced_runs):
        for t, tree in trees:
            paced[t].append(_run_in(tree, ["-c", snippet, str(n), "paced", str(paced_s)]))
    ratio = statistics.median(
        a[1] / b[1] for a, b in zip(lock["this tree"], lock[f"`{rev}`"], strict=True)
    )
    lines = [
        "",
        f"{n} channels, this tree vs `{rev}` in the same run (alternated; lockstep {rounds} × "
        f"10 s simulated, paced {paced_runs} × {paced_s:g} s at 1024 Hz); median CPU time "
        f"ratio {ratio:.3f}:",
        "",
        "| tree | lockstep steps/s (median) | loop CPU µs/step (median, min) | Python bytecodes "
        "per step | paced overruns, per run | caused by the work, per run |",
        "|---|---|---|---|---|---|",
    ]
    for t, _ in trees:
        rs = lock[t]
        lines.append(
            f"| {t} | {statistics.median(r[0] for r in rs):.0f} | "
            f"{statistics.median(r[1] for r in rs):.1f}, {min(r[1] for r in rs):.1f} | "
            f"{ops[t]:.0f} | {', '.join(f'{int(p[3])}' for p in paced[t])} of "
            f"{int(paced[t][0][5]) if paced[t] else 0} | "
            f"{', '.join(f'{int(p[4])} = {100 * p[4] / max(p[5], 1):.3f} %' for p in paced[t])}"
            f"{'' if all(p[6] for p in paced[t]) else ' (a run tripped)'} |"
        )
    return lines


def channels(
    duration: float,
    paced_s: float,
    baseline: str | None,
    rounds: int,
    pin: int | None = None,
    paced_runs: int = 3,
) -> str:
    """Section 6: 1, 2, 4 and 8 channels over CAN virtual; returns the Markdown table."""
    lines = [
        f"## 6. Channels over CAN virtual (one bus, nodes 1..n; n-storey shear building; "
        f"lockstep {duration:g} s simulated, best of 3)",
        "",
        f"Load average at the start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs.",
        "",
        "| channels | lockstep steps/s | loop work p50 (µs) | loop work p99 (µs) | "
        "work per channel p50 (µs) |",
        "|---|---|---|---|---|",
    ]
    print("\n" + lines[0] + "\n")
    print("\n".join(lines[2:]))
    for n in (1, 2, 4, 8):
        best = None
        for _ in range(3):
            r = run_channels(n, "lockstep", duration)
            assert r.status == "completed", r.trip
            if best is None or r.steps_per_second > best.steps_per_second:
                best = r
        w50, w99 = np.percentile(best.work, [50, 99]) * 1e6
        row = f"| {n} | {best.steps_per_second:.0f} | {w50:.1f} | {w99:.1f} | {w50 / n:.1f} |"
        lines.append(row)
        print(row)
    if paced_s > 0:
        lines += [
            "",
            f"Paced, 4 channels at 1024 Hz, {paced_runs} runs of {paced_s:g} s (SCHED_FIFO "
            "priority 10; the twins served in the loop's process, their reply time not counted "
            "as the loop's work):",
            "",
            "| run | loop work p50 (µs) | loop work p99 (µs) | p99 / period (goal ≤ 30 %) | "
            "overruns | caused by the work (goal ≤ 0.01 %) | status |",
            "|---|---|---|---|---|---|---|",
        ]
        print("\n".join(lines[-5:]))
        for i in range(paced_runs):
            r = run_channels(4, "paced", paced_s, ("fei.exact_hop=256",))
            period = 1.0 / r.fs
            w50, w99 = np.percentile(r.work, [50, 99])
            cause = attribute_overruns(r.lateness, r.ready, r.overrun_threshold)
            work_over = int(np.sum((cause == WORK) | (cause == WORK_BACKLOG)))
            lines.append(
                f"| {i + 1} | {w50 * 1e6:.1f} | {w99 * 1e6:.1f} | {100 * w99 / period:.1f} % | "
                f"{r.overruns} of {r.steps} | {work_over} = "
                f"{100 * work_over / max(r.steps, 1):.4f} % | {r.status} |"
            )
            print(lines[-1])
    if baseline:
        revs = [rev.strip() for rev in baseline.split(",")]
        extra: list[str] = []
        lines += ["", "| comparison | steps/s | result |", "|---|---|---|"]
        for i, rev in enumerate(revs):
            with baseline_tree(rev) as wt:
                _, row = one_channel_vs_baseline(rev, rounds, 5.0, pin, wt)
                lines.append(row)
                print(row)
                if i == 0:  # the first baseline also with the channels, lockstep and paced
                    extra = channels_vs_baseline(rev, wt, rounds, paced_runs, paced_s)
                    print("\n".join(extra))
        lines += extra
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="paced run length (s)")
    ap.add_argument("--floor", type=float, default=15.0, help="empty-loop floor length (s)")
    ap.add_argument("--lockstep-duration", type=float, default=20.0)
    ap.add_argument(
        "--priority", type=int, default=10, help="SCHED_FIFO priority for paced (0 = off)"
    )
    ap.add_argument("--skip-paced", action="store_true")
    ap.add_argument("--paced-only", action="store_true", help="only the paced runs (section 4)")
    ap.add_argument(
        "--cases",
        default="can@1024,modbus@1024,serial@1024,can@4096",
        help="paced cases, driver@fs, comma separated",
    )
    ap.add_argument(
        "--profile", metavar="DRIVER@FS", help="only a per-phase profile of one paced run"
    )
    ap.add_argument(
        "--lock",
        metavar="PATH",
        help="flock PATH around each timed measurement (each floor + run + floor separately)",
    )
    ap.add_argument(
        "--channels",
        action="store_true",
        help="only section 6 (1/2/4/8 channels) and write benchmarks/results/bench_loop.md",
    )
    ap.add_argument("--channels-paced", type=float, default=20.0, help="paced 4-channel run (s)")
    ap.add_argument("--paced-runs", type=int, default=3, help="paced 4-channel runs")
    ap.add_argument(
        "--baseline",
        metavar="REV",
        help="git revision(s), comma separated, to compare the single-channel lockstep rate "
        "with (same run)",
    )
    ap.add_argument("--rounds", type=int, default=5, help="alternations of the comparison")
    ap.add_argument(
        "--pin", type=int, default=None, metavar="CPU", help="run the comparison on this CPU"
    )
    args = ap.parse_args()
    print(
        f"# bench_loop — {time.strftime('%Y-%m-%d %H:%M')}, python {sys.version.split()[0]}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    )
    if args.channels:
        with bench_lock(args.lock):
            table = channels(
                10.0, args.channels_paced, args.baseline, args.rounds, args.pin, args.paced_runs
            )
        write_results(
            "bench_loop",
            table,
            goals="4 channels at 1024 Hz paced: loop work p99 ≤ 30 % of the period, "
            "work-caused overruns ≤ 0.01 %; lockstep ≥ 4 000 steps/s with 4 channels; one "
            "channel no slower than before the channels redesign (±5 %, same run).",
            command="python benchmarks/bench_loop.py --channels --baseline REV[,REV] --pin 1",
        )
        return
    if args.profile:
        name, fs = args.profile.split("@")
        profile(name, float(fs), args.duration, args.priority, args.lock)
        return
    cases = [(c.split("@")[0], float(c.split("@")[1])) for c in args.cases.split(",")]
    if not args.paced_only:
        if not args.skip_paced:
            with bench_lock(args.lock):
                floor(min(args.floor, 20.0), args.priority)
        with bench_lock(args.lock):
            breakdown()
            round_trips()
        with bench_lock(args.lock):
            lockstep(args.lockstep_duration)
    if not args.skip_paced:
        paced(args.duration, args.priority, args.floor, args.lock, cases)
    print(f"\nload average at the end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        main()

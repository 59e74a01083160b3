"""The fixed-step real-time hybrid simulation loop.

One loop ties together the numerical substructure (:class:`rths_hil.structure.CRStepper`), the
compensator (:mod:`rths_hil.compensation`), a bus driver (:mod:`drivers`) talking to a twin
(:mod:`sim_backends.twin`) or a real controller, the online evaluators (streaming and exact
:class:`rths_hil.fei.OnlineFEI`, :class:`rths_hil.estimation.DelayGainEstimator`), the safety
rules (:mod:`rths_hil.safety`) and the crash-safe recorder (:mod:`rths_hil.recorder`).

Step order
----------
Logically every step ``k`` is: integrate the structure with the measured restoring force (CR)
→ target ``x_t[k]`` → compensation ``x_c[k]`` → driver send → feedback (with timeout) → online
FEI and Kalman → safety → recorder. The CR algorithm is explicit in displacement (Chen & Ricles
2008): ``x[k+1]`` depends only on the state of step ``k``. The loop exploits this by rotating
the work so that the send is the first thing done at a deadline::

    deadline k:  send x_c[k] (already computed)            <- nothing before the send
                 receive feedback k (measured x_m[k], force f[k])
                 safety: watchdog, sequence, controller status, NaN, limits, stuck
                 CR: commit step k with f[k] -> x_t[k+1]; compensate -> x_c[k+1]
                 safety: x_t[k+1], v[k], x_c[k+1] checked *before* x_c[k+1] is ever sent
                 streaming FEI (every sample), exact FEI (every exact_hop), Kalman
                 safety: FEI rule, Kalman rule, overruns
                 recorder: row k
    deadline k+1: send x_c[k+1] ...

so the command leaves at the deadline with no computation in front of it, and the integration
uses the force measured at the displacement it imposed (no extra step of lag).

Modes
-----
``paced``
    Wall clock. The first deadline is 0.1 s after the start, deadline ``k`` is
    ``t0 + k·Δt`` (an absolute grid: no drift). The loop sleeps until ``spin`` before the
    deadline (at least 0.1 Δt when 0.2 Δt remain: a SCHED_FIFO thread that never sleeps is
    stopped ≈ 50 ms a second by the kernel's RT bandwidth limit), then busy-waits, then sends;
    ``lateness[k] = t_send − deadline`` is recorded, and ``ready[k]`` (when the previous step's
    work was done, minus the deadline) attributes each overrun to the machine or to the work
    (:func:`attribute_overruns`, measured against :func:`paced_floor`).
    **Overrun policy**: a step whose command leaves more than ``overrun_threshold·Δt`` after its
    deadline is an overrun. Steps are never skipped and the grid is never shifted (skipping
    would change the integration step; shifting would make the test slower than real time):
    after a long step the following ones start at once until the loop has caught up with the
    grid. ``safety.max_overruns`` consecutive overruns trip the e-stop. During a paced run the
    interpreter's thread switch interval is lowered to 100 µs (``sys.setswitchinterval``) so
    that the in-process twin, the exact-FEI worker and the loop hand the GIL over quickly, and
    the cyclic garbage collector is paused.
``lockstep``
    Virtual time: each step waits for its reply (loop.lockstep_timeout, 5 s of wall clock by
    default; none by then trips the watchdog) and starts the next one
    at once. Deterministic; for CI, tuning and what-if runs. Lateness is recorded as 0.

The exact-FEI cross-check runs synchronously in lockstep and in a worker thread when paced, so
its O(N log N) windows never sit on the step path.

On a trip (or an operator stop) the loop sends the e-stop through the driver, records the step
that tripped and the event (time, step, rule, values), confirms the latch with one status poll,
flushes the record and returns; the CLI prints one line and exits with 3 (130 for an operator
stop, SIGINT or SIGTERM).
"""

from __future__ import annotations

import array
import contextlib
import datetime as _dt
import gc
import logging
import math
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import Driver, Status
from drivers.registry import create_driver, driver_class

from . import groundmotion
from .compensation import AdaptiveAlpha, InverseCompensator
from .config import SCHEMA, Config, load_config
from .errors import InputError
from .fei import OnlineFEI
from .recorder import Recorder, RecordWriteError
from .safety import (
    ControllerRule,
    FEIRule,
    KalmanRule,
    OverrunRule,
    SafetyMonitor,
    SequenceRule,
    StuckRule,
    Trip,
    WatchdogRule,
)
from .structure import BoucWenParams, CRStepper

log = logging.getLogger(__name__)

__all__ = [
    "CAUSES",
    "RTHSLoop",
    "RunResult",
    "attribute_overruns",
    "build_ground_motion",
    "count_causes",
    "new_run_dir",
    "paced_floor",
    "run",
]

_ESTOP = int(Status.ESTOP_ACTIVE)
_LEAD_IN = 0.1  # s between the start of a paced run and its first deadline
# Paced: when the work leaves less than ``spin`` before the deadline, still sleep this fraction
# of a period if there is room for it (and as much again to spin). A SCHED_FIFO thread that
# never sleeps exhausts the kernel's RT bandwidth (sched_rt_runtime_us = 95 %; on Linux ≥ 6.12
# the fair server) and is stopped for ≈ 50 ms every second: at 4096 Hz with ≈ 170 µs of work
# per 244 µs period that alone made 18 % of the steps late (measured, 2026-11-22).
_MIN_SLEEP = 0.1


def new_run_dir(pattern: str, base: Path | None = None) -> Path:
    """Expand ``{timestamp}`` in ``pattern``; add a suffix if the directory already has a run."""
    if not str(pattern).strip():
        raise InputError("output.dir is empty: give a run directory such as 'runs/{timestamp}'")
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    p = Path(pattern.replace("{timestamp}", stamp)).expanduser()
    if base is not None and not p.is_absolute():
        p = base / p
    out, i = p, 1
    while any((out / f).exists() for f in ("record.npy", "events.jsonl", "meta.json")):
        out = p.with_name(f"{p.name}-{i}")
        i += 1
    return out


def build_ground_motion(cfg: Config) -> groundmotion.GroundMotion:
    """The configured record: loaded, PGA-scaled, padded with the tail, resampled to ``fs``."""
    g = cfg["ground_motion"]
    spec = g["record"]
    try:
        if spec == "default":
            gm = groundmotion.default_record()
        else:
            p = cfg.resolve_path(spec)
            gm = groundmotion.load(p) if p.is_file() else groundmotion.resolve(spec)
        if g["pga"] > 0:
            gm = gm.scaled(g["pga"])
        if g["tail"] > 0:
            gm = gm.padded(g["tail"])
        return gm.resampled(cfg["loop"]["fs"])
    except InputError as exc:
        raise InputError(f"{cfg.source}: ground_motion.record: {exc}") from None


# ----------------------------------------------------------------------------------------------
# online FEI helpers


class _StreamingFEI:
    """Per-sample streaming FEI (OnlineFEI ``method="streaming"``, hop 1).

    Uses :meth:`OnlineFEI.push`, the evaluator's one-sample fast path (no result arrays per
    call; :meth:`OnlineFEI.update` with a one-sample block allocates a result of seven arrays,
    ≈ 26 µs). :attr:`latest` holds the newest window's (amplitude, delay, f_eq, valid).
    """

    def __init__(self, fs: float, window_s: float) -> None:
        self.online = OnlineFEI(fs, window_s, hop=1, method="streaming")
        self.N = self.online.N
        self._push = self.online.push
        self.latest = (math.nan, math.nan, math.nan, False)

    def push(self, target: float, measured: float) -> bool:
        """Push one sample pair; True when a window completed (see :attr:`latest`)."""
        res = self._push(target, measured)
        if res is None:
            return False
        self.latest = res
        return True


_EXACT_RESULT = struct.Struct("<4dq")  # amplitude, delay, f_eq, valid (0/1), windows


def _exact_worker_main() -> None:  # pragma: no cover - runs in the worker process
    """Exact-FEI worker process: ``fs window_s hop`` in argv, blocks on stdin, results out.

    Each block is ``2·hop`` float64 (target then measured); each completed window is answered
    with one :data:`_EXACT_RESULT` record (the first record, with ``windows = -1``, says ready).
    End of input (the loop finished or was killed) ends the process.
    """
    fs, window_s, hop = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
    with contextlib.suppress(AttributeError, OSError):  # not under the loop's RT priority
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    online = OnlineFEI(fs, window_s, hop=hop, method="exact")
    warm = OnlineFEI(fs, window_s, hop=hop, method="exact")  # FFT plans and caches
    t = np.arange(online.N + hop) / fs
    warm.update(np.sin(6.0 * t), np.sin(6.0 * t - 0.1))
    out = sys.stdout.buffer
    out.write(_EXACT_RESULT.pack(math.nan, math.nan, math.nan, 0.0, -1))
    out.flush()
    size = 16 * hop
    inp = sys.stdin.buffer
    windows = 0
    while True:
        data = inp.read(size)
        if len(data) < size:
            return
        xy = np.frombuffer(data, dtype=float)
        res = online.update(xy[:hop], xy[hop:])
        if len(res):
            windows += len(res)
            out.write(
                _EXACT_RESULT.pack(
                    float(res.amplitude[-1]),
                    float(res.delay[-1]),
                    float(res.f_eq[-1]),
                    1.0 if res.valid[-1] else 0.0,
                    windows,
                )
            )
            out.flush()


class _ExactFEI:
    """Exact OnlineFEI at a coarse hop, fed in blocks of ``hop`` samples.

    ``background=False`` evaluates in the caller (lockstep: deterministic).
    ``background=True`` (paced) writes each block to a worker *process* through a pipe and
    reads its results (non-blocking) when it hands over the next block, so the window's FFT work
    (≈ 0.5 ms at N = 4 k) never runs on the step path. A worker thread is not good enough: it
    holds the GIL during its numpy calls and the loop thread then waits for the GIL after each
    reply (measured: 3.6 % → 8.5 % late steps at 1024 Hz). :attr:`latest` holds the newest
    completed window (it lags the stream by up to one hop in the background mode).
    """

    def __init__(self, fs: float, window_s: float, hop: int, background: bool) -> None:
        self.hop = hop
        self._bxy = np.zeros(2 * hop)
        self._i = 0
        self.latest = (math.nan, math.nan, math.nan, False)
        self.windows = 0
        self.online = None
        self._proc: subprocess.Popen | None = None
        self._pending = b""
        if background:
            self._proc = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    "from rths_hil.loop import _exact_worker_main as m; m()",
                    repr(float(fs)),
                    repr(float(window_s)),
                    str(int(hop)),
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                bufsize=0,
                start_new_session=True,  # a terminal's Ctrl-C goes to the loop only
            )
            self._in = self._proc.stdin.fileno()
            self._out = self._proc.stdout.fileno()
            ready = self._proc.stdout.read(_EXACT_RESULT.size)  # blocks until warmed up
            if len(ready) != _EXACT_RESULT.size:
                raise RuntimeError("the exact-FEI worker process did not start")
            os.set_blocking(self._out, False)
        else:
            self.online = OnlineFEI(fs, window_s, hop=hop, method="exact")

    def _collect(self) -> None:
        try:
            data = os.read(self._out, 65536)
        except BlockingIOError:
            return
        buf = self._pending + data
        n = len(buf) // _EXACT_RESULT.size
        if n:
            a, d, f, v, w = _EXACT_RESULT.unpack_from(buf, (n - 1) * _EXACT_RESULT.size)
            self.latest = (a, d, f, v > 0.5)
            self.windows = w
        self._pending = buf[n * _EXACT_RESULT.size :]

    def push(self, target: float, measured: float) -> None:
        """Add one sample pair; evaluate (or hand over) each full block."""
        i = self._i
        b = self._bxy
        b[i] = target
        b[self.hop + i] = measured
        i += 1
        if i < self.hop:
            self._i = i
            return
        self._i = 0
        if self._proc is not None:
            self._collect()
            os.write(self._in, b.tobytes())
            return
        res = self.online.update(b[: self.hop], b[self.hop :])
        if len(res):
            self.windows += len(res)
            self.latest = (
                float(res.amplitude[-1]),
                float(res.delay[-1]),
                float(res.f_eq[-1]),
                bool(res.valid[-1]),
            )

    def close(self) -> None:
        """Stop the worker process (after it has evaluated what it was given)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()
            proc.wait(timeout=5.0)
            os.set_blocking(self._out, True)
            rest = self._pending + proc.stdout.read()
            n = len(rest) // _EXACT_RESULT.size
            if n:
                a, d, f, v, w = _EXACT_RESULT.unpack_from(rest, (n - 1) * _EXACT_RESULT.size)
                self.latest = (a, d, f, v > 0.5)
                self.windows = w
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
        finally:
            proc.stdout.close()


# ----------------------------------------------------------------------------------------------
# overrun attribution and the machine's own floor

#: Causes of a paced overrun, the codes :func:`attribute_overruns` returns.
ON_TIME, MACHINE, MACHINE_BACKLOG, WORK, WORK_BACKLOG = range(5)
CAUSES = ("on_time", "machine", "machine_backlog", "work", "work_backlog")


def attribute_overruns(lateness: np.ndarray, ready: np.ndarray, threshold: float) -> np.ndarray:
    """Attribute each paced overrun to the machine or to the loop's own work.

    Parameters
    ----------
    lateness : ndarray
        Per-step send time minus deadline (s), :attr:`RunResult.lateness`.
    ready : ndarray
        Per-step time at which the loop was ready to wait for the deadline (the previous
        step's work done) minus the deadline (s; < 0 when it had to wait),
        :attr:`RunResult.ready`.
    threshold : float
        Overrun threshold (s): a step is an overrun when ``lateness > threshold``.

    Returns
    -------
    ndarray of int8
        One code per step: :data:`ON_TIME`; :data:`MACHINE` — the loop was ready in time
        (``ready <= threshold``) but the wait (sleep, then spin) returned, or the send left,
        more than the threshold after the deadline: a stall that an empty loop suffers in the
        same way; :data:`WORK` — the previous step was sent in time but its work (reply,
        integration, evaluators, recorder, and whatever preempted them) ran past this step's
        threshold; :data:`MACHINE_BACKLOG` / :data:`WORK_BACKLOG` — ready late because the
        previous step was itself an overrun of that cause: the catch-up after it (steps are
        never skipped, see the overrun policy).

    Notes
    -----
    A stall of the machine that lands inside a step's work (rather than in its wait) counts
    as :data:`WORK`: the timestamps cannot tell it apart from slow work. Compare the counts
    with :func:`paced_floor` on the same machine, at the same rate and scheduling.
    """
    lat = np.asarray(lateness, dtype=float)
    rdy = np.asarray(ready, dtype=float)
    if lat.shape != rdy.shape:
        raise ValueError("lateness and ready must have the same length")
    over = lat > threshold
    cause = np.zeros(lat.size, dtype=np.int8)
    cause[over] = MACHINE
    backlog = np.flatnonzero(over & (rdy > threshold))
    for k in backlog.tolist():  # in order: a chain inherits the cause of its first step
        if k > 0 and over[k - 1]:
            cause[k] = (
                MACHINE_BACKLOG if cause[k - 1] in (MACHINE, MACHINE_BACKLOG) else (WORK_BACKLOG)
            )
        else:
            cause[k] = WORK
    return cause


def count_causes(cause: np.ndarray) -> dict[str, int]:
    """Overrun counts per cause of :func:`attribute_overruns` (``on_time`` left out)."""
    counts = np.bincount(np.asarray(cause, dtype=np.int64), minlength=len(CAUSES))
    return {name: int(counts[i]) for i, name in enumerate(CAUSES) if i != ON_TIME}


def paced_floor(
    fs: float,
    duration: float,
    spin: float = 3e-4,
    priority: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """The machine's own timing floor: the paced loop's wait with no work at all.

    Runs the same wait as a paced :class:`RTHSLoop` (absolute grid ``t0 + k·Δt``, sleep until
    ``spin`` before each deadline, then spin; switch interval 100 µs, GC paused, SCHED_FIFO
    ``priority`` when > 0 and permitted) for ``duration`` seconds and does nothing else.

    Parameters
    ----------
    fs : float
        Rate (Hz).
    duration : float
        Length (s).
    spin : float
        Busy-wait before each deadline (s); capped at 0.4 Δt like the loop's.
    priority : int
        SCHED_FIFO priority (0: leave the scheduler alone).

    Returns
    -------
    lateness, ready : ndarray
        As :attr:`RunResult.lateness` and :attr:`RunResult.ready`: feed them to
        :func:`attribute_overruns` (every overrun of an empty loop is the machine's).
    """
    if not (fs > 0 and duration > 0):
        raise InputError(f"paced_floor: fs and duration must be > 0, got {fs}, {duration}")
    dt = 1.0 / fs
    spin = min(spin, 0.4 * dt)
    min_sleep = _MIN_SLEEP * dt
    n = max(1, round(duration * fs))
    lat_list = [0.0] * n
    ready_list = [0.0] * n
    perf = time.perf_counter
    sleep = time.sleep
    old_sched = None
    if priority > 0:
        try:
            old_sched = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (AttributeError, PermissionError, OSError) as exc:
            old_sched = None
            log.info("paced_floor: cannot set SCHED_FIFO priority %d (%s)", priority, exc)
    old_switch = sys.getswitchinterval()
    gc_was = gc.isenabled()
    sys.setswitchinterval(1e-4)
    gc.collect()
    gc.disable()
    try:
        t0 = perf() + _LEAD_IN
        for k in range(n):
            deadline = t0 + k * dt
            now = perf()
            gap = deadline - now
            ready_list[k] = -gap
            rem = gap - spin
            if rem < min_sleep and gap > 2.0 * min_sleep:
                rem = min_sleep
            if rem > 0:
                sleep(rem)
                now = perf()
            while now < deadline:
                now = perf()
            lat_list[k] = now - deadline
    finally:
        sys.setswitchinterval(old_switch)
        if gc_was:
            gc.enable()
        if old_sched is not None:
            os.sched_setscheduler(0, old_sched[0], old_sched[1])
    return np.array(lat_list), np.array(ready_list)


def _p99(x: np.ndarray) -> float:
    """``np.percentile(x, 99)`` (linear interpolation) by a partial sort: ≈ 10× cheaper."""
    n = x.size
    pos = 0.99 * (n - 1)
    lo = int(pos)
    hi = min(lo + 1, n - 1)
    part = np.partition(x, (lo, hi))
    return float(part[lo] + (part[hi] - part[lo]) * (pos - lo))


# ----------------------------------------------------------------------------------------------
# results


@dataclass
class RunResult:
    """What a run did.

    Attributes
    ----------
    status : {"completed", "trip", "operator_stop"}
    steps : int
        Steps executed (rows recorded).
    planned_steps : int
        Steps the configuration asked for.
    trip : Trip or None
        The safety trip (``status == "trip"``) or the operator stop.
    run_dir : Path
        Where the record is.
    mode : str
        ``paced`` or ``lockstep``.
    fs : float
        Loop rate (Hz).
    wall_time : float
        Wall-clock duration of the stepping (s).
    lateness : ndarray
        Per-step lateness (s); zeros in lockstep.
    overruns : int
        Paced steps later than the overrun threshold.
    missed_replies : int
        Steps without a matching reply.
    estop_confirmed : bool or None
        Whether the controller reported the e-stop latched (None when no e-stop was sent).
    driver_stats, twin_stats : dict
        Counters of the driver and (if any) the twin.
    final_alpha : float
        α at the end (differs from the configured one with adaptive compensation).
    ready : ndarray
        Paced: per-step time at which the loop was ready to wait for the deadline (previous
        step's work done) minus the deadline (s; < 0: it waited); empty in lockstep.
    overrun_threshold : float
        Lateness above which a paced step is an overrun (s); NaN in lockstep.
    """

    status: str
    steps: int
    planned_steps: int
    trip: Trip | None
    run_dir: Path
    mode: str
    fs: float
    wall_time: float
    lateness: np.ndarray
    overruns: int
    missed_replies: int
    estop_confirmed: bool | None
    driver_stats: dict = field(default_factory=dict)
    twin_stats: dict = field(default_factory=dict)
    final_alpha: float = math.nan
    ready: np.ndarray = field(default_factory=lambda: np.zeros(0))
    overrun_threshold: float = math.nan

    @property
    def exit_code(self) -> int:
        """0 completed, 3 safety trip, 130 operator stop."""
        return {"completed": 0, "trip": 3, "operator_stop": 130}[self.status]

    @property
    def steps_per_second(self) -> float:
        """Steps per wall-clock second."""
        return self.steps / self.wall_time if self.wall_time > 0 else math.nan

    def overrun_causes(self) -> dict[str, int]:
        """Overruns per cause (:func:`attribute_overruns`): machine vs the loop's own work.

        Keys ``machine``, ``machine_backlog``, ``work``, ``work_backlog``; they add up to
        :attr:`overruns`. All zero in lockstep.
        """
        if self.mode != "paced" or self.ready.size != self.steps:
            return {name: 0 for name in CAUSES[1:]}
        cause = attribute_overruns(self.lateness[: self.steps], self.ready, self.overrun_threshold)
        return count_causes(cause)

    def lateness_stats(self) -> dict[str, float]:
        """p50, p99, p99.9 and max lateness (s) and the overrun count."""
        lat = self.lateness[: self.steps]
        if lat.size == 0:
            return {
                "p50": math.nan,
                "p99": math.nan,
                "p99.9": math.nan,
                "max": math.nan,
                "overruns": 0,
            }
        p50, p99, p999 = np.percentile(lat, [50, 99, 99.9])
        return {
            "p50": float(p50),
            "p99": float(p99),
            "p99.9": float(p999),
            "max": float(lat.max()),
            "overruns": int(self.overruns),
        }


# ----------------------------------------------------------------------------------------------
# the loop


class RTHSLoop:
    """A configured RTHS test, ready to :meth:`run`.

    Parameters
    ----------
    cfg : Config
        Resolved configuration (:func:`rths_hil.config.load_config`).
    run_dir : str or Path, optional
        Run directory; default from ``output.dir``.
    plant : Plant, optional
        Use this plant in the twin instead of building one from ``[twin]`` (tests, what-ifs).
    live : callable, optional
        Called with a status dict every ``loop.console`` seconds (the console line).
    mode : {"paced", "lockstep"}, optional
        Overrides ``loop.mode``.
    duration : float, optional
        Overrides ``loop.duration`` (s; 0 = whole record).

    Notes
    -----
    Construction validates and builds the numerical parts (record, structure, plant,
    compensation, evaluators, rules); :meth:`run` opens the twin, the driver and the recorder.
    """

    def __init__(
        self,
        cfg: Config,
        run_dir: str | Path | None = None,
        *,
        plant: Any = None,
        live: Callable[[dict], None] | None = None,
        mode: str | None = None,
        duration: float | None = None,
    ) -> None:
        self.cfg = cfg
        lp = cfg["loop"]
        self.mode = mode or lp["mode"]
        if self.mode not in ("paced", "lockstep"):
            raise InputError(f"mode must be 'paced' or 'lockstep', got {self.mode!r}")
        self.fs = float(lp["fs"])
        self.dt = 1.0 / self.fs
        dur = lp["duration"] if duration is None else float(duration)
        if not (math.isfinite(dur) and dur >= 0):
            raise InputError(f"duration must be >= 0 s, got {duration!r}")
        self.run_dir = Path(run_dir) if run_dir is not None else new_run_dir(cfg["output"]["dir"])
        self.live = live

        # ground motion, padded with zeros when the duration exceeds the record
        gm = build_ground_motion(cfg)
        ag = np.asarray(gm.accel, dtype=float)
        n = round(dur * self.fs) if dur > 0 else ag.size
        if n < 2:
            raise InputError(f"duration {dur:g} s is shorter than two steps at {self.fs:g} Hz")
        if n > ag.size:
            ag = np.concatenate([ag, np.zeros(n - ag.size)])
        self.ground_motion = gm
        self.ag = ag[:n].copy()
        self.n_steps = n

        # structure (seed Section 5: SDOF MRF with Bouc-Wen, CR integration)
        s = cfg["structure"]
        k_struct = s["mass"] * (2.0 * math.pi * s["fn"]) ** 2
        bw = None
        if s["bouc_wen"]:
            bw = BoucWenParams(
                x_y=s["x_y"],
                k_a=k_struct,
                eta=s["eta"],
                beta=s["beta"],
                gamma=s["gamma"],
                q=s["q"],
            )
        try:
            self.structure = CRStepper(
                s["mass"],
                s["damping"],
                k_struct,
                self.dt,
                bouc_wen=bw,
                k_specimen=s["k_specimen"],
                ag0=float(self.ag[0]),
            )
        except InputError as exc:
            raise InputError(f"{cfg.source}: structure: {exc}") from None

        # the driver must exist (and have a twin when one is asked for)
        name = cfg["driver"]["name"]
        try:
            driver_class(name)
        except InputError as exc:
            raise InputError(f"{cfg.source}: driver.name: {exc}") from None
        if cfg["twin"]["enabled"] and name not in ("can", "modbus", "serial"):
            raise InputError(
                f"{cfg.source}: twin.enabled: there is no twin for driver {name!r} (twins exist "
                "for can, modbus, serial); set twin.enabled = false to use the real controller"
            )

        # the twin's plant
        tw = cfg["twin"]
        self.twin_enabled = bool(tw["enabled"])
        self.plant = plant
        if self.twin_enabled and plant is None:
            self.plant = _build_plant(cfg, self.dt)
        self.faults = None
        if tw["faults"]:
            from sim_backends.faults import Faults

            try:
                self.faults = Faults.parse(tw["faults"])
            except InputError as exc:
                raise InputError(f"{cfg.source}: twin.faults: {exc}") from None

        # compensation
        c = cfg["compensation"]
        self.compensator = InverseCompensator(c["alpha"], c["amplitude"], c["enabled"])
        self.adaptive = None
        fe = cfg["fei"]
        if c["adaptive"] and c["enabled"]:
            self.adaptive = AdaptiveAlpha(
                self.compensator,
                self.dt,
                fe["pair"],
                c["time_constant"],
                c["rate"],
                c["alpha_min"],
                c["alpha_max"],
            )

        # evaluators
        self.window_s = cfg.window_s
        self.fei_pair = fe["pair"]
        self.stream_fei = _StreamingFEI(self.fs, self.window_s) if fe["enabled"] else None
        if self.stream_fei is not None and self.stream_fei.N > min(n, gm.npts):
            longer = "record" if gm.npts < n else "run"
            what = (
                f"FEI window fei.window = {self.window_s:g} s is longer than the {longer} "
                f"({min(n, gm.npts) / self.fs:g} s): no FEI window completes and the FEI rule "
                "never arms"
            )
            if self.stream_fei.N > gm.npts:  # longer than the whole record: can never work
                raise InputError(f"{cfg.source}: {what}")
            log.warning("%s", what)  # a short run asked for explicitly
        self.exact_hop = fe["exact_hop"] if fe["enabled"] else 0
        kc = cfg["kalman"]
        self.kalman = None
        self.kalman_pair = kc["pair"]
        self.kalman_every = kc["every"]
        if kc["enabled"]:
            from .estimation import DelayGainEstimator

            opts = dict(kc["options"])
            if kc["pair"] == "command":
                opts.setdefault(
                    "delay0",
                    min((self.compensator.alpha - 1.0) * self.dt, 0.09) if c["enabled"] else 0.0,
                )
            try:
                self.kalman = DelayGainEstimator(self.fs, **opts)
            except TypeError as exc:
                raise InputError(f"{cfg.source}: kalman.options: {exc}") from None
            except InputError as exc:
                raise InputError(f"{cfg.source}: kalman.options: {exc}") from None

        # safety
        sf = cfg["safety"]
        self.warmup_steps = round(sf["warmup"] * self.fs)
        self.monitor = SafetyMonitor(
            self.dt,
            displacement_limit=sf["displacement_limit"] or None,
            velocity_limit=sf["velocity_limit"] or None,
            force_limit=sf["force_limit"] or None,
            fei=(
                FEIRule(
                    sf["fei_amplitude_tol"] or math.inf,
                    sf["fei_delay_tol"] or math.inf,
                    sf["fei_consecutive"],
                )
                if fe["enabled"] and (sf["fei_amplitude_tol"] or sf["fei_delay_tol"])
                else None
            ),
            kalman=(
                KalmanRule(sf["kf_gain_min"], sf["kf_gain_max"], sf["kf_delay_max"] or math.inf)
                if kc["enabled"]
                else None
            ),
            watchdog=WatchdogRule(
                sf["watchdog_missed"],
                # paced: wall-clock time since the last good reply; lockstep: the generous
                # wall-clock bound of the wait for each reply (virtual time, deterministic)
                (sf["watchdog_timeout"] or sf["watchdog_missed"] * self.dt)
                if self.mode == "paced"
                else lp["lockstep_timeout"],
            ),
            sequence=SequenceRule(sf["max_sequence_gaps"]),
            overrun=OverrunRule(sf["max_overruns"]) if self.mode == "paced" else None,
            stuck=StuckRule(sf["stuck_steps"], sf["stuck_motion"]) if sf["stuck_steps"] else None,
            controller=ControllerRule() if sf["controller_status"] else None,
        )

        # timing
        if self.mode == "paced":
            self.timeout = lp["feedback_timeout"] or 0.8 * self.dt
        else:  # lockstep waits for every reply, up to the wall-clock bound that trips
            self.timeout = lp["lockstep_timeout"]
        # never spin through a whole period: a SCHED_FIFO thread that never sleeps is stopped by
        # Linux's RT throttling (95 % of a CPU) for 50 ms every second
        self.spin = min(lp["spin"], 0.4 * self.dt)
        self.overrun_threshold = lp["overrun_threshold"] * self.dt
        self.heartbeat_steps = round(lp["heartbeat"] * self.fs) if lp["heartbeat"] > 0 else 0
        self.console_interval = lp["console"]

        self.twin = None  # the running twin endpoint (kept after the run for inspection)
        self.driver: Driver | None = None
        self.result: RunResult | None = None
        self._stop_signal: str | None = None

    # ------------------------------------------------------------------------------------------
    def _open_transport(self, stack: contextlib.ExitStack) -> Driver:
        cfg = self.cfg
        name = cfg["driver"]["name"]
        conn = dict(cfg["driver"]["connection"])
        if self.twin_enabled:
            from sim_backends.twin import start_twin

            # Over the in-process virtual CAN bus, serve the twin from this thread (same frames,
            # codecs and controller; no thread hand-off and GIL contention twice per step).
            inline = (
                self.cfg["twin"]["inline"]
                and name == "can"
                and conn.get("interface", "virtual") == "virtual"
            )
            try:
                self.twin = start_twin(
                    name,
                    self.plant,
                    faults=self.faults,
                    threaded=not inline,
                    # lockstep is virtual time: a stalled bridge is not a dead one
                    heartbeat_timeout=(cfg["twin"]["watchdog"] or None)
                    if self.mode == "paced"
                    else None,
                    **conn,
                )
            except InputError as exc:
                raise InputError(f"{cfg.source}: driver.connection: {exc}") from None
            stack.callback(self.twin.stop)
            conn = dict(self.twin.connection)
        try:
            driver = create_driver(name, **conn)
        except InputError as exc:
            raise InputError(f"{cfg.source}: driver: {exc}") from None
        except TypeError as exc:
            raise InputError(f"{cfg.source}: driver.connection: {exc}") from None
        driver.open()
        stack.callback(driver.close)
        self.driver = driver
        return driver

    def _realtime(self, stack: contextlib.ExitStack, priority: int) -> None:
        """SCHED_FIFO for this thread (and the threads it starts: twin, exact-FEI worker)."""
        try:
            old = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (AttributeError, PermissionError, OSError) as exc:
            explicit = priority != SCHEMA["loop"]["priority"].default
            (log.warning if explicit else log.info)(
                "cannot set SCHED_FIFO priority %d (%s); running without", priority, exc
            )
            return
        stack.callback(os.sched_setscheduler, 0, old[0], old[1])

    def _install_signals(self, stack: contextlib.ExitStack) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def handler(signum, frame):
            if self._stop_signal is not None:  # second Ctrl-C: give up at once
                raise KeyboardInterrupt
            self._stop_signal = signal.Signals(signum).name

        for sig in (signal.SIGINT, signal.SIGTERM):
            old = signal.signal(sig, handler)
            stack.callback(signal.signal, sig, old)

    def run(self) -> RunResult:
        """Run the test; return a :class:`RunResult` (never raises on a safety trip)."""
        cfg = self.cfg
        with contextlib.ExitStack() as stack:
            self._install_signals(stack)
            if self.mode == "paced" and cfg["loop"]["priority"] > 0:
                self._realtime(stack, cfg["loop"]["priority"])
            driver = self._open_transport(stack)
            rec = Recorder(
                self.run_dir,
                self.fs,
                config=cfg.as_dict(),
                flush_interval=cfg["output"]["flush_interval"],
                extra_meta={
                    "config_source": cfg.source,
                    "mode": self.mode,
                    "planned_steps": self.n_steps,
                    "ground_motion": {
                        "name": self.ground_motion.name,
                        "source": self.ground_motion.source,
                        "pga": self.ground_motion.pga,
                    },
                    "driver": cfg["driver"]["name"],
                    "twin": self.twin.connection if self.twin is not None else None,
                    "window_s": self.window_s,
                    "fei_pair": self.fei_pair,
                },
            )
            stack.callback(rec.close)
            exact = None
            if self.stream_fei is not None and self.exact_hop > 0:
                exact = _ExactFEI(
                    self.fs, self.window_s, self.exact_hop, background=self.mode == "paced"
                )
                stack.callback(exact.close)
            self._warm_up()
            rec.event(
                "start",
                0.0,
                0,
                mode=self.mode,
                fs=self.fs,
                steps=self.n_steps,
                rules=self.monitor.rules,
            )
            # a new run on the controller: restart its sequence count, acknowledge a latch
            armed = driver.arm(max(self.timeout, 0.5), self._receiver(driver))
            rec.event(
                "arm", 0.0, 0, replied=armed is not None,
                status=None if armed is None else int(armed.status),
            )  # fmt: skip
            result = self._loop(driver, rec, exact)
            if result.status == "completed":
                try:  # the last rows: a write failure here is still a safety event
                    rec.flush()
                except RecordWriteError as exc:
                    result.status = "trip"
                    result.trip = Trip("record", str(exc)).at(result.steps * self.dt, result.steps)
                    rec.event("trip", **dict(list(result.trip.as_event().items())[1:]))
            if result.status != "completed":
                result.estop_confirmed = self._estop(driver, rec, result)
            ls = result.lateness_stats()
            result.driver_stats = driver.stats.as_dict()
            if self.twin is not None:
                result.twin_stats = self.twin.stats.as_dict()
            rec.event(
                "end",
                result.steps * self.dt,
                result.steps,
                status=result.status,
                wall_duration=result.wall_time,
                steps_per_second=result.steps_per_second,
                lateness=ls,
                overrun_causes=result.overrun_causes(),
                missed_replies=result.missed_replies,
                estop_confirmed=result.estop_confirmed,
                driver_stats=result.driver_stats,
                twin_stats=result.twin_stats,
                final_alpha=result.final_alpha,
                exact_windows=exact.windows if exact is not None else 0,
            )
        self.result = result
        return result

    def _warm_up(self) -> None:
        """Compile and touch the evaluators on throwaway instances before the clock starts.

        The streaming FEI kernel is numba-compiled on its first call (hundreds of ms) and the
        exact FEI's FFT plans are built on first use; neither may happen at a deadline.
        """
        if self.stream_fei is not None:
            tmp = _StreamingFEI(self.fs, self.window_s)
            for i in range(4):
                tmp.push(math.sin(i), math.cos(i))
            if self.exact_hop > 0:
                ex = OnlineFEI(self.fs, self.window_s, hop=self.exact_hop, method="exact")
                t = np.arange(self.stream_fei.N + self.exact_hop) / self.fs
                ex.update(np.sin(6.0 * t), np.sin(6.0 * t - 0.1))

    def _receiver(self, driver: Driver):
        """``driver.receive``, preceded by serving an inline twin (lockstep over virtual CAN)."""
        twin = self.twin
        if twin is None or not getattr(twin, "inline", False):
            return driver.receive
        pump, recv = twin.pump, driver.receive

        def receive(timeout: float):
            pump()
            return recv(timeout)

        return receive

    def _estop(self, driver: Driver, rec: Recorder, result: RunResult) -> bool | None:
        """Send the e-stop, then poll once to see the controller report it latched."""
        driver.estop()
        with contextlib.suppress(RecordWriteError):  # already a trip; keep what was flushed
            rec.flush()
        # One status poll: a new command with enable=True is ignored by a latched controller
        # (it holds position) and answered with ESTOP_ACTIVE. enable=False would acknowledge
        # (clear) the latch, so it is not used here.
        seq = result.steps  # the next sequence number: no gap for the controller
        try:
            driver.send(seq, self._last_command, True)
            fb = self._receiver(driver)(0.2)
        except InputError:
            fb = None
        confirmed = fb is not None and bool(fb.status & _ESTOP)
        rec.event(
            "estop",
            result.steps * self.dt,
            result.steps - 1,
            confirmed=confirmed,
            status=None if fb is None else int(fb.status),
        )
        if not confirmed:
            log.warning("e-stop sent but not confirmed by the controller")
        return confirmed

    # ------------------------------------------------------------------------------------------
    def _loop(self, driver: Driver, rec: Recorder, exact: _ExactFEI | None) -> RunResult:
        n = self.n_steps
        dt = self.dt
        fs = self.fs
        paced = self.mode == "paced"
        ag = array.array("d", self.ag)  # floats on indexing, 8 B each (a list: 32 B each)
        st = self.structure
        comp = self.compensator
        mon = self.monitor
        adaptive = self.adaptive
        sfei = self.stream_fei
        kal = self.kalman

        # bound methods
        send = driver.send
        receive = self._receiver(driver)
        heartbeat = driver.heartbeat
        cr_step = st.step
        comp_step = comp.step
        check_feedback = mon.check_feedback
        check_command = mon.check_command
        check_fei = mon.check_fei
        check_kalman = mon.check_kalman
        check_overrun = mon.check_overrun
        append = rec.append
        fei_push = sfei.push if sfei is not None else None
        exact_push = exact.push if exact is not None else None
        adapt = adaptive.update if adaptive is not None else None
        if kal is not None:
            kal_push, kal_predict, kal_correct = kal.push, kal.predict, kal.correct
            kal_update = kal.update
        kal_every = self.kalman_every
        fei_target = self.fei_pair == "target"
        kal_target = self.kalman_pair == "target"
        warm = self.warmup_steps
        timeout = self.timeout
        spin = self.spin
        min_sleep = _MIN_SLEEP * dt
        thr = self.overrun_threshold
        hb_steps = self.heartbeat_steps
        perf = time.perf_counter
        sleep = time.sleep
        nan = math.nan

        # lateness in a C double array: the console's p99 reads it as an ndarray without a copy
        # of the list (converting 2 k Python floats and np.percentile cost ≈ 240 µs per console
        # line on this VM, a whole 4096 Hz period; this way ≈ 15 µs)
        lat_list = array.array("d", [0.0]) * n  # no n-byte temporary
        lat_view = np.frombuffer(lat_list, dtype=float)
        ready_list = [0.0] * n if paced else None
        console = self.console_interval if self.live is not None else 0.0
        next_console = math.inf

        # state of step 0
        x_t = st.x  # target of step k
        alpha = comp.alpha
        comp.reset(x_t)
        c = comp_step(x_t)  # command of step k
        trip = mon.check_command(0.0, 0, x_t, st.v, c)
        meas = 0.0
        force = 0.0
        a_fei = d_fei = f_fei = nan
        v_fei = False
        a_ex = d_ex = nan
        v_ex = False
        kf_g = kf_d = nan
        overruns = 0
        missed = 0
        pk_disp = pk_vel = pk_force = 0.0
        status = "completed"
        k = 0
        old_switch = sys.getswitchinterval()
        gc_was = gc.isenabled()
        if paced:
            sys.setswitchinterval(1e-4)
        gc.collect()
        gc.disable()
        t_start = perf()
        t0 = t_start + (_LEAD_IN if paced else 0.0)
        # wall-clock time of deadline 0: row k was sent at wall_t0 + k·Δt + lateness[k]
        rec.event("clock", 0.0, 0, wall_t0=time.time() + (t0 - perf()))
        if console > 0:
            next_console = t_start + console
            last_console_k, last_console_t = 0, t_start
        lat = 0.0
        was_over = False
        try:
            while k < n and trip is None:
                if self._stop_signal is not None:
                    status = "operator_stop"
                    trip = Trip("operator", f"operator stop ({self._stop_signal})").at(k * dt, k)
                    rec.event("operator_stop", k * dt, k, signal=self._stop_signal)
                    break
                tk = k * dt
                # ---- wait for the deadline, then send at once -------------------------------
                if paced:
                    deadline = t0 + tk
                    now = perf()
                    gap = deadline - now
                    ready_list[k] = -gap  # > 0: the previous step's work ran past the deadline
                    rem = gap - spin
                    if rem < min_sleep and gap > 2.0 * min_sleep:
                        rem = min_sleep  # give the CPU away every period (RT bandwidth limit)
                    if rem > 0:
                        sleep(rem)
                        now = perf()
                    while now < deadline:
                        now = perf()
                    send(k, c, True)
                    lat = now - deadline
                    lat_list[k] = lat
                else:
                    send(k, c, True)
                # ---- feedback ----------------------------------------------------------------
                fb = receive(timeout)
                if fb is not None:
                    ok = True
                    meas = fb.displacement
                    force = fb.force
                    trip = check_feedback(tk, k, True, k, fb.seq, fb.status, c, meas, force)
                else:
                    ok = False
                    missed += 1
                    trip = check_feedback(tk, k, False, k, -1, 0, c, meas, force)
                if hb_steps and k % hb_steps == 0:
                    heartbeat()
                # ---- structure: commit step k with the measured force, next target -------------
                v = st.v
                if trip is None:
                    if k > 0:
                        x_next = cr_step(ag[k], force)
                    else:
                        x_next = st.x_next
                    v = st.v
                    alpha = comp.alpha
                    c_next = comp_step(x_next)
                    trip = check_command(tk, k, x_next, v, c_next)
                else:
                    x_next = x_t
                    c_next = c
                # ---- evaluators -------------------------------------------------------------
                if fei_push is not None:
                    if fei_push(x_t if fei_target else c, meas):
                        a_fei, d_fei, f_fei, v_fei = sfei.latest
                        if adapt is not None:
                            adapt(d_fei, v_fei)
                        if trip is None and k >= warm:
                            trip = check_fei(tk, k, a_fei, d_fei, v_fei)
                    if exact_push is not None:
                        exact_push(x_t if fei_target else c, meas)
                        a_ex, d_ex, _, v_ex = exact.latest
                if kal is not None:
                    u = x_t if kal_target else c
                    if kal_every == 1:
                        kf_g, kf_d = kal_update(u, meas)
                        kal_new = True
                    else:
                        kal_push(u, meas)
                        kal_predict()
                        kal_new = k % kal_every == 0
                        if kal_new:
                            kal_correct()
                            kf_g, kf_d = kal.gain, kal.delay
                    if kal_new and trip is None and k >= warm:
                        trip = check_kalman(tk, k, kf_g, kf_d)
                if paced:
                    over = lat > thr
                    if over:
                        overruns += 1
                    # the rule counts consecutive overruns: nothing to tell it while none
                    if (over or was_over) and trip is None:
                        trip = check_overrun(tk, k, over, lat)
                    was_over = over
                # ---- record ----------------------------------------------------------------
                append(
                    tk,
                    k,
                    ag[k],
                    x_t,
                    c,
                    meas,
                    force,
                    v,
                    st.restoring_force,
                    alpha,
                    a_fei,
                    d_fei,
                    f_fei,
                    v_fei,
                    a_ex,
                    d_ex,
                    v_ex,
                    kf_g,
                    kf_d,
                    lat,
                    ok,
                    k,
                )
                a = -x_t if x_t < 0 else x_t
                if a > pk_disp:
                    pk_disp = a
                a = -v if v < 0 else v
                if a > pk_vel:
                    pk_vel = a
                a = -force if force < 0 else force
                if a > pk_force:
                    pk_force = a
                self._last_command = c
                k += 1
                x_t = x_next
                c = c_next
                if console > 0:
                    now = perf()
                    if now >= next_console:
                        rate = (k - last_console_k) / (now - last_console_t)
                        recent = lat_view[last_console_k:k]
                        self.live(
                            {
                                "t": tk,
                                "k": k,
                                "n": n,
                                "rate": rate,
                                "p99_lateness": _p99(recent) if paced and recent.size else 0.0,
                                "overruns": overruns,
                                "amplitude": a_fei,
                                "delay": d_fei,
                                "valid": v_fei,
                                "peak_displacement": pk_disp,
                                "margin": mon.margin(pk_disp, pk_vel, pk_force),
                                "alpha": comp.alpha,
                                "mode": self.mode,
                            }
                        )
                        last_console_k, last_console_t = k, now
                        next_console = now + console
            wall = perf() - t_start
        except RecordWriteError as exc:  # disk full or gone: a safety event, not a crash
            wall = perf() - t_start
            trip = Trip("record", str(exc), values={"rows_on_disk": rec.rows}).at(k * dt, k)
            self._last_command = c
            k += 1  # step k was sent and answered; only its row is lost
        except BaseException:
            with contextlib.suppress(Exception):
                driver.estop()
                if self.twin is not None and getattr(self.twin, "inline", False):
                    self.twin.pump()
            rec.event("error", k * dt, k, error=repr(sys.exc_info()[1]))
            raise
        finally:
            sys.setswitchinterval(old_switch)
            if gc_was:
                gc.enable()
            if not hasattr(self, "_last_command"):
                self._last_command = c
        if trip is not None and status != "operator_stop":
            status = "trip"
            self._last_command = c if k == 0 else self._last_command
            rec.event("trip", **{k2: v2 for k2, v2 in trip.as_event().items() if k2 != "kind"})
        lateness = lat_view[:k]  # a view: keeps lat_list alive, no copy
        ready = np.array(ready_list[:k], dtype=float) if paced else np.zeros(0)
        return RunResult(
            status=status,
            steps=k,
            planned_steps=n,
            trip=trip,
            run_dir=self.run_dir,
            mode=self.mode,
            fs=fs,
            wall_time=wall,
            lateness=lateness,
            overruns=overruns,
            missed_replies=missed,
            estop_confirmed=None,
            final_alpha=comp.alpha,
            ready=ready,
            overrun_threshold=thr if paced else math.nan,
        )


def _build_plant(cfg: Config, dt: float):
    from sim_backends.modelfile import load_plant

    tw = cfg["twin"]
    if tw["model"]:
        path = cfg.resolve_path(tw["model"])
        try:
            return load_plant(path, dt)
        except InputError as exc:
            raise InputError(f"{cfg.source}: twin.model: {exc}") from None
    spec: dict[str, Any] = {"actuator": dict(tw["actuator"])}
    if tw["specimen"]:
        spec["specimen"] = dict(tw["specimen"])
    if tw["sensor"]:
        spec["sensor"] = dict(tw["sensor"])
    try:
        return load_plant(spec, dt)
    except InputError as exc:
        raise InputError(f"{cfg.source}: twin.{exc}") from None


def run(
    config: str | Path | Config | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    **kwargs: Any,
) -> RunResult:
    """Load a configuration (path, :class:`Config` or the embedded default) and run it.

    ``kwargs`` go to :class:`RTHSLoop` (``run_dir``, ``plant``, ``live``, ``mode``,
    ``duration``).
    """
    cfg = config if isinstance(config, Config) else load_config(config, overrides)
    return RTHSLoop(cfg, **kwargs).run()

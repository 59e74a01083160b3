"""Can this computer hold the loop's rate? ``rths-hil check-host [CONFIG]``.

Two parts:

Timing (:func:`measure`)
    As ``cyclictest`` of the rt-tests suite does (docs/references.md): one thread — SCHED_FIFO at
    ``loop.priority`` when the limits allow it, else the normal scheduler — pinned to
    ``loop.cpu`` when one is named, wakes at absolute deadlines one loop period apart for N
    seconds (sleeping, no spinning) and records how late each wake-up is. The lateness
    percentiles and the longest stall are what the host adds to every step before the loop can
    even send its commands.
The host (:func:`host_facts`)
    Kernel (PREEMPT_RT: ``uname -v`` or ``/sys/kernel/realtime``), isolated CPUs
    (``/sys/devices/system/cpu/isolated``) and ``nohz_full``, the kernel command line, the
    frequency governor of each CPU, SMT, the real-time priority limit (``RLIMIT_RTPRIO``) and
    whether SCHED_FIFO was granted.

Verdict (:func:`verdict`) for a configuration's rate ``fs``: a paced step is an overrun when
its command leaves more than ``loop.overrun_threshold`` periods after its deadline; the loop
sleeps until ``loop.spin`` before the deadline and spins the rest, so a wake-up may be up to
``spin + overrun_threshold / fs`` late before it costs an overrun (the *budget*). The host

* **holds** the rate when at most 0.1 % of the wake-ups exceed the budget and the longest stall
  is below half of ``safety.max_overruns`` periods (the run's overrun trip);
* is **marginal** when more wake-ups exceed the budget but no stall reaches the trip;
* **cannot hold** it when a stall as long as the trip occurred (a paced run would stop itself).

The margin is the budget over the p99.9 lateness. The loop's own work per step (structure,
evaluators, driver) comes on top: ``benchmarks/bench_loop.py`` measures it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import resource
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "MIN_DURATION",
    "HostFacts",
    "Timing",
    "cache_path",
    "host_facts",
    "measure",
    "verdict",
]

#: Shortest measurement that gives a verdict (s): a second of wake-ups at the loop's rate.
MIN_DURATION = 1.0


@dataclass
class Timing:
    """Wake-up lateness of a periodic thread (s)."""

    period: float
    duration: float
    wakeups: int
    p50: float
    p99: float
    p999: float
    max: float
    fifo: bool
    priority: int
    cpu: int
    lateness: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    def as_dict(self) -> dict[str, Any]:
        """Without the samples."""
        d = asdict(self)
        d.pop("lateness")
        return d


@dataclass
class HostFacts:
    """What the kernel and the CPUs say about real-time use."""

    kernel: str
    preempt_rt: bool
    isolated: str
    nohz_full: str
    cmdline: str
    governors: dict[str, int]
    smt: str
    rtprio_limit: str
    cpus: int


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def host_facts() -> HostFacts:
    """Read the kernel's real-time facts (module docstring)."""
    uname = platform.uname()
    version = uname.version
    rt_flag = _read("/sys/kernel/realtime")
    preempt_rt = "PREEMPT_RT" in version or rt_flag == "1"
    governors: dict[str, int] = {}
    for cpu in sorted(Path("/sys/devices/system/cpu").glob("cpu[0-9]*")):
        g = _read(str(cpu / "cpufreq" / "scaling_governor"))
        if g is not None:
            governors[g] = governors.get(g, 0) + 1
    smt = _read("/sys/devices/system/cpu/smt/active")
    soft, hard = resource.getrlimit(resource.RLIMIT_RTPRIO)

    def lim(v: int) -> str:
        return "unlimited" if v == resource.RLIM_INFINITY else str(v)

    return HostFacts(
        kernel=f"{uname.release} {version}",
        preempt_rt=preempt_rt,
        isolated=_read("/sys/devices/system/cpu/isolated") or "",
        nohz_full=_read("/sys/devices/system/cpu/nohz_full") or "",
        cmdline=_read("/proc/cmdline") or "",
        governors=governors,
        smt={"1": "on", "0": "off"}.get(smt or "", "unknown"),
        rtprio_limit=f"soft {lim(soft)}, hard {lim(hard)}",
        cpus=os.cpu_count() or 1,
    )


def measure(
    period: float,
    duration: float,
    priority: int = 0,
    cpu: int = -1,
    stop: Callable[[], bool] | None = None,
) -> Timing:
    """Wake a thread every ``period`` s for ``duration`` s; record each wake-up's lateness.

    Parameters
    ----------
    period : float
        Wake-up period (s): the loop's ``1 / fs``.
    duration : float
        Measurement time (s).
    priority : int
        SCHED_FIFO priority to ask for (0: the normal scheduler). Refused (no permission):
        the normal scheduler, reported in :attr:`Timing.fifo`.
    cpu : int
        CPU to pin the thread to (-1: any).
    stop : callable, optional
        Asked at every wake-up; True ends the measurement early (an operator stop): the
        :class:`Timing` then holds the wake-ups measured so far.
    """
    n = max(1, round(duration / period))
    lat = np.empty(n)
    state: dict[str, Any] = {"fifo": False, "done": n}

    def body() -> None:
        if priority > 0:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
                state["fifo"] = True
            except (PermissionError, OSError, AttributeError):
                state["fifo"] = False
        if cpu >= 0:
            os.sched_setaffinity(0, {cpu})
        perf = time.perf_counter
        sleep = time.sleep
        t0 = perf() + 0.05
        for i in range(n):
            if stop is not None and stop():
                state["done"] = i
                return
            deadline = t0 + i * period
            gap = deadline - perf()
            if gap > 0:
                sleep(gap)
            lat[i] = perf() - deadline

    th = threading.Thread(target=body, name="rths-check-host", daemon=True)
    th.start()
    while th.is_alive():  # the main thread stays free for the signal handlers
        th.join(0.1)
    n = max(1, int(state["done"]))
    if state["done"] == 0:
        lat[0] = 0.0
    lat = np.maximum(lat[:n], 0.0)
    p50, p99, p999 = np.percentile(lat, [50, 99, 99.9])
    return Timing(
        period=period,
        duration=n * period,
        wakeups=n,
        p50=float(p50),
        p99=float(p99),
        p999=float(p999),
        max=float(lat.max()),
        fifo=state["fifo"],
        priority=priority if state["fifo"] else 0,
        cpu=cpu,
        lateness=lat,
    )


def verdict(
    timing: Timing,
    fs: float,
    spin: float,
    overrun_threshold: float,
    max_overruns: int,
) -> tuple[str, str, dict[str, float]]:
    """``(word, line, figures)`` for a loop at ``fs`` on this host (module docstring)."""
    period = 1.0 / fs
    budget = min(spin, 0.4 * period) + overrun_threshold * period
    lat = timing.lateness
    over = float(np.mean(lat > budget)) if lat.size else math.nan
    trip = max_overruns * period
    margin = budget / timing.p999 if timing.p999 > 0 else math.inf
    if timing.max >= trip:
        word = "cannot hold"
    elif over > 1e-3 or timing.max >= 0.5 * trip:
        word = "marginal"
    else:
        word = "holds"
    line = (
        f"host {word} {fs:g} Hz: wake-up lateness p99 {timing.p99 * 1e6:.0f} µs, p99.9 "
        f"{timing.p999 * 1e6:.0f} µs, longest stall {timing.max * 1e3:.2f} ms "
        f"(budget {budget * 1e6:.0f} µs, margin ×{margin:.2g}; {100 * over:.3f} % of wake-ups "
        f"over it; overrun trip at {trip * 1e3:.0f} ms; "
        f"{'SCHED_FIFO' if timing.fifo else 'normal scheduler'})"
    )
    figures = {
        "budget": budget,
        "over_fraction": over,
        "margin": margin,
        "trip_stall": trip,
    }
    return word, line, figures


def cache_path() -> Path:
    """Where the last verdict is kept (``$RTHS_HIL_CACHE`` or ``~/.cache/rths-hil``)."""
    base = os.environ.get("RTHS_HIL_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "rths-hil"
    )
    return Path(base) / "check-host.json"


def save_verdict(line: str, word: str, fs: float) -> None:
    """Keep the verdict for ``rths-hil run`` to print at start-up (never raises)."""
    path = cache_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        data = {"line": line, "word": word, "fs": fs, "time": time.time()}
        path.write_text(json.dumps(data), encoding="utf-8")
    except OSError as exc:
        log.info("cannot keep the check-host verdict in %s: %s", path, exc)


def cached_verdict() -> dict[str, Any] | None:
    """The last saved verdict, or None."""
    try:
        return json.loads(cache_path().read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def facts_lines(f: HostFacts, t: Timing | None = None) -> list[str]:
    """The host facts as report lines."""
    gov = ", ".join(f"{g} × {n}" for g, n in f.governors.items()) or "not exposed"
    lines = [
        f"kernel: {f.kernel} — {'PREEMPT_RT' if f.preempt_rt else 'not PREEMPT_RT'}",
        f"isolated CPUs: {f.isolated or 'none'}; nohz_full: {f.nohz_full or 'none'}",
        f"CPUs: {f.cpus}; SMT: {f.smt}; frequency governor: {gov}",
        f"RLIMIT_RTPRIO: {f.rtprio_limit}",
    ]
    if t is not None:
        sched = f"SCHED_FIFO {t.priority}" if t.fifo else "normal scheduler (SCHED_FIFO refused)"
        where = f"CPU {t.cpu}" if t.cpu >= 0 else "any CPU"
        lines.append(
            f"measured: {t.wakeups} wake-ups every {t.period * 1e6:.0f} µs over {t.duration:.1f} "
            f"s, {sched}, {where}"
        )
    return lines

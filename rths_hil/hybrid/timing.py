"""Pacing of the loop and overrun attribution (paced mode).

The paced wait itself (absolute grid ``t0 + k·Δt``, sleep until ``spin`` before the deadline,
then busy-wait) is :class:`~.pacer.Pacer`; here: the machine's own floor (:func:`paced_floor`,
the same wait with no work) and the attribution of each overrun to the machine or to the
loop's work (:func:`attribute_overruns`).
See ``docs/loop.md``.
"""

from __future__ import annotations

import gc
import logging
import os
import sys
import time

import numpy as np

from ..errors import InputError
from .pacer import MIN_SLEEP, PHASE_LEAD, Pacer, first_deadline

log = logging.getLogger(__name__)

__all__ = [
    "CAUSES",
    "MACHINE",
    "MACHINE_BACKLOG",
    "MACHINE_IN_WORK",
    "MIN_SLEEP",
    "ON_TIME",
    "PHASE_LEAD",
    "WORK",
    "WORK_BACKLOG",
    "attribute_overruns",
    "count_causes",
    "first_deadline",
    "paced_floor",
]

LEAD_IN = 0.1  # s between the start of paced_floor's stepping and its first deadline


#: Causes of a paced overrun, the codes :func:`attribute_overruns` returns.
ON_TIME, MACHINE, MACHINE_BACKLOG, WORK, WORK_BACKLOG, MACHINE_IN_WORK = range(6)
CAUSES = ("on_time", "machine", "machine_backlog", "work", "work_backlog", "machine_in_work")


def attribute_overruns(
    lateness: np.ndarray,
    ready: np.ndarray,
    threshold: float,
    stalled: np.ndarray | None = None,
) -> np.ndarray:
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
    stalled : ndarray, optional
        Per-step time the loop's thread was taken off the CPU inside the step (send, replies,
        work, record) without blocking (s), :attr:`RunResult.stalled`: the wall time minus the
        thread's CPU time, 0 when the thread blocked (a voluntary context switch: a wait for a
        reply, for the interpreter lock, for I/O). Without it no overrun is
        :data:`MACHINE_IN_WORK`.

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
        never skipped, see the overrun policy); :data:`MACHINE_IN_WORK` — a :data:`WORK`
        overrun that the machine caused inside the work: the thread was preempted (another
        task, the hypervisor) and without that time the work was done within the threshold
        (``ready[k] - stalled[k - 1] <= threshold``); its catch-up is :data:`MACHINE_BACKLOG`.

    Notes
    -----
    In a step where the thread blocked at all (waited for a controller's reply, for another
    thread of the bridge, for I/O) a stall stays :data:`WORK`: the thread's clock cannot tell
    a slow controller or the bridge's own threads from the machine there. Compare the counts
    with :func:`paced_floor` on the same machine, at the same rate and scheduling.
    """
    lat = np.asarray(lateness, dtype=float)
    rdy = np.asarray(ready, dtype=float)
    if lat.shape != rdy.shape:
        raise ValueError("lateness and ready must have the same length")
    over = lat > threshold
    cause = np.zeros(lat.size, dtype=np.int8)
    cause[over] = MACHINE
    st = None if stalled is None else np.asarray(stalled, dtype=float)
    if st is not None and st.shape != lat.shape:
        raise ValueError("stalled must have the length of lateness")
    backlog = np.flatnonzero(over & (rdy > threshold))
    for k in backlog.tolist():  # in order: a chain inherits the cause of its first step
        if k > 0 and over[k - 1]:
            machine = cause[k - 1] in (MACHINE, MACHINE_BACKLOG, MACHINE_IN_WORK)
            cause[k] = MACHINE_BACKLOG if machine else WORK_BACKLOG
        elif st is not None and k > 0 and rdy[k] - st[k - 1] <= threshold:
            cause[k] = MACHINE_IN_WORK  # in time but for the preemption inside step k-1's work
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
    pacer = Pacer.for_loop(1.0 / fs, spin)  # the loop's own wait (spin capped at 0.4 Δt)
    n = max(1, round(duration * fs))
    lat_list = [0.0] * n
    ready_list = [0.0] * n
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
        pacer.t0 = time.perf_counter() + LEAD_IN
        wait = pacer.wait
        for k in range(n):
            now = wait(k)
            ready_list[k] = pacer.ready
            lat_list[k] = now - pacer.due
    finally:
        sys.setswitchinterval(old_switch)
        if gc_was:
            gc.enable()
        if old_sched is not None:
            os.sched_setscheduler(0, old_sched[0], old_sched[1])
    return np.array(lat_list), np.array(ready_list)


def p99(x: np.ndarray) -> float:
    """``np.percentile(x, 99)`` (linear interpolation) by a partial sort: ≈ 10× cheaper."""
    n = x.size
    pos = 0.99 * (n - 1)
    lo = int(pos)
    hi = min(lo + 1, n - 1)
    part = np.partition(x, (lo, hi))
    return float(part[lo] + (part[hi] - part[lo]) * (pos - lo))

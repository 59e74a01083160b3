"""What a run did: :class:`RunResult`, returned by every run (completed, tripped or stopped)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..safety import Trip
from .timing import CAUSES, attribute_overruns, count_causes

__all__ = ["RunResult"]


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
        The safety trip (``status == "trip"``) or the operator stop; ``trip.channel`` names
        the channel whose rule fired.
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
        Steps without a matching reply (summed over the channels).
    estop_confirmed : bool or None
        Whether every controller reported the e-stop latched (None when no e-stop was sent).
    driver_stats, twin_stats : dict
        Counters of the driver and (if any) the twin; with several channels, one dict per
        channel name.
    final_alpha : float
        α at the end (first channel; differs from the configured one with adaptive
        compensation).
    ready : ndarray
        Paced: per-step time at which the loop was ready to wait for the deadline (previous
        step's work done) minus the deadline (s; < 0: it waited); empty in lockstep.
    overrun_threshold : float
        Lateness above which a paced step is an overrun (s); NaN in lockstep.
    work : ndarray
        Per-step time of the loop's own work (s): from the last reply to the end of the step's
        record (structure, compensation, evaluators, safety, recorder).
    stalled : ndarray
        Paced: per step, the time the loop's thread was taken off the CPU from the step's send
        to the end of its record without blocking (s): that wall time minus the thread's CPU
        time (``time.thread_time``), 0 when the thread made a voluntary context switch (waited
        for a reply, for the interpreter lock, for I/O); empty in lockstep. A preemption by
        another task or the hypervisor, see :func:`~rths_hil.hybrid.timing.attribute_overruns`.
    channels : list of str
        Channel names.
    stalls : list of tuple
        Paced: each stall of the bridge itself as ``(step, length in s)``
        (:class:`~rths_hil.safety.StallRule`).
    handback : bool or None
        After a completed run or an operator stop: whether every controller confirmed it was
        disabled and not latched (:mod:`.phases`); None when the run ended in an e-stop.
    start_steps : int
        Steps of the start ramp before step 0 (0: the actuators were already at the first
        command, or offset mode).
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
    work: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stalled: np.ndarray = field(default_factory=lambda: np.zeros(0))
    channels: list = field(default_factory=list)
    stalls: list = field(default_factory=list)
    handback: bool | None = None
    start_steps: int = 0

    @property
    def exit_code(self) -> int:
        """0 completed, 3 safety trip, 130 operator stop."""
        return {"completed": 0, "trip": 3, "operator_stop": 130}[self.status]

    @property
    def steps_per_second(self) -> float:
        """Steps per wall-clock second."""
        return self.steps / self.wall_time if self.wall_time > 0 else math.nan

    def overrun_causes(self) -> dict[str, int]:
        """Overruns per cause (:func:`~rths_hil.hybrid.timing.attribute_overruns`).

        Keys ``machine``, ``machine_backlog``, ``work``, ``work_backlog``,
        ``machine_in_work``; they add up to :attr:`overruns`. All zero in lockstep.
        """
        if self.mode != "paced" or self.ready.size != self.steps:
            return {name: 0 for name in CAUSES[1:]}
        stalled = self.stalled if self.stalled.size == self.steps else None
        cause = attribute_overruns(
            self.lateness[: self.steps], self.ready, self.overrun_threshold, stalled
        )
        return count_causes(cause)

    def stall_summary(self) -> dict[str, float]:
        """Count, longest and total length (s) of the run's stalls, for the end event."""
        lengths = [s for _, s in self.stalls]
        return {
            "count": len(lengths),
            "longest": max(lengths, default=0.0),
            "total": sum(lengths),
        }

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
        p50, p99_, p999 = np.percentile(lat, [50, 99, 99.9])
        return {
            "p50": float(p50),
            "p99": float(p99_),
            "p99.9": float(p999),
            "max": float(lat.max()),
            "overruns": int(self.overruns),
        }

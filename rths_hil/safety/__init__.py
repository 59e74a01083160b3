"""Safety: the rules that trip the e-stop, the monitor that checks them, and each channel's set.

* :mod:`rths_hil.safety.rules` — one small object per rule (limits, FEI, stability, Kalman,
  watchdog, stall, sequence, controller status, overrun, stuck) with a cheap per-sample check;
* :mod:`rths_hil.safety.monitor` — :class:`SafetyMonitor`, a channel's configured rules asked at
  fixed points of each step, returning the first trip;
* :mod:`rths_hil.safety.channels` — the rules of every channel asked once per phase of a step.
"""

from .monitor import SafetyMonitor
from .rules import (
    ControllerRule,
    FEIRule,
    KalmanRule,
    LimitRule,
    OverrunRule,
    SequenceRule,
    StabilityRule,
    StallRule,
    StuckRule,
    Trip,
    WatchdogRule,
)

__all__ = [
    "ControllerRule",
    "FEIRule",
    "KalmanRule",
    "LimitRule",
    "OverrunRule",
    "SafetyMonitor",
    "SequenceRule",
    "StabilityRule",
    "StallRule",
    "StuckRule",
    "Trip",
    "WatchdogRule",
]

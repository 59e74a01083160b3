"""Safety: the rules that trip the e-stop, the monitor that checks them, and each channel's set.

* :mod:`rths_hil.safety.rules` — one small object per rule (limits, FEI, stability, Kalman,
  watchdog, stall, sequence, controller status, overrun, stuck) with a cheap per-sample check;
* :mod:`rths_hil.safety.monitor` — :class:`SafetyMonitor`, a channel's configured rules asked at
  fixed points of each step, returning the first trip;
* :mod:`rths_hil.safety.channels` — the rules of every channel asked once per phase of a step.
"""

from . import rules
from .monitor import SafetyMonitor
from .rules import *  # noqa: F403 (the rules' public names, as asyncio re-exports its parts)

__all__ = ["SafetyMonitor", *rules.__all__]

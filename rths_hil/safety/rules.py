"""Safety rules and the monitor that trips the e-stop.

Every rule is a small object with a cheap per-sample ``check`` (a few float comparisons, no
allocation on the pass path) that returns ``None`` while all is well and a :class:`Trip` when
it fires. A :class:`SafetyMonitor` owns the configured rules and is called by the real-time loop
at fixed points of each step; it returns the *first* trip (time, step, rule, reason, values) and
then stays tripped.

Rules (names as they appear in events and on the console):

``nan``
    A non-finite value (NaN or ±inf) in the target, command, measured displacement or force, or
    in a valid online estimate. Always on.
``displacement`` / ``velocity`` / ``force``
    ``|value| > limit``. Displacement is checked on the command *before it is sent* and on the
    target and measured displacement; velocity on the structure's velocity and on the measured
    velocity (backward difference over the steps since the previous reply); force on the
    measured specimen force.
``fei``
    :class:`FEIRule`: ``consecutive`` valid online FEI windows with
    ``|A − 1| > amplitude_tol`` or ``|d| > delay_tol`` (the FEI paper's Eq. 2.2, 2.5). Invalid
    windows neither trip nor reset the count.
``kalman``
    Kalman gain outside ``[gain_min, gain_max]`` or ``|delay| > delay_max``.
``stability``
    :class:`StabilityRule`: the energy stability indicator ``S`` of a channel
    (:mod:`rths_hil.stability`) above ``limit`` (``safety.stability = "trip"``). Its warning
    level is not a trip: each upward crossing is a ``stability`` event.
``watchdog``
    Controller silence: more than ``timeout`` seconds without a good reply while the bridge was
    running (paced runs, and the wall-clock bound of a lockstep run; stalls of the bridge itself
    do not count), or ``missed`` consecutive steps without a matching reply (lockstep). Missed
    replies within the limit are a degradation, not a fault: the loop holds the last good
    measurement, records the gap (a ``reply_gap`` event) and feeds the Kalman filter no
    held sample (``docs/loop.md``, "Missed replies").
``link``
    The driver found its transport closed or gone (:class:`rths_hil.drivers.base.LinkDown`: a
    closed socket or serial line, a stopped CAN reader, a CANopen heartbeat lost): trips at
    the first reply it costs, without waiting for the watchdog's limit. Always on.
``stall``
    :class:`StallRule`: the bridge itself did not run for longer than ``max_stall`` (paced).
``sequence``
    More than ``max_gaps`` sequence gaps: a reply whose echoed sequence number is not the one
    sent, or a reply flagged ``SEQ_GAP`` by the controller (a command went missing).
``controller``
    The reply's status word carries an alarm of the controller itself: ``ESTOP_ACTIVE``,
    ``FAULT`` or ``WATCHDOG`` (:class:`rths_hil.drivers.base.Status`).
``overrun``
    ``consecutive`` consecutive paced steps later than the overrun threshold.
``stuck``
    The measured displacement identical for ``steps`` consecutive replies while the command
    moved by more than ``motion`` (m) over the same steps (a frozen sensor or a stalled
    actuator).
``record``
    Not a rule of the monitor: the recorder could not write (disk full, file-size limit); the
    loop stops with an e-stop and keeps the rows already on disk (:mod:`rths_hil.records.recorder`).
``operator``
    Not a rule: the operator stop (Ctrl-C) uses the same path (see :mod:`rths_hil.hybrid`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from rths_hil.drivers.base import Status

from ..errors import InputError
from ..formats import json_safe
from ..units import positive_number

__all__ = [
    "ControllerRule",
    "FEIRule",
    "KalmanRule",
    "LimitRule",
    "OverrunRule",
    "SequenceRule",
    "StabilityRule",
    "StallRule",
    "StuckRule",
    "Trip",
    "WatchdogRule",
]

_isfinite = math.isfinite
_ALARM_BITS = int(Status.ESTOP_ACTIVE | Status.FAULT | Status.WATCHDOG)
_SEQ_GAP = int(Status.SEQ_GAP)


@dataclass(frozen=True)
class Trip:
    """A fired safety rule.

    Attributes
    ----------
    rule : str
        Rule name (``displacement``, ``fei``, ``watchdog`` …).
    reason : str
        One line naming the quantity, its value and the limit.
    time : float
        Loop time of the step that tripped, in s (NaN when not known to the rule).
    step : int
        Loop step index (-1 when not known to the rule).
    values : dict
        The quantities involved (name → value), for the event record.
    channel : str
        The channel (actuator) whose rule fired (``""``: the single channel or the whole loop).
    """

    rule: str
    reason: str
    time: float = math.nan
    step: int = -1
    values: dict[str, float] = field(default_factory=dict)
    channel: str = ""

    def at(self, time: float, step: int) -> Trip:
        """This trip stamped with the loop time and step."""
        return Trip(self.rule, self.reason, float(time), int(step), self.values, self.channel)

    def on(self, channel: str) -> Trip:
        """This trip attributed to ``channel``."""
        return Trip(self.rule, self.reason, self.time, self.step, self.values, channel)

    def as_event(self) -> dict:
        """JSON-ready event fields."""
        return {
            "kind": "trip",
            "rule": self.rule,
            "reason": self.reason,
            "time": self.time,
            "step": self.step,
            "channel": self.channel,
            "values": json_safe(dict(self.values), "name"),
        }


def _count(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _tolerance(value: Any, what: str) -> float:
    """A rule's tolerance: a number > 0, or 0 / ``inf`` for "this part of the rule is off"
    (the configuration's documented ``0 = off``), which is returned as ``inf``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number, got {value!r}") from None
    if v == 0.0 or v == math.inf:
        return math.inf
    return positive_number(v, what)


class LimitRule:
    """``|value| > limit`` on one quantity (displacement, velocity, force).

    Parameters
    ----------
    rule : str
        Rule name used in the trip (``displacement``, ``velocity``, ``force``).
    limit : float
        Limit in SI units (> 0).
    unit : str
        SI unit of the values; the reason shows displacements in mm, velocities in mm/s and
        forces in kN (what an operator reads), the trip's ``values`` stay SI.
    """

    __slots__ = ("limit", "rule", "unit")

    #: SI unit → (unit shown in the reason, scale)
    SHOWN: ClassVar[dict[str, tuple[str, float]]] = {
        "m": ("mm", 1e3),
        "m/s": ("mm/s", 1e3),
        "N": ("kN", 1e-3),
    }

    def __init__(self, rule: str, limit: float, unit: str) -> None:
        self.rule = rule
        self.limit = positive_number(limit, f"{rule} limit")
        self.unit = unit

    def check(self, quantity: str, value: float) -> Trip | None:
        """Trip when ``|value| > limit``; ``quantity`` names what was measured."""
        if -self.limit <= value <= self.limit:
            return None
        u, f = self.SHOWN.get(self.unit, (self.unit, 1.0))
        return Trip(
            self.rule,
            f"{quantity} {value * f:.6g} {u} exceeds the limit ±{self.limit * f:.6g} {u}",
            values={quantity: value, "limit": self.limit},
        )


class FEIRule:
    """E-stop on the online FEI: ``consecutive`` valid windows out of tolerance.

    A valid window is out of tolerance when ``|A − 1| > amplitude_tol`` or
    ``|d| > delay_tol`` (A and d per the FEI paper's Eq. 2.2 and 2.5). ``consecutive`` such windows
    in a row trip the rule; a valid window within tolerance resets the count; an invalid window (too
    little target energy, NaN values) neither trips nor resets it.

    Parameters
    ----------
    amplitude_tol : float
        Tolerance on ``|A − 1|`` (fraction, > 0); ``math.inf`` disables the amplitude check.
    delay_tol : float
        Tolerance on ``|d|`` in s (> 0); ``math.inf`` disables the delay check.
    consecutive : int
        Number of consecutive out-of-tolerance valid windows that trip (≥ 1).
    """

    __slots__ = ("amplitude_tol", "consecutive", "count", "delay_tol", "rule", "tripped")

    def __init__(self, amplitude_tol: float, delay_tol: float, consecutive: int = 1) -> None:
        self.rule = "fei"
        self.amplitude_tol = _tolerance(amplitude_tol, "FEI amplitude tolerance")
        self.delay_tol = _tolerance(delay_tol, "FEI delay tolerance")
        self.consecutive = _count("FEI consecutive windows", consecutive)
        self.count = 0
        self.tripped: Trip | None = None

    def reset(self) -> None:
        """Clear the count and a previous trip."""
        self.count = 0
        self.tripped = None

    def check(self, amplitude: float, delay: float, valid: bool) -> Trip | None:
        """Feed one window's estimate; return the trip on the ``consecutive``-th bad window."""
        if self.tripped is not None:
            return self.tripped
        if not valid or amplitude != amplitude or delay != delay:
            return None
        a_err = abs(amplitude - 1.0)
        d_abs = abs(delay)
        if a_err <= self.amplitude_tol and d_abs <= self.delay_tol:
            self.count = 0
            return None
        self.count += 1
        if self.count < self.consecutive:
            return None
        parts = []
        if d_abs > self.delay_tol:
            parts.append(f"delay d = {delay * 1e3:.3f} ms outside ±{self.delay_tol * 1e3:.3f} ms")
        if a_err > self.amplitude_tol:
            parts.append(f"amplitude A = {amplitude:.4f} outside 1 ± {self.amplitude_tol:.4g}")
        self.tripped = Trip(
            self.rule,
            "FEI " + " and ".join(parts) + f" for {self.count} consecutive valid windows",
            values={
                "amplitude": float(amplitude),
                "delay": float(delay),
                "amplitude_tol": self.amplitude_tol,
                "delay_tol": self.delay_tol,
                "consecutive": self.count,
            },
        )
        return self.tripped

    def update(self, amplitude, delay, valid) -> Trip | None:
        """Feed the estimates of several windows (arrays, or scalars); return the first trip.

        This is the form that takes an :class:`rths_hil.fei.OnlineFEI` ``update`` result
        (``result.amplitude, result.delay, result.valid``) directly.
        """
        a = np.atleast_1d(np.asarray(amplitude, dtype=float))
        d = np.atleast_1d(np.asarray(delay, dtype=float))
        v = np.atleast_1d(np.asarray(valid, dtype=bool))
        if not (a.shape == d.shape == v.shape) or a.ndim != 1:
            raise ValueError("amplitude, delay and valid must have the same length")
        check = self.check
        for ai, di, vi in zip(a.tolist(), d.tolist(), v.tolist(), strict=True):
            trip = check(ai, di, vi)
            if trip is not None:
                return trip
        return None


class StabilityRule:
    """The energy stability indicator's rule: a warning at ``warn``, a trip above ``limit``.

    Fed the channel's windowed ratio ``S`` every step (NaN: not valid, ignored). An upward
    crossing of ``warn`` sets :attr:`warning` (the ratio; the caller records it as an event
    and clears it); the rule is re-armed when ``S`` falls below ``0.9·warn``. With ``trip``
    a valid ``S`` above ``limit`` returns a :class:`Trip` whose reason names the channel and
    the figure.

    Parameters
    ----------
    warn, limit : float
        Warning and trip levels of ``S`` (> 0, ``limit ≥ warn``).
    trip : bool
        Trip above ``limit`` (``safety.stability = "trip"``); else only warn.
    channel : str
        The channel's name, for the reason (``""``: the actuator).
    """

    __slots__ = ("armed", "channel", "limit", "rule", "trip", "tripped", "warn", "warning")

    def __init__(self, warn: float, limit: float, trip: bool, channel: str = "") -> None:
        self.rule = "stability"
        self.warn = _tolerance(warn, "stability warning level")
        self.limit = _tolerance(limit, "stability limit")
        if self.limit < self.warn:
            raise InputError(
                f"safety.stability_limit ({self.limit:g}) is below safety.stability_warn "
                f"({self.warn:g})"
            )
        self.trip = bool(trip)
        self.channel = channel
        self.armed = True
        self.warning: float | None = None
        self.tripped: Trip | None = None

    def check(self, ratio: float, injected: float = math.nan) -> Trip | None:
        """Feed one step's ``S`` (and the energy injected so far, J, for the reason)."""
        if self.tripped is not None:
            return self.tripped
        if ratio != ratio:  # not valid
            return None
        if self.armed:
            if ratio > self.warn:
                self.armed = False
                self.warning = ratio
        elif ratio < 0.9 * self.warn:
            self.armed = True
        if self.trip and ratio > self.limit:
            who = f"channel {self.channel}" if self.channel else "the actuator"
            self.tripped = Trip(
                self.rule,
                f"stability indicator S = {ratio:.3g} on {who} above the limit "
                f"{self.limit:g}: the interface injects {ratio:.3g} times the energy the "
                "structure's damping dissipates",
                values={"ratio": float(ratio), "limit": self.limit, "injected": float(injected)},
            )
            return self.tripped
        return None


class KalmanRule:
    """Bounds on the Kalman estimator's gain and delay estimates (:mod:`rths_hil.estimation`).

    Parameters
    ----------
    gain_min, gain_max : float
        Allowed gain range.
    delay_max : float
        Allowed ``|delay|`` in s.
    """

    __slots__ = ("delay_max", "gain_max", "gain_min", "rule")

    def __init__(self, gain_min: float, gain_max: float, delay_max: float) -> None:
        self.rule = "kalman"
        if not (math.isfinite(gain_min) and math.isfinite(gain_max) and gain_min < gain_max):
            raise InputError(
                f"Kalman gain range must be finite with min < max, got [{gain_min}, {gain_max}]"
            )
        self.gain_min = float(gain_min)
        self.gain_max = float(gain_max)
        self.delay_max = _tolerance(delay_max, "Kalman delay limit")

    def check(self, gain: float, delay: float) -> Trip | None:
        """Trip when the gain leaves its range or the delay exceeds its limit."""
        if self.gain_min <= gain <= self.gain_max and -self.delay_max <= delay <= self.delay_max:
            return None
        if not (self.gain_min <= gain <= self.gain_max):
            reason = (
                f"Kalman gain estimate {gain:.4f} outside "
                f"[{self.gain_min:.4g}, {self.gain_max:.4g}]"
            )
        else:
            reason = (
                f"Kalman delay estimate {delay * 1e3:.3f} ms exceeds ±{self.delay_max * 1e3:.3f} ms"
            )
        return Trip(
            self.rule,
            reason,
            values={
                "kf_gain": gain,
                "kf_delay": delay,
                "gain_min": self.gain_min,
                "gain_max": self.gain_max,
                "delay_max": self.delay_max,
            },
        )


class WatchdogRule:
    """Feedback watchdog: controller silence while the bridge was running and looking.

    Two limits, either may be off:

    * ``timeout`` (s, paced runs): time since the last good reply during which the bridge was
      running, on the monotonic ``clock``. Time in which the bridge itself was not running — a
      stall of this process or of the computer, found by the loop and reported through
      :meth:`stalled` — does not count: the controller cannot be blamed for replies nobody
      was there to read. A good reply (one that echoes the command just sent) always resets
      the clock, however long after the previous one it came: a controller that answered the
      current command is not silent, and the gap is the loop's own stall (its rule is
      :class:`StallRule`).
    * ``missed`` consecutive steps without a matching reply (virtual time: what a lockstep run
      relies on; 0 = off).

    Parameters
    ----------
    missed : int
        Consecutive steps without a reply that trip (0 = no step limit).
    timeout : float or None
        Seconds of silence that trip (> 0), or ``None`` for the step count only.
    clock : callable
        Monotonic clock in seconds (default :func:`time.perf_counter`, the loop's clock).
    """

    __slots__ = ("clock", "count", "credit", "last_ok", "missed", "rule", "timeout")

    def __init__(
        self,
        missed: int,
        timeout: float | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.rule = "watchdog"
        self.missed = _count("watchdog missed replies", missed, minimum=0)
        self.timeout = None if timeout is None else positive_number(timeout, "watchdog timeout")
        if self.missed == 0 and self.timeout is None:
            raise InputError("watchdog: give a timeout (s) or a number of missed replies")
        self.clock = clock
        self.count = 0
        self.last_ok = math.nan
        self.credit = 0.0  # stalled time of the bridge since last_ok (s)

    def reset(self) -> None:
        """Forget the previous replies (the next check starts the clock)."""
        self.count = 0
        self.last_ok = math.nan
        self.credit = 0.0

    def stalled(self, start: float, end: float) -> None:
        """The bridge was not running from ``start`` to ``end`` (clock seconds): not silence.

        Only the part after the last good reply counts (a stall found late, after a reply that
        came when it ended, discounts nothing twice).
        """
        last = self.last_ok
        if last == last and end > start:
            self.credit += max(0.0, end - max(start, last))

    def check(self, ok: bool) -> Trip | None:
        """Feed whether this step got its reply (called once the receive has returned)."""
        timeout = self.timeout
        if timeout is not None:
            now = self.clock()
            if ok:
                self.last_ok = now
                self.credit = 0.0
            else:
                last = self.last_ok
                if last != last:  # first check: the clock starts now
                    last = self.last_ok = now
                silent = now - last - self.credit
                if silent > timeout:
                    self.count += 1
                    return Trip(
                        self.rule,
                        f"no good feedback for {silent * 1e3:.1f} ms while the bridge ran "
                        f"(limit {timeout * 1e3:.1f} ms, {self.count} missed steps"
                        + (
                            f"; {self.credit * 1e3:.1f} ms of bridge stall not counted)"
                            if self.credit > 0.0
                            else ")"
                        ),
                        values={
                            "elapsed": silent,
                            "timeout": timeout,
                            "missed": self.count,
                            "stalled": self.credit,
                        },
                    )
        if ok:
            self.count = 0
            return None
        self.count += 1
        if self.missed == 0 or self.count < self.missed:
            return None
        return Trip(
            self.rule,
            f"no feedback for {self.count} consecutive steps (limit {self.missed})",
            values={"missed": self.count, "limit": self.missed},
        )


class StallRule:
    """A stall of the bridge itself: the loop found a deadline long past (paced runs).

    A stall is a gap in the loop's own progress — this process or the computer did not run it
    (``SIGSTOP``, a host or hypervisor stall, swapping) — measured as the time between two
    sends beyond one period. It is not controller silence (:meth:`WatchdogRule.stalled`
    discounts it there). Below ``max_stall`` the test goes on and the stall is an event; above
    it the test trips with a reason that names the stall and the machine.

    Parameters
    ----------
    max_stall : float
        Longest stall (s) after which the test may go on.
    min_stall : float
        Shortest gap (s) reported as a stall (shorter ones are ordinary overruns).
    """

    __slots__ = ("count", "longest", "max_stall", "min_stall", "rule", "total")

    def __init__(self, max_stall: float, min_stall: float) -> None:
        self.rule = "stall"
        self.max_stall = positive_number(max_stall, "max_stall")
        self.min_stall = positive_number(min_stall, "min_stall")
        self.count = 0
        self.longest = 0.0
        self.total = 0.0

    def check(self, length: float) -> Trip | None:
        """Feed one stall of ``length`` seconds (≥ ``min_stall``, found by the loop)."""
        self.count += 1
        self.total += length
        if length > self.longest:
            self.longest = length
        if length <= self.max_stall:
            return None
        return Trip(
            self.rule,
            f"the bridge itself stalled for {length * 1e3:.1f} ms (limit "
            f"{self.max_stall * 1e3:.0f} ms): this computer did not run the loop; "
            "the controllers were not at fault",
            values={"stall": length, "max_stall": self.max_stall},
        )


class SequenceRule:
    """Sequence gaps: more than ``max_gaps`` gaps trip.

    A gap is a reply whose echoed sequence number is not the one sent, or a reply whose status
    carries the controller's ``SEQ_GAP`` flag (the controller saw a command go missing).
    """

    __slots__ = ("count", "max_gaps", "rule")

    def __init__(self, max_gaps: int) -> None:
        self.rule = "sequence"
        self.max_gaps = _count("maximum sequence gaps", max_gaps, minimum=0)
        self.count = 0

    def check(self, expected: int, received: int, controller_gap: bool = False) -> Trip | None:
        """Feed the sequence number sent, the one echoed and the controller's gap flag."""
        if expected == received and not controller_gap:
            return None
        self.count += 1
        if self.count <= self.max_gaps:
            return None
        if expected != received:
            what = f"reply sequence {received} where {expected} was expected"
        else:
            what = f"the controller reports a missing command before step {expected}"
        return Trip(
            self.rule,
            f"{what} ({self.count} gaps, limit {self.max_gaps})",
            values={
                "expected": expected,
                "received": received,
                "gaps": self.count,
                "limit": self.max_gaps,
            },
        )


class ControllerRule:
    """The controller's own alarms in the feedback status: e-stop latched, fault, watchdog.

    Parameters
    ----------
    mask : int
        Status bits that trip (default ``ESTOP_ACTIVE | FAULT | WATCHDOG`` of
        :class:`rths_hil.drivers.base.Status`).
    """

    __slots__ = ("mask", "rule")

    def __init__(self, mask: int | None = None) -> None:
        self.rule = "controller"
        self.mask = int(_ALARM_BITS if mask is None else mask)

    def check(self, status: int) -> Trip | None:
        """Feed the status word of a reply."""
        bad = status & self.mask
        if not bad:
            return None
        names = [b.name for b in Status if b & bad]
        return Trip(
            self.rule,
            f"controller status reports {', '.join(n for n in names if n)} (status 0x{status:02x})",
            values={"status": int(status)},
        )


class OverrunRule:
    """``consecutive`` consecutive overruns (paced steps later than the threshold) trip."""

    __slots__ = ("consecutive", "count", "rule")

    def __init__(self, consecutive: int) -> None:
        self.rule = "overrun"
        self.consecutive = _count("consecutive overruns", consecutive)
        self.count = 0

    def check(self, overrun: bool, lateness: float) -> Trip | None:
        """Feed whether this step overran and its lateness (s)."""
        if not overrun:
            self.count = 0
            return None
        self.count += 1
        if self.count < self.consecutive:
            return None
        return Trip(
            self.rule,
            f"{self.count} consecutive overruns (limit {self.consecutive}), "
            f"last step {lateness * 1e3:.3f} ms late",
            values={"overruns": self.count, "lateness": lateness, "limit": self.consecutive},
        )


class StuckRule:
    """A frozen measurement: identical for ``steps`` replies while the command moved.

    Parameters
    ----------
    steps : int
        Number of consecutive identical measured values (≥ 2).
    motion : float
        The command must have travelled more than this (m, sum of |Δcommand|) over those steps.
    """

    __slots__ = ("count", "last", "motion", "moved", "prev_cmd", "rule", "steps")

    def __init__(self, steps: int, motion: float) -> None:
        self.rule = "stuck"
        self.steps = _count("stuck-sensor steps", steps, minimum=2)
        self.motion = positive_number(motion, "stuck-sensor motion")
        self.count = 0
        self.moved = 0.0
        self.last = math.nan
        self.prev_cmd = math.nan

    def check(self, command: float, measured: float) -> Trip | None:
        """Feed this step's command and measured displacement (m)."""
        dc = command - self.prev_cmd
        self.prev_cmd = command
        if measured == self.last:
            self.count += 1
            if dc == dc:
                self.moved += abs(dc)
        else:
            self.last = measured
            self.count = 1
            self.moved = 0.0
            return None
        if self.count < self.steps or self.moved <= self.motion:
            return None
        return Trip(
            self.rule,
            f"measured displacement stuck at {measured:.6g} m for {self.count} steps while the "
            f"command moved {self.moved:.6g} m (limit {self.motion:.6g} m)",
            values={
                "measured": measured,
                "steps": self.count,
                "command_motion": self.moved,
                "motion_limit": self.motion,
            },
        )

"""The safety monitor: every configured rule of a channel, checked at fixed points of a step.

The rules are in :mod:`rths_hil.safety.rules`; the monitor owns them, is called by the
real-time loop and returns the first trip.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from ..units import positive_number
from .rules import (
    _SEQ_GAP,
    ControllerRule,
    FEIRule,
    KalmanRule,
    LimitRule,
    OverrunRule,
    SequenceRule,
    StabilityRule,
    StuckRule,
    Trip,
    WatchdogRule,
    _isfinite,
)

__all__ = ["SafetyMonitor"]


class SafetyMonitor:
    """All configured rules, checked at fixed points of each loop step.

    Parameters
    ----------
    dt : float
        Loop step (s), for the measured velocity.
    displacement_limit, velocity_limit, force_limit : float or None
        Limits in m, m/s, N; ``None`` disables the rule.
    fei : FEIRule or None
    kalman : KalmanRule or None
    watchdog : WatchdogRule or None
    sequence : SequenceRule or None
    overrun : OverrunRule or None
    stuck : StuckRule or None
    controller : ControllerRule or None
    stability : StabilityRule or None
    control : str
        The channel's ``control.mode``. ``"displacement"``: the target and the command are
        displacements, checked against the displacement limit. ``"force"`` or ``"load"``: they
        are forces, checked against the force limit, and the structure's trial displacement
        (:meth:`check_command`'s ``trial``) against the displacement limit; the measured
        displacement and force are checked in every mode; the stuck-sensor rule (command
        motion against measured motion, in m) does not apply to a force-controlled channel
        (a held load does not move).

    Notes
    -----
    Call order in a step (see :mod:`rths_hil.hybrid.runner`): :meth:`check_command` before the
    command is sent, :meth:`check_feedback` when the reply (or its absence) is known,
    :meth:`check_fei` and :meth:`check_kalman` with the estimates. Overruns belong to the whole
    loop, not to a channel: the runner keeps one :class:`OverrunRule` for all channels. Each returns
    the first :class:`Trip` (stamped with time and step) or ``None``; after a trip the monitor
    keeps returning it.
    """

    def __init__(
        self,
        dt: float,
        displacement_limit: float | None = None,
        velocity_limit: float | None = None,
        force_limit: float | None = None,
        fei: FEIRule | None = None,
        kalman: KalmanRule | None = None,
        watchdog: WatchdogRule | None = None,
        sequence: SequenceRule | None = None,
        overrun: OverrunRule | None = None,
        stuck: StuckRule | None = None,
        controller: ControllerRule | None = None,
        stability: StabilityRule | None = None,
        control: str = "displacement",
    ) -> None:
        self.dt = positive_number(dt, "time step")
        self.control = control
        self.force_mode = control != "displacement"
        inf = math.inf
        self._disp = (
            LimitRule("displacement", displacement_limit, "m") if displacement_limit else None
        )
        self._vel = LimitRule("velocity", velocity_limit, "m/s") if velocity_limit else None
        self._force = LimitRule("force", force_limit, "N") if force_limit else None
        self.disp_limit = self._disp.limit if self._disp else inf
        # the band a displacement relative to the start position may take: inside the limit,
        # and its absolute position (relative + offset) inside the limit too (set_offset)
        self.offset = 0.0
        self._d_lo, self._d_hi = -self.disp_limit, self.disp_limit
        self.vel_limit = self._vel.limit if self._vel else inf
        self.force_limit = self._force.limit if self._force else inf
        self.fei = fei
        self.kalman = kalman
        self.watchdog = watchdog
        self.sequence = sequence
        self.overrun = overrun
        self.stuck = stuck
        self.controller = controller
        self.stability = stability
        self.tripped: Trip | None = None
        self._prev_meas = math.nan
        self._prev_k = -1

    @property
    def rules(self) -> list[str]:
        """Names of the active rules."""
        names = ["nan"]
        for r in (
            self._disp,
            self._vel,
            self._force,
            self.fei,
            self.kalman,
            self.watchdog,
            self.sequence,
            self.overrun,
            None if self.force_mode else self.stuck,  # not on a force channel
            self.controller,
        ):
            if r is not None:
                names.append(r.rule)
        if self.stability is not None and self.stability.trip:  # a warning is no rule
            names.append(self.stability.rule)
        return names

    def set_offset(self, offset: float) -> None:
        """Displacements checked from now on are relative to ``offset`` (m), the start position
        of ``start.mode = "offset"``: each must stay inside the limit, and so must the absolute
        position ``value + offset`` (the actuator's stroke does not move with the test)."""
        self.offset = float(offset)
        lim = self.disp_limit
        self._d_lo = max(-lim, -lim - self.offset)
        self._d_hi = min(lim, lim - self.offset)

    def _disp_trip(self, quantity: str, value: float) -> Trip:
        """The displacement trip of ``value`` (relative), named absolute when only the
        absolute position ``value + offset`` is outside the limit."""
        rule = self._disp
        assert rule is not None
        trip = rule.check(quantity, value)
        if trip is None:
            absolute = value + self.offset
            trip = rule.check(f"absolute {quantity} (start position {self.offset * 1e3:+.6g} mm)",
                              absolute)  # fmt: skip
        assert trip is not None
        return trip

    @staticmethod
    def _limit_trip(rule: LimitRule | None, quantity: str, value: float) -> Trip:
        """The trip of ``rule`` for ``value`` outside its limit (the rule exists whenever its
        limit is finite, and only a finite limit can be exceeded)."""
        assert rule is not None
        trip = rule.check(quantity, value)
        assert trip is not None
        return trip

    def _fire(self, trip: Trip, t: float, k: int) -> Trip:
        self.tripped = trip.at(t, k)
        return self.tripped

    def _ask(
        self,
        rule: FEIRule | StabilityRule | KalmanRule | WatchdogRule | None,
        t: float,
        k: int,
        *values: Any,
    ) -> Trip | None:
        """``rule.check(*values)``, its trip stamped and kept; ``None`` without the rule."""
        if rule is None:
            return None
        trip = rule.check(*values)
        return None if trip is None else self._fire(trip, t, k)

    def _nan(self, t: float, k: int, names: Sequence[str], values: Sequence[float]) -> Trip:
        bad = [(n, v) for n, v in zip(names, values, strict=True) if not _isfinite(v)]
        reason = ", ".join(f"{n} = {v!r}" for n, v in bad)
        return self._fire(Trip("nan", f"non-finite value: {reason}", values=dict(bad)), t, k)

    def check_command(
        self, t: float, k: int, target: float, velocity: float, command: float, trial: float = 0.0
    ) -> Trip | None:
        """Before sending: the target, the structure's velocity and the command.

        A force-controlled channel's target and command are forces (N) and ``trial`` is the
        structure's displacement along it (m; class docstring).
        """
        if self.tripped is not None:
            return self.tripped
        if not _isfinite(target + velocity + command):
            return self._nan(t, k, ("target", "velocity", "command"), (target, velocity, command))
        if self.force_mode:
            return self._check_force_command(t, k, target, velocity, command, trial)
        lo, hi = self._d_lo, self._d_hi
        if not (lo <= command <= hi and lo <= target <= hi):
            q, v = ("command", command) if not (lo <= command <= hi) else ("target", target)
            return self._fire(self._disp_trip(q, v), t, k)
        lim = self.vel_limit
        if not (-lim <= velocity <= lim):
            return self._fire(self._limit_trip(self._vel, "velocity", velocity), t, k)
        return None

    def _check_force_command(
        self, t: float, k: int, target: float, velocity: float, command: float, trial: float
    ) -> Trip | None:
        """:meth:`check_command` of a force-controlled channel."""
        lim = self.force_limit
        if not (-lim <= command <= lim and -lim <= target <= lim):
            q, v = (
                ("commanded force", command)
                if not (-lim <= command <= lim)
                else ("target force", target)
            )
            return self._fire(self._limit_trip(self._force, q, v), t, k)
        if not _isfinite(trial):
            return self._nan(t, k, ("trial displacement",), (trial,))
        if not (self._d_lo <= trial <= self._d_hi):
            return self._fire(self._disp_trip("trial displacement", trial), t, k)
        lim = self.vel_limit
        if not (-lim <= velocity <= lim):
            return self._fire(self._limit_trip(self._vel, "velocity", velocity), t, k)
        return None

    def _silence(self, t: float, k: int, ok: bool, link_down: str | None) -> Trip | None:
        """The link and the watchdog (see :meth:`check_feedback`)."""
        if not ok and link_down is not None:
            reason = f"the link to the controller is down ({link_down})"
            return self._fire(Trip("link", reason), t, k)
        rule = self.watchdog  # (as _ask, without its call: every step)
        if rule is None:
            return None
        trip = rule.check(ok)
        return None if trip is None else self._fire(trip, t, k)

    def check_feedback(
        self,
        t: float,
        k: int,
        ok: bool,
        expected_seq: int,
        received_seq: int,
        status: int,
        command: float,
        measured: float,
        force: float,
        link_down: str | None = None,
    ) -> Trip | None:
        """After the reply: link, watchdog, sequence, controller status, NaN, limits, stuck.

        ``ok`` is False when no matching reply came within the timeout; then ``measured`` and
        ``force`` are the held previous values and only the link and the watchdog are checked:
        ``link_down`` (the driver's :attr:`~rths_hil.drivers.base.Driver.link_down`, why its
        transport is gone, or ``None``) trips the ``link`` rule at once. ``status`` is the
        reply's :class:`rths_hil.drivers.base.Status` word.
        """
        if self.tripped is not None:
            return self.tripped
        if not ok or self.watchdog is not None:
            trip = self._silence(t, k, ok, link_down)
            if trip is not None or not ok:
                return trip
        seq = self.sequence
        if seq is not None and (expected_seq != received_seq or status & _SEQ_GAP):
            trip = seq.check(expected_seq, received_seq, bool(status & _SEQ_GAP))
            if trip is not None:
                return self._fire(trip, t, k)
        ctl = self.controller
        if ctl is not None and status & ctl.mask:
            trip = ctl.check(status)
            if trip is not None:  # always: the status has a bit of the mask
                return self._fire(trip, t, k)
        if not _isfinite(measured + force):
            return self._nan(t, k, ("measured", "force"), (measured, force))
        if not (self._d_lo <= measured <= self._d_hi):
            return self._fire(self._disp_trip("measured displacement", measured), t, k)
        lim = self.force_limit
        if not (-lim <= force <= lim):
            return self._fire(self._limit_trip(self._force, "measured force", force), t, k)
        prev = self._prev_meas
        prev_k = self._prev_k
        self._prev_meas = measured
        self._prev_k = k
        lim = self.vel_limit
        if lim != math.inf and prev == prev and k > prev_k:
            # backward difference over the steps since the previous reply (missed replies
            # hold the measurement; its change is spread over the whole gap)
            v = (measured - prev) / ((k - prev_k) * self.dt)
            if not (-lim <= v <= lim):
                return self._fire(self._limit_trip(self._vel, "measured velocity", v), t, k)
        st = self.stuck
        if st is not None and not self.force_mode:
            trip = st.check(command, measured)
            if trip is not None:
                return self._fire(trip, t, k)
        return None

    def check_fei(
        self, t: float, k: int, amplitude: float, delay: float, valid: bool
    ) -> Trip | None:
        """One online FEI window estimate (invalid windows are ignored)."""
        if self.tripped is not None:
            return self.tripped
        if valid and not _isfinite(amplitude + delay):
            return self._nan(t, k, ("fei_amplitude", "fei_delay"), (amplitude, delay))
        return self._ask(self.fei, t, k, amplitude, delay, valid)

    def check_stability(
        self, t: float, k: int, ratio: float, injected: float = math.nan
    ) -> Trip | None:
        """The channel's energy stability indicator ``S`` of this step (NaN: not valid)."""
        if self.tripped is not None:
            return self.tripped
        rule = self.stability  # (as _ask, without its call: every step)
        if rule is None:
            return None
        trip = rule.check(ratio, injected)
        return None if trip is None else self._fire(trip, t, k)

    def check_kalman(self, t: float, k: int, gain: float, delay: float) -> Trip | None:
        """The Kalman estimator's gain and delay."""
        if self.tripped is not None:
            return self.tripped
        if not _isfinite(gain + delay):
            return self._nan(t, k, ("kf_gain", "kf_delay"), (gain, delay))
        rule = self.kalman  # (as _ask, without its call: every Kalman estimate)
        if rule is None:
            return None
        trip = rule.check(gain, delay)
        return None if trip is None else self._fire(trip, t, k)

    def margin(self, peak_displacement: float, peak_velocity: float, peak_force: float):
        """The nearest limit: ``(name, fraction of the limit still unused)`` (for the console)."""
        best = ("none", math.inf)
        for name, peak, lim in (
            ("displacement", peak_displacement, self.disp_limit),
            ("velocity", peak_velocity, self.vel_limit),
            ("force", peak_force, self.force_limit),
        ):
            if lim != math.inf:
                m = 1.0 - abs(peak) / lim
                if m < best[1]:
                    best = (name, m)
        return best

"""The safety rules of every channel, asked once per phase of a step.

The runner calls :class:`Safety` at fixed points of each step (``docs/loop.md``): after the
replies (:meth:`Safety.feedback`), before the next commands leave (:meth:`Safety.command`),
after the evaluators (:meth:`Safety.evaluators`) and, paced, with the step's lateness
(:meth:`Safety.timing`). The rules themselves are in :mod:`rths_hil.safety`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from ..hybrid.channel import Channel
from . import OverrunRule, Trip

__all__ = ["Safety"]


def _feedback(check: Callable[..., Trip | None], ch: Channel, t: float, k: int) -> Trip | None:
    """``check`` (a :meth:`~rths_hil.safety.SafetyMonitor.check_feedback`) on ``ch``'s reply."""
    return check(
        t,
        k,
        ch.feedback_ok,
        k,
        ch.reply_seq,
        ch.reply_status,
        ch.command,
        ch.measured,
        ch.force,
        ch.link_down,
    )


class Safety:
    """The safety rules of every channel, asked once per phase of a step.

    Each channel has its own :class:`~rths_hil.safety.SafetyMonitor` (its limits, watchdog,
    sequence, stuck sensor, FEI and Kalman rules); the overrun rule belongs to the loop. Every
    method returns the first fired :class:`~rths_hil.safety.Trip` (stamped with time, step and
    channel) or ``None``.
    """

    def __init__(self, channels: list[Channel], overrun: OverrunRule | None) -> None:
        self.channels = channels
        self.overrun = overrun
        self.tripped: Trip | None = None
        #: events for the record from the rules that warn (the stability indicator's
        #: crossings of its warning level): the runner writes and clears them each step
        self.events: list[dict] = []
        if len(channels) == 1:  # the same checks without the loop over channels (≈ 0.5 µs)
            self._ch = channels[0]
            self._check_feedback = channels[0].monitor.check_feedback
            self._check_command = channels[0].monitor.check_command
            self.feedback = self._feedback_one  # type: ignore[method-assign]
            self.command = self._command_one  # type: ignore[method-assign]

    def _feedback_one(self, t: float, k: int) -> Trip | None:
        ch = self._ch  # (as _feedback, without its call: the one-channel step's path)
        trip = self._check_feedback(
            t, k, ch.feedback_ok, k, ch.reply_seq, ch.reply_status, ch.command, ch.measured,
            ch.force, ch.link_down,
        )  # fmt: skip
        return None if trip is None else self.fire(trip, ch, t, k)

    def _command_one(self, t: float, k: int) -> Trip | None:
        ch = self._ch
        trip = self._check_command(
            t, k, ch.target_next, ch.velocity, ch.command_next, ch.trial_next
        )
        return None if trip is None else self.fire(trip, ch, t, k)

    def fire(self, trip: Trip, ch: Channel | None, t: float, k: int) -> Trip:
        """Stamp ``trip`` with time, step and channel (and a controller's fault text); keep it."""
        trip = trip.at(t, k) if trip.step < 0 else trip
        why = getattr(ch.driver, "fault_text", None) if ch is not None else None
        if trip.rule == "controller" and why is not None and why():  # e.g. a CANopen EMCY code
            trip = Trip(trip.rule, f"{trip.reason}; {why()}", trip.time, trip.step, trip.values)
        self.tripped = trip.on(ch.name) if ch is not None else trip
        return self.tripped

    @property
    def rules(self) -> dict[str, list[str]] | list[str]:
        """Active rules (per channel when there are several)."""
        extra = ["overrun"] if self.overrun is not None else []
        if len(self.channels) == 1:
            return self.channels[0].monitor.rules + extra
        out = {ch.name: ch.monitor.rules for ch in self.channels}
        if extra:
            out[""] = extra
        return out

    def command(self, t: float, k: int) -> Trip | None:
        """Before sending: each channel's next target, its velocity and its command (and a
        force-controlled channel's trial displacement)."""
        for ch in self.channels:
            trip = ch.monitor.check_command(
                t, k, ch.target_next, ch.velocity, ch.command_next, ch.trial_next
            )
            if trip is not None:
                return self.fire(trip, ch, t, k)
        return None

    def feedback(self, t: float, k: int) -> Trip | None:
        """After the replies: link, watchdog, sequence, controller status, NaN, limits, stuck."""
        for ch in self.channels:
            trip = _feedback(ch.monitor.check_feedback, ch, t, k)
            if trip is not None:
                return self.fire(trip, ch, t, k)
        return None

    def evaluators(self, t: float, k: int) -> Trip | None:
        """New FEI windows and Kalman estimates, and the stability indicator, of each channel.

        A crossing of the stability warning level is appended to :attr:`events`.
        """
        for ch in self.channels:
            ind = ch.stability_ind
            if ind is not None and k >= ch.warmup_steps:
                mon = ch.monitor
                trip = mon.check_stability(t, k, ch.stability, ind.injected)
                rule = mon.stability
                if rule is not None and rule.warning is not None:
                    self.events.append(
                        {
                            "channel": ch.name,
                            "ratio": rule.warning,
                            "level": rule.warn,
                            "injected": ind.injected,
                            "dissipated": ind.dissipated,
                        }
                    )
                    rule.warning = None
                if trip is not None:
                    return self.fire(trip, ch, t, k)
            if ch.fei_new:
                trip = ch.monitor.check_fei(t, k, ch.fei_amplitude, ch.fei_delay, ch.fei_valid)
                if trip is not None:
                    return self.fire(trip, ch, t, k)
            if ch.kalman_new:
                trip = ch.monitor.check_kalman(t, k, ch.kf_gain, ch.kf_delay)
                if trip is not None:
                    return self.fire(trip, ch, t, k)
        return None

    def timing(self, t: float, k: int, over: bool, lateness: float) -> Trip | None:
        """A paced step's overrun flag and lateness (the loop's rule, no channel)."""
        rule = self.overrun
        if rule is None:
            return None
        trip = rule.check(over, lateness)
        return None if trip is None else self.fire(trip, None, t, k)

    def margin(self) -> tuple[str, str, float]:
        """The channel nearest to a limit: ``(channel, quantity, unused fraction)``."""
        best = ("", "none", math.inf)
        for ch in self.channels:
            q, m = ch.monitor.margin(ch.peak_displacement, ch.peak_velocity, ch.peak_force)
            if m < best[2]:
                best = (ch.name, q, m)
        return best

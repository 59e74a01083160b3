"""Timing modes of the experimental site: how OpenSees' trials become actuator commands.

The loop calls :meth:`TimingMode.step` once per loop step ``k`` with the measurement of the
command it sent at step ``k`` and sends the returned command at step ``k + 1``; the actuator
never waits on OpenSees' schedule. A *target* is the trial whose forces OpenSees asked for
(:class:`rths_hil.openfresco.server.Target`); its measurement is handed back through the
:class:`~rths_hil.openfresco.server.Mailbox` at the first loop step whose command equals it.

:class:`Lockstep`
    Virtual time (loop ``mode = "lockstep"``): each target is executed by a linear ramp from
    the current command over the trial's time step (from the trial's time block, rounded to
    whole loop steps, at least one), the force measured at the end of the ramp is returned,
    then the loop waits for the next target. Deterministic; for CI and what-if runs.
:class:`PredictorCorrector`
    Real time (loop ``mode = "paced"``): the loop is the master at its own rate and a new
    target is due every ``k = element step / loop step`` loop steps. The command follows the
    structure's trajectory on a clock in structure time, ``c(s) = L(τ(s)) + e(s)``: ``L`` the
    Lagrange polynomial through the last targets (it extrapolates between targets: the
    *predictor*; a new target moves the point set on: the *corrector*), ``e`` the jump this
    makes, blended out with a cubic Hermite so command and slope stay continuous, after the
    predictor–corrector of Schellenberg, Mahin and Fenves (2009) and Mosqueda, Stojadinovic
    and Mahin (2007). The clock runs in real time and slows smoothly when OpenSees falls
    behind (to a hold by ``hold_after``, an e-stop past ``estop_after``); a measurement taken
    past a late target is corrected back to it with the stiffness estimate. Every loop step
    is recorded as executed, corrected, predicted, held or idle, and every target with
    OpenSees' latency (from the force reply to the next request). Details in the class.
:class:`RampHold`
    Slow continuous testing (loop ``mode = "paced"``): each target is reached by a linear ramp
    of ``ramp_time`` seconds, held ``hold_time`` seconds, then its force is returned; the
    actuator holds while OpenSees computes.

References
----------
A. Schellenberg, S. A. Mahin, G. L. Fenves, "Advanced implementation of hybrid simulation",
PEER Report 2009/104, Section 4.3 (predictor–corrector for continuous testing).
G. Mosqueda, B. Stojadinovic, S. A. Mahin, "Real-time error monitoring for hybrid simulation.
Part I: Methodology and experimental verification", J. Struct. Eng. 133(8), 1100–1108, 2007.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from .server import Mailbox, Target

__all__ = [
    "CORRECTED",
    "EXECUTED",
    "HELD",
    "IDLE",
    "KINDS",
    "PREDICTED",
    "Lockstep",
    "PredictorCorrector",
    "RampHold",
    "SiteFault",
    "TimingMode",
    "make_timing",
]

IDLE, EXECUTED, PREDICTED, CORRECTED, HELD = 0, 1, 2, 3, 4
#: Longest time step between two trials (s) the ramp modes execute (an element's step of an
#: earthquake analysis is milliseconds; a quasi-static test's a few seconds).
MAX_TRIAL_STEP = 60.0
#: Poll period (s) of a lockstep wait for OpenSees: stop flag and controller keep-alive.
KEEPALIVE = 0.1
_SMOOTH = 0.2  # per loop step: first-order smoothing of the predictor–corrector's clock speed
#: Per-step command kinds as recorded.
KINDS = {IDLE: "idle", EXECUTED: "executed", PREDICTED: "predicted", CORRECTED: "corrected",
         HELD: "held"}  # fmt: skip


class SiteFault(Exception):
    """The session failed (disconnect, bad frame, OpenSees too late): one line, e-stop."""


def lagrange(xs: list[float], ys: list[np.ndarray], x: float) -> np.ndarray:
    """Lagrange polynomial through ``(xs[j], ys[j])`` evaluated at ``x`` (extrapolates too)."""
    out = np.zeros_like(ys[0])
    n = len(xs)
    for j in range(n):
        w = 1.0
        xj = xs[j]
        for m in range(n):
            if m != j:
                w *= (x - xs[m]) / (xj - xs[m])
        out += w * ys[j]
    return out


class TimingMode:
    """Common bookkeeping: the command, the per-step kinds and the per-target log.

    Parameters
    ----------
    mailbox : Mailbox
        Shared with the server thread.
    n : int
        Number of actuator channels.
    dt : float
        Loop step in seconds.
    start_timeout : float
        Seconds to wait for the first target.
    client_timeout : float
        Seconds to wait for any later target (lockstep and ramp-hold; 0 = no limit).
    """

    name = ""

    def __init__(
        self,
        mailbox: Mailbox,
        n: int,
        dt: float,
        *,
        start_timeout: float = 60.0,
        client_timeout: float = 60.0,
    ) -> None:
        self.mb = mailbox
        self.n = int(n)
        self.dt = float(dt)
        self.start_timeout = float(start_timeout)
        self.client_timeout = float(client_timeout)
        self.cmd = np.zeros(self.n)
        self.kinds: list[int] = []
        #: per target: (seq, loop step it arrived at, latency s, trial time s)
        self.targets: list[tuple[int, int, float, float]] = []
        self.seq = 0  # last target taken
        self.pending: Target | None = None  # taken, its force not yet returned
        self.wall_reply = time.perf_counter()
        self.t_trial = 0.0  # time block of the last target
        self.finished = False
        self.reply_delta: np.ndarray | None = None  # command − target of a passed target
        self.stiffness: np.ndarray | None = None  # actuator-coordinates estimate (N/m)
        #: the runner's stop flag (SIGINT/SIGTERM): a wait for OpenSees ends when it is set
        self.stop: Callable[[], bool] = lambda: False
        #: called every :data:`KEEPALIVE` s while the loop waits for OpenSees (keeps the
        #: controllers fed; the site stage sends each channel's heartbeat)
        self.keepalive: Callable[[], None] = lambda: None
        #: called once after such a wait (the site stage restarts the feedback watchdogs'
        #: clocks: time spent waiting on OpenSees is not controller silence)
        self.resume: Callable[[], None] = lambda: None

    # -- helpers ------------------------------------------------------------------------------
    def _check_closed(self) -> bool:
        """True when the client said DIE; :class:`SiteFault` on any other end of session."""
        mb = self.mb
        if mb.closed is None:
            return False
        if mb.fault or mb.closed != "die":
            raise SiteFault(mb.closed if mb.fault else f"openfresco: {mb.closed}")
        self.finished = True
        return True

    def _new_target(self) -> Target | None:
        t = self.mb.target
        if t is not None and t.seq > self.seq:
            return t
        return None

    def _target_or_end(self) -> bool:
        """A new target is there, or the session ended (a condition wait's predicate)."""
        return self._new_target() is not None or self.mb.closed is not None

    def _take(self, t: Target, k: int) -> None:
        self.seq = t.seq
        self.pending = t
        lat = t.wall - self.wall_reply if self.targets else math.nan
        self.targets.append((t.seq, k, lat, t.time))

    def _reply(self, k: int, disp: np.ndarray, force: np.ndarray) -> None:
        t = self.pending
        self.pending = None
        self.wall_reply = time.perf_counter()
        d = np.array(disp, dtype=float)
        f = np.array(force, dtype=float)
        delta = self.reply_delta
        if delta is not None:  # measured past the target: correct back to it (force correction)
            d = d - delta
            if self.stiffness is not None:
                f = f - self.stiffness @ delta
            self.reply_delta = None
        self.mb.post_reply(t.seq, d, f, k * self.dt)

    def _steps_for(self, t: Target, default: float) -> int:
        """Loop steps to spend on a target: its time step (from the time block) or ``default``.

        A time step over :data:`MAX_TRIAL_STEP` is a :class:`SiteFault` (one line): its ramp
        would hold the loop for that long in one call.
        """
        span = t.time - self.t_trial if math.isfinite(t.time) else default
        if span > MAX_TRIAL_STEP:
            raise SiteFault(
                f"openfresco: trial {t.seq} at time {t.time:g} s is {span:g} s after the last "
                f"one: a time step over {MAX_TRIAL_STEP:g} s is not a test step"
            )
        if math.isfinite(t.time):
            self.t_trial = t.time
        return max(1, round(span / self.dt)) if span > 0 else 1

    def step(self, k: int, disp: np.ndarray, force: np.ndarray) -> np.ndarray | None:
        """Measurement of step ``k`` in; command of step ``k + 1`` out (None: client done)."""
        raise NotImplementedError

    # -- summary ------------------------------------------------------------------------------
    def kind_counts(self) -> dict[str, int]:
        """How many loop steps were idle, executed, predicted, corrected, held."""
        a = np.bincount(np.asarray(self.kinds, dtype=int), minlength=len(KINDS))
        return {KINDS[i]: int(a[i]) for i in KINDS}

    def latencies(self) -> np.ndarray:
        """OpenSees' latency per target (s): from the force reply to the next request."""
        lat = np.array([t[2] for t in self.targets], dtype=float)
        return lat[np.isfinite(lat)]


def _monotone_slopes(
    c0: np.ndarray, d: np.ndarray, span: float, v0: np.ndarray, v1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """End slopes of a cubic Hermite from ``c0`` to ``d`` limited so that it is monotone.

    Fritsch and Carlson (1980): with ``δ = (d − c0)/span``, a slope against ``δ`` becomes 0,
    and when ``α = v0/δ``, ``β = v1/δ`` leave the circle ``α² + β² ≤ 9`` both are scaled onto
    it. The segment then never leaves ``[min(c0, d), max(c0, d)]``: the command between two
    trials stays within their envelope, however uneven the trials' time steps (a slope
    estimated over a tiny step and used over a long one would overshoot by far).
    """
    delta = (d - c0) / span
    v0 = np.where(v0 * delta > 0.0, v0, 0.0)
    v1 = np.where(v1 * delta > 0.0, v1, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(delta != 0.0, v0 / delta, 0.0)
        b = np.where(delta != 0.0, v1 / delta, 0.0)
        r = np.hypot(a, b)
        scale = np.where(r > 3.0, 3.0 / np.where(r > 0.0, r, 1.0), 1.0)
    return v0 * scale, v1 * scale


class _RampBase(TimingMode):
    """Ramp to each target over some loop steps, return the force at its end."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.ramp: deque[np.ndarray] = deque()
        self.reply_at: int | None = None  # loop step whose measurement answers the target
        self.vel = np.zeros(self.n)  # slope of the path at the current target
        self.hermite = False
        self.path: deque[tuple[float, np.ndarray]] = deque(maxlen=2)  # (virtual time, target)

    def _start_ramp(self, t: Target, k: int, steps: int, hold: int = 0) -> None:
        """Ramp from the current command to ``t`` over ``steps`` loop steps, then hold.

        Lockstep uses a C¹ cubic Hermite path: its slope at each target is the three-point
        backward difference through the last three targets, ``(3d₂ − 4d₁ + d₀)/(2h)`` on a
        uniform grid (second-order accurate; the non-uniform form below), so the specimen
        moves through the targets with the velocity of a smooth path. The client's own
        velocity block is not used: its meaning depends on the integrator (Newmark's
        predictor sends ``−v_n``).
        """
        self._take(t, k)
        c0 = self.cmd
        d = np.array(t.displacement, dtype=float)
        span = steps * self.dt
        v0 = self.vel
        v1 = None
        if self.hermite and self.path:
            (t0, d0), (t1, d1) = (
                self.path[-2] if len(self.path) > 1 else self.path[-1],
                self.path[-1],
            )
            h2 = span
            h1 = t1 - t0
            if h1 > 0:  # f'(t2) from (t0, d0), (t1, d1), (t2, d)
                v1 = (
                    d0 * (h2 / (h1 * (h1 + h2)))
                    - d1 * ((h1 + h2) / (h1 * h2))
                    + d * ((2.0 * h2 + h1) / (h2 * (h1 + h2)))
                )
            else:
                v1 = (d - d1) / h2
        if v1 is not None:
            v0, v1 = _monotone_slopes(c0, d, span, np.asarray(v0, float), np.asarray(v1, float))
            lo, hi = np.minimum(c0, d), np.maximum(c0, d)
        for j in range(1, steps + 1):
            s = j / steps
            if v1 is not None:
                # cubic Hermite: position and velocity continuous at both ends of the ramp
                h00 = (1.0 + 2.0 * s) * (1.0 - s) ** 2
                h10 = s * (1.0 - s) ** 2
                h01 = s * s * (3.0 - 2.0 * s)
                h11 = s * s * (s - 1.0)
                # within [c0, d] by the slopes' limits; the clip only removes round-off
                p = h00 * c0 + h10 * span * v0 + h01 * d + h11 * span * v1
                self.ramp.append(np.clip(p, lo, hi))
            else:
                self.ramp.append(c0 + (d - c0) * s)
        for _ in range(hold):
            self.ramp.append(d.copy())
        if hold:
            self.vel = np.zeros(self.n)
        else:  # the slope the path leaves the target with
            self.vel = v1 if v1 is not None else (d - c0) / span
        t_end = (self.path[-1][0] if self.path else 0.0) + span
        if self.path and span > 0 and not hold:
            self.path.append((t_end, d))
        elif not self.path:
            self.path.append((0.0, c0.copy()))
            self.path.append((t_end, d))
        self.reply_at = k + steps + hold


class Lockstep(_RampBase):
    """Each target ramped over its time step in virtual time; the loop waits for OpenSees.

    Parameters
    ----------
    ramp_time : float
        Ramp duration (s) for a trial without a time block (OpenFresco GenericTCP without
        ``-ctrlModes … 1`` for time).
    """

    name = "lockstep"

    def __init__(self, *args, ramp_time: float = 0.01, hermite: bool = True, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.ramp_time = float(ramp_time)
        self.hermite = bool(hermite)

    def step(self, k: int, disp: np.ndarray, force: np.ndarray) -> np.ndarray | None:
        if self.pending is not None and k >= self.reply_at:
            self._reply(k, disp, force)
        if self.ramp:
            self.cmd = self.ramp.popleft()
            self.kinds.append(EXECUTED)
            return self.cmd
        # wait (virtual time stands still) for the next target, in short polls: each one
        # checks the runner's stop flag and keeps the controllers fed (the actuator holds its
        # last command meanwhile)
        mb = self.mb
        limit = self.start_timeout if not self.targets else self.client_timeout
        deadline = time.monotonic() + limit if limit > 0 else math.inf
        waited = False
        while True:
            with mb.cond:
                # a poll: a new target, the end of the session or KEEPALIVE s (the
                # condition's own wait, on its monotonic clock)
                left = deadline - time.monotonic()
                mb.cond.wait_for(self._target_or_end, min(max(left, 0.0), KEEPALIVE))
                t = self._new_target()
                if t is None:
                    if self._check_closed():
                        return None
                    if deadline - time.monotonic() <= 0:
                        raise SiteFault(f"openfresco: no trial from the client within {limit:g} s")
            if t is not None:
                break
            waited = True
            if self.stop():  # hold; the runner stops at its next step (e-stop, end event)
                self.kinds.append(HELD)
                return self.cmd
            self.keepalive()
        if waited:
            self.resume()
        self._start_ramp(t, k, self._steps_for(t, self.ramp_time))
        self.cmd = self.ramp.popleft()
        self.kinds.append(EXECUTED)
        return self.cmd


class RampHold(_RampBase):
    """Ramp ``ramp_time``, hold ``hold_time``, return the force; hold while OpenSees computes."""

    name = "ramp-hold"

    def __init__(self, *args, ramp_time: float = 0.5, hold_time: float = 0.1, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.ramp_steps = max(1, round(float(ramp_time) / self.dt))
        self.hold_steps = max(0, round(float(hold_time) / self.dt))
        self.wait_since = time.monotonic()

    def step(self, k: int, disp: np.ndarray, force: np.ndarray) -> np.ndarray | None:
        if self.pending is not None and k >= self.reply_at:
            self._reply(k, disp, force)
            self.wait_since = time.monotonic()
        if self.ramp:
            self.cmd = self.ramp.popleft()
            self.kinds.append(EXECUTED)
            return self.cmd
        t = self._new_target()
        if t is None:
            if self._check_closed():
                return None
            limit = self.start_timeout if not self.targets else self.client_timeout
            if limit > 0 and time.monotonic() - self.wait_since > limit:
                raise SiteFault(f"openfresco: no trial from the client within {limit:g} s")
            self.kinds.append(HELD if self.targets else IDLE)
            return self.cmd
        if math.isfinite(t.time):
            self.t_trial = t.time
        self._start_ramp(t, k, self.ramp_steps, self.hold_steps)
        self.cmd = self.ramp.popleft()
        self.kinds.append(EXECUTED)
        return self.cmd


class PredictorCorrector(TimingMode):
    """Real-time predictor–corrector (after Schellenberg et al. 2009, Section 4.3).

    The command follows the structure's trajectory through OpenSees' targets on a clock that
    runs in real time: ``c(s) = L(τ(s)) + e(s)``. ``τ`` is *structure time* (OpenSees' analysis
    time in loop steps) and advances by one per loop step; ``L`` is the Lagrange polynomial of
    order ``p`` through the last ``p + 1`` known targets — between targets it extrapolates (the
    *predictor*); when a target arrives, the point set moves on to include it (the
    *corrector*) and the jump this makes at ``τ_r``, ``L_old(τ_r) − L_new(τ_r)``, becomes the
    offset ``e`` that is blended out with the cubic Hermite ``h00`` over the steps left to the
    target's time (an element step, at least four loop steps, when it came late), so command
    and slope stay
    continuous: the compensator after the site extrapolates the target ``α − 1`` steps ahead,
    so any stall or kink would come out ``α − 1`` times larger.

    The force is returned from the first loop step whose structure time reached the target's:
    exactly the target when it came in time, otherwise a point up to the lateness further
    along the trajectory (the clock is not stopped: stalls would be amplified by the
    compensation). Such a measurement is corrected back to the target with the configured
    stiffness estimate ``K`` (``openfresco.stiffness``), ``f = f_m − K·(c − d)`` and
    ``d_m − (c − d)``, with ``c`` the command and ``d`` the target (a first-order force
    correction; exact for a linear specimen whose stiffness is known).

    When the clock gets ahead of OpenSees — past the time the next target is due — its speed is
    lowered smoothly, ``σ* = 1 − excess/H`` (``excess`` the steps past the due time, ``H =
    hold_after/Δt``; ``σ`` follows ``σ*`` with a first-order lag of five steps): a slow client
    slows the test, a stalled one brings the actuator to a hold on the trajectory by
    ``hold_after``; a target later than ``estop_after`` faults the site (e-stop).

    Parameters
    ----------
    order : int
        Polynomial order ``p`` (1 linear, 2 quadratic, 3 cubic).
    wait : float
        Seconds the loop may wait, after its feedback, for a target due at the next step.
    hold_after, estop_after : float
        Lateness (s) past the due time by which the actuator holds, and at which it faults.
    element_dt : float
        OpenSees' time step (s) when the trials carry no time block (0: from the time block).
    """

    name = "predictor-corrector"

    def __init__(
        self,
        *args,
        order: int = 2,
        wait: float = 0.0,
        hold_after: float = 0.02,
        estop_after: float = 0.25,
        element_dt: float = 0.0,
        **kwargs,
    ) -> None:
        super().__init__(*args, **kwargs)
        if order not in (1, 2, 3):
            raise ValueError(f"order must be 1, 2 or 3, got {order!r}")
        self.order = int(order)
        self.wait = float(wait)
        self.hold_after = float(hold_after)
        self.estop_after = float(estop_after)
        self.element_dt = float(element_dt)
        # known targets: structure time (loop steps) and displacement; rest at time 0
        self.hist_s: deque[float] = deque([0.0], maxlen=order + 1)
        self.hist_d: deque[np.ndarray] = deque([np.zeros(self.n)], maxlen=order + 1)
        self.k_sub = 1  # loop steps per element step (from the targets)
        self.tau = 0.0  # structure time of the command (loop steps)
        self.sigma = 1.0  # clock speed (1 = real time; < 1 only while holding)
        self.t_goal: float | None = None  # structure time of the target awaiting its force
        self.reply_at: int | None = None
        self.start_wall = time.monotonic()
        self.worst_late = 0.0
        self.late_steps = 0
        self._horizon = max(1.0, self.hold_after / self.dt)
        self._e0 = np.zeros(self.n)  # blended offset e: value at s_r, over m steps
        self._s_r = 0
        self._m = 1

    def _base(self, tau: float) -> np.ndarray:
        return lagrange(list(self.hist_s), list(self.hist_d), tau)

    def _offset(self, s: int) -> np.ndarray | None:
        x = (s - self._s_r) / self._m
        if x >= 1.0:
            return None
        return self._e0 * ((1.0 + 2.0 * x) * (1.0 - x) ** 2)

    def _arrive(self, t: Target, k: int) -> None:
        """Target ``t`` seen at loop step ``k`` (after the command of ``k`` was sent)."""
        self._take(t, k)
        t_last = self.hist_s[-1]
        if math.isfinite(t.time):
            t_new = t.time / self.dt
            self.t_trial = t.time
        else:
            t_new = t_last + (self.element_dt / self.dt if self.element_dt > 0 else self.k_sub)
        if t_new <= t_last:  # an iteration at the same time: a tiny step
            t_new = t_last + 1e-6
        self.k_sub = max(1, round(t_new - t_last))
        old = self._base(self.tau)
        rest = self._offset(k)
        self.hist_s.append(t_new)
        self.hist_d.append(np.array(t.displacement, dtype=float))
        new = self._base(self.tau)
        self._e0 = (old - new) + (rest if rest is not None else 0.0)
        self._s_r = k
        left = t_new - self.tau
        # on time: blend out by the target's time; late: over an element step, at least 4
        self._m = max(1, round(left)) if left >= 1.0 else max(self.k_sub, 4)
        self.t_goal = t_new

    def step(self, k: int, disp: np.ndarray, force: np.ndarray) -> np.ndarray | None:  # noqa: C901
        if self.pending is not None and self.reply_at is not None and k >= self.reply_at:
            self._reply(k, disp, force)
            self.reply_at = None
        if self.t_goal is None and self.pending is None:
            t = self._new_target()
            if t is None and self.targets and self.wait > 0:
                if self.tau + 1.0 >= self.hist_s[-1] + self.k_sub:  # due at the next step
                    t = self._wait_for(self.wait)
            if t is not None:
                self._arrive(t, k)
        s = k + 1
        if not self.targets:  # before the first target: stand still
            if self._check_closed():
                return None
            if time.monotonic() - self.start_wall > self.start_timeout > 0:
                raise SiteFault(
                    f"openfresco: no trial from the client within {self.start_timeout:g} s"
                )
            self.kinds.append(IDLE)
            return self.cmd
        if self.t_goal is None and self.pending is None and self._check_closed():
            return None
        kind = PREDICTED
        # how far the clock would run past the due time of the next target nobody sent yet:
        # the clock slows smoothly as it gets ahead of OpenSees (σ* = 1 − excess/H, H the
        # hold_after horizon) so a slow or stalled client brings the actuator to a hold
        # without a jerk (the compensation multiplies jerks by α − 1)
        excess = self.tau + 1.0 - (self.hist_s[-1] + self.k_sub)
        if excess > 0.0 and self.t_goal is None:
            self.late_steps += 1
            late = self.late_steps * self.dt
            if late > self.worst_late:
                self.worst_late = late
            if late > self.estop_after:
                raise SiteFault(
                    f"openfresco: OpenSees is {late * 1e3:.1f} ms late with its next trial "
                    f"(bound openfresco.estop_after = {self.estop_after * 1e3:g} ms)"
                )
        elif self.t_goal is not None:
            self.late_steps = 0
        goal = 1.0 - min(1.0, max(0.0, excess) / self._horizon)
        self.sigma += _SMOOTH * (goal - self.sigma)
        if self.sigma < 0.5:
            kind = HELD  # the clock is below half speed: the actuator is coming to a hold
        self.tau += self.sigma
        c = self._base(self.tau)
        e = self._offset(s)
        if e is not None:
            c = c + e
            if kind == PREDICTED:
                kind = CORRECTED
        if self.t_goal is not None:
            if self.tau >= self.t_goal - 1e-9:  # the target's time is reached: its force next
                if abs(self.tau - self.t_goal) < 1e-9 and e is None:
                    kind = EXECUTED
                else:  # passed (a late target) or not yet blended: measured off the target
                    self.reply_delta = c - self.hist_d[-1]
                self.t_goal = None
                self.reply_at = s
            else:
                kind = CORRECTED
        self.cmd = c
        self.kinds.append(kind)
        return c

    def _wait_for(self, limit: float) -> Target | None:
        """A new target within ``limit`` s (or the end of the session): the target or None."""
        mb = self.mb
        with mb.cond:
            mb.cond.wait_for(self._target_or_end, limit)
            return self._new_target()


def make_timing(name: str, mailbox: Mailbox, n: int, dt: float, opts: dict) -> TimingMode:
    """Build the timing mode ``name`` with the options of ``[openfresco]``."""
    common = {
        "start_timeout": opts.get("start_timeout", 60.0),
        "client_timeout": opts.get("client_timeout", 60.0),
    }
    if name == "lockstep":
        return Lockstep(mailbox, n, dt, ramp_time=opts.get("ramp_time", 0.01), **common)
    if name == "ramp-hold":
        return RampHold(
            mailbox,
            n,
            dt,
            ramp_time=opts.get("ramp_time", 0.5),
            hold_time=opts.get("hold_time", 0.1),
            **common,
        )
    if name == "predictor-corrector":
        pc = PredictorCorrector(
            mailbox,
            n,
            dt,
            order=int(opts.get("order", 2)),
            wait=opts.get("wait", 0.4 * dt),
            hold_after=opts.get("hold_after", 0.02),
            estop_after=opts.get("estop_after", 0.25),
            element_dt=opts.get("element_dt", 0.0),
            **common,
        )
        pc.stiffness = opts.get("stiffness_matrix")
        return pc
    raise ValueError(f"unknown timing {name!r}")

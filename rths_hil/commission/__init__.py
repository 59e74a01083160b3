"""Commissioning of each actuator channel before a test: ``rths-hil commission CONFIG``.

A scripted check of every channel of a configuration against its controller (a twin for CI,
the hardware after the operator's confirmation), in this order, each step passed, failed or
skipped with the reason:

``identify``
    Open the driver, arm the controller, read position, force and status (the arming reply);
    the position must be readable, within ``safety.displacement_limit``, and the controller
    must report no fault. The driver, its profile and the twin or hardware are reported, and
    what the driver found out about the link when it opened (``link_note``: a Modbus server
    that answers one request at a time, to which the driver then sends one at a time).
``latency``
    Round trips at the loop rate for ``commission.latency_time`` seconds with the actuator
    **disabled** (commands with ``enable = False`` at the held position): histogram, p50, p99,
    maximum, missed replies, the longest gap between two replies, and the link time the link
    budget computes for one step (:mod:`rths_hil.linkbudget`). Fails when more than 1 % of the
    replies are missed or the p99 round trip is above the loop's feedback timeout
    (``loop.feedback_timeout``, default 0.8 period).
``enable``
    Enable at the held position for 0.2 s (status ``ENABLED``, no motion beyond 20 µm + 5 % of
    ``commission.amplitude``), then disable (status without ``ENABLED``).
``motion``
    A ramp–hold–ramp of ``commission.amplitude`` (cosine ramps at most ``commission.velocity``,
    0.5 s holds) from the held position and back. Tracking from the FEI of the whole motion
    (the FEI paper's Eq. 2.1–2.5, :func:`rths_hil.fei.fei`) and from the Kalman estimator
    (:class:`rths_hil.estimation.DelayGainEstimator`); fails when the hold misses the target by
    more than 10 % of the amplitude or the FEI amplitude is off by more than 10 %.
``plant``
    A logarithmic chirp about the held position (:func:`plant_path`: 0.5 Hz up to 20 Hz or
    ``fs/16``, :data:`CHIRP_TIME` s, amplitude at most half ``commission.amplitude`` and
    velocity at most ``commission.velocity``), and a least-squares fit of the delayed
    first-order model ``g·e^(−sτ)/(T s + 1)`` to it (:func:`identify_plant`): the channel's
    delay τ, lag T and gain g as the loop sees them (the link's own latency is part of τ).
    Fails when the model explains less than 90 % of the motion or a value sits at its bound;
    a chirp during which the controller latched (its watchdog, when the computer stalled) is
    acknowledged by arming and run once more.
``estop``
    Enabled at the held position, e-stop through the driver; for 0.2 s commands towards half
    the amplitude must be ignored (status ``ESTOP_ACTIVE`` in every reply after the first
    :data:`ESTOP_GRACE`, position held within 20 µm); an
    ``enable = False`` command must acknowledge it and an ``enable = True`` command re-enable.
    The controller is then armed again (a new run: whatever the driver kept going after its
    e-stop, e.g. a CANopen bus's heartbeat, stops).
``watchdog``
    Only when ``commission.watchdog_test`` and the controller's heartbeat timeout are known
    (``commission.watchdog_timeout``, or the twin's ``twin.watchdog``): enabled, then silent;
    the controller must have latched (``WATCHDOG`` with ``ESTOP_ACTIVE`` or ``FAULT``) after
    the timeout plus a margin. The latch is then acknowledged by arming, as a run does.
``limits``
    Skipped: the drivers' protocols carry no limit registers to read back.
``hand-back``
    Always, also after a failed step or an operator stop: the last position is held (when
    enabled) for ``end.hold`` seconds, the controller disabled, a latch left by a step
    acknowledged by arming, and the status read: passed when the controller reports neither
    ``ENABLED`` nor ``ESTOP_ACTIVE``, ``WATCHDOG`` or ``FAULT``.

**Operator stop.** Ctrl-C, SIGTERM or SIGHUP (:data:`rths_hil.hybrid.runner.STOP_SIGNALS`, as
``rths-hil run``) end the step under way at its next period; the steps not reached are
skipped, the hand-back step runs, the report is written and the command exits 130. A second
signal e-stops every channel at once.

**Tuned fragment.** When every channel's ``plant`` step passed, ``tuned.toml`` beside the
report (:func:`tuned_fragment`) sets each channel's compensation to the ``model`` method with
the identified τ, T, g and ``safety.watchdog_timeout`` to :data:`WATCHDOG_SHARE` of the
controller's own watchdog when it is known, else :data:`GAP_MARGIN` × the longest reply gap of
the latency step (at least the key's default); a test configuration takes it with
``include = ["…/tuned.toml"]`` (``docs/config.md``).

The report (``report.md``, one PNG per channel with the latency histogram, the motion and the
chirp with the fitted model) goes to ``commission/<timestamp>/``.

Modules: :mod:`.session` (the channels opened, the steps run in order, the report written),
:mod:`.steps` (one function a step), :mod:`.controller` (paced command/reply exchanges with
one controller), :mod:`.plant` (the chirp and the delayed first-order fit), :mod:`.report`
(the results, ``report.md`` and its plots), :mod:`.tuned` (``tuned.toml``).
"""

from __future__ import annotations

from .plant import CHIRP_TIME, PlantFit, identify_plant, plant_path
from .report import ChannelReport, StepResult, write_report
from .session import MAX_LATENCY_TIME, commission
from .steps import MOVING, STEPS
from .tuned import GAP_MARGIN, WATCHDOG_SHARE, tuned_fragment

__all__ = [
    "CHIRP_TIME",
    "GAP_MARGIN",
    "MAX_LATENCY_TIME",
    "MOVING",
    "STEPS",
    "WATCHDOG_SHARE",
    "ChannelReport",
    "PlantFit",
    "StepResult",
    "commission",
    "identify_plant",
    "plant_path",
    "tuned_fragment",
    "write_report",
]

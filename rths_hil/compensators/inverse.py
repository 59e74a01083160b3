"""Actuator delay compensation: inverse compensation with an optional adaptive α.

Inverse compensation (Chen & Ricles, "Analysis of actuator delay compensation methods for
real-time testing", Engineering Structures 31, 2009; Chen, Ricles, Marullo & Mercan,
"Real-time hybrid testing using the unconditionally stable explicit CR integration algorithm",
EESD 38, 2009) models the servo-hydraulic actuator as a discrete first-order lag of ``α`` steps
and sends its inverse::

    x_c[k] = a · (α · x_t[k] − (α − 1) · x_t[k−1])

``x_t`` is the target (calculated) displacement, ``x_c`` the command, ``a`` an optional
amplitude factor (1 by default). For a slowly varying target this is a linear extrapolation
``x_c ≈ x_t(t + (α − 1)·Δt)``, so an actuator of delay τ is compensated by
``α = 1 + τ/Δt``; ``α = 1`` is no compensation. Issue 6's tuning rule ``α ← α + d/Δt``
follows from the same relation: a residual equivalent delay ``d`` of measured vs target (the FEI
paper's Eq. 2.5, d > 0 when measured lags) asks for ``d/Δt`` more steps of lead.

The adaptive option (:class:`AdaptiveAlpha`) moves α online towards that goal from the online FEI
delay estimate, through a first-order law with time constant ``time_constant`` (it must exceed
the lag of the moving-window estimate, about half a window), a rate limit and bounds. Only valid
windows move it.

The compensator contract is :class:`~rths_hil.compensators.base.Compensator`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

from ..errors import InputError
from ..keys import Key, seconds
from ..units import positive_number
from .base import Compensator

__all__ = ["AdaptiveAlpha", "InverseCompensator", "alpha_for_delay"]


def alpha_for_delay(delay: float, dt: float) -> float:
    """The inverse-compensation α that cancels a pure delay ``delay`` (s) at step ``dt`` (s).

    ``α = 1 + delay/dt`` (see the module docstring).
    """
    if dt <= 0:
        raise InputError(f"time step must be > 0 s, got {dt}")
    return 1.0 + delay / dt


class InverseCompensator(Compensator):
    """Inverse compensation ``x_c = a·(α·x_t − (α−1)·x_t,prev)`` stepped once per loop step.

    Parameters
    ----------
    alpha : float
        Compensation parameter α ≥ 1 (steps). 1 means no compensation.
    amplitude : float
        Amplitude factor ``a`` > 0 applied to the compensated command (1 = none).
    enabled : bool
        When False the command equals the target (α and ``a`` are ignored).

    Notes
    -----
    :meth:`step` does only float arithmetic (no allocation), so it can sit on the loop's step
    path. ``alpha`` may be changed between steps (adaptive compensation).
    """

    __slots__ = ("alpha", "amplitude", "enabled", "prev")
    #: the adaptive α's keys (:class:`AdaptiveAlpha`); each bound and rate also in loop steps
    #: (``rths_hil.config.STEP_KEYS``: ``alpha_min = 1 + delay_min·fs``, ``rate = delay_rate·fs``)
    KEYS: ClassVar[Mapping[str, Key]] = {
        "adaptive": Key("bool", False, doc="inverse: adapt α online from the online FEI delay"),
        "time_constant": seconds(6.0, doc="adaptive: time constant of the α update", positive=True),
        "delay_rate": Key(
            "float",
            0.0048828125,
            unit="s/s",
            doc="adaptive: maximum rate of change of the compensated delay (5 steps/s at 1024 Hz)",
            lo=0,
            lo_open=True,
        ),
        "rate": Key(
            "float",
            5.0,
            unit="1/s",
            doc="adaptive: maximum |dα/dt|, another way to give delay_rate (rate = delay_rate·fs)",
            lo=0,
            lo_open=True,
        ),
        "delay_min": seconds(0.0, doc="adaptive: lower bound of delay", hi=1.0),
        "delay_max": seconds(0.0966796875, doc="adaptive: upper bound of delay", hi=1.0),
        "alpha_min": Key(
            "float", 1.0, unit="steps", doc="adaptive: lower bound of α (1 + delay_min·fs)", lo=1
        ),
        "alpha_max": Key(
            "float", 100.0, unit="steps", doc="adaptive: upper bound of α (1 + delay_max·fs)", lo=1
        ),
    }

    @classmethod
    def from_config(cls, c: Mapping[str, Any], fs: float) -> InverseCompensator:
        """α = 1 + ``delay``·fs (Chen & Ricles 2009), amplitude factor ``amplitude``."""
        return cls(alpha_for_delay(c["delay"], 1.0 / fs), c["amplitude"], c["enabled"])

    def __init__(self, alpha: float = 1.0, amplitude: float = 1.0, enabled: bool = True) -> None:
        if not (math.isfinite(alpha) and alpha >= 1.0):
            raise InputError(f"compensation alpha must be a finite number >= 1, got {alpha}")
        self.alpha = float(alpha)
        self.amplitude = positive_number(amplitude, "compensation amplitude factor")
        self.enabled = bool(enabled)
        self.prev = 0.0

    def reset(self, target: float = 0.0) -> None:
        """Forget the history; the previous target becomes ``target`` (m)."""
        self.prev = float(target)

    def step(self, target: float) -> float:
        """Return the command (m) for the target ``target`` (m) of this step."""
        prev = self.prev
        self.prev = target
        if not self.enabled:
            return target
        a = self.alpha
        return self.amplitude * (a * target - (a - 1.0) * prev)


class AdaptiveAlpha:
    """Online α from the online delay estimate, with a time constant, a rate limit and bounds.

    Each valid estimate ``d`` (s) sets a goal for α:

    * ``pair="target"`` (d of measured vs target, the residual delay): ``α* = α + d/Δt``;
    * ``pair="command"`` (d of measured vs command, the actuator's own delay): ``α* = 1 + d/Δt``.

    α then moves towards α* by ``(α* − α)·Δt/T`` per sample (a first-order approach with time
    constant ``T = time_constant``), the move limited to ``rate·Δt`` per sample and α kept in
    ``[alpha_min, alpha_max]``. Invalid or non-finite estimates leave α unchanged.

    Parameters
    ----------
    compensator : InverseCompensator
        The compensator whose ``alpha`` is adapted (in place).
    dt : float
        Loop step in s.
    pair : {"target", "command"}
        Which pair the delay estimate comes from.
    time_constant : float
        T in s (> 0). Keep it above the estimate's own lag (≈ half the FEI window).
    rate : float
        Maximum |dα/dt| in 1/s (> 0).
    alpha_min, alpha_max : float
        Bounds, 1 ≤ alpha_min ≤ alpha_max.
    """

    __slots__ = ("_gain", "_max_step", "alpha_max", "alpha_min", "comp", "dt", "pair")

    def __init__(
        self,
        compensator: InverseCompensator,
        dt: float,
        pair: str = "target",
        time_constant: float = 6.0,
        rate: float = 5.0,
        alpha_min: float = 1.0,
        alpha_max: float = 100.0,
    ) -> None:
        if pair not in ("target", "command"):
            raise InputError(
                f"adaptive compensation: pair must be 'target' or 'command', not {pair!r}"
            )
        if not (dt > 0 and time_constant > 0 and rate > 0):
            raise InputError("adaptive compensation: dt, time_constant and rate must be > 0")
        if not (1.0 <= alpha_min <= alpha_max):
            raise InputError(
                f"adaptive compensation: need 1 <= alpha_min <= alpha_max, got "
                f"{alpha_min}, {alpha_max}"
            )
        self.comp = compensator
        self.dt = float(dt)
        self.pair = pair
        self._gain = self.dt / float(time_constant)
        self._max_step = float(rate) * self.dt
        self.alpha_min = float(alpha_min)
        self.alpha_max = float(alpha_max)
        compensator.alpha = min(max(compensator.alpha, self.alpha_min), self.alpha_max)

    def goal(self, delay: float) -> float:
        """α* for the delay estimate ``delay`` (s), before bounds."""
        if self.pair == "target":
            return self.comp.alpha + delay / self.dt
        return 1.0 + delay / self.dt

    def update(self, delay: float, valid: bool) -> float:
        """Move α one sample towards the goal set by ``delay`` (s); return the new α."""
        comp = self.comp
        alpha = comp.alpha
        if not valid or delay != delay or delay in (math.inf, -math.inf):
            return alpha
        if self.pair == "target":
            move = delay / self.dt * self._gain
        else:
            move = (1.0 + delay / self.dt - alpha) * self._gain
        lim = self._max_step
        if move > lim:
            move = lim
        elif move < -lim:
            move = -lim
        alpha += move
        if alpha < self.alpha_min:
            alpha = self.alpha_min
        elif alpha > self.alpha_max:
            alpha = self.alpha_max
        comp.alpha = alpha
        return alpha

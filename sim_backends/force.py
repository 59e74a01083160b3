"""The force-controlled twin: a servo-hydraulic actuator closing its loop on the load cell.

A force-controlled actuator pushes on the specimen until the load cell reads the set-point. The
valve opens in proportion to the force error and the piston moves at the flow it lets through,
so, with the force-loop gain ``K_f`` (m/s of piston velocity per N of force error; the
controller's proportional gain times the valve's flow gain over the piston area)::

    ẋ = K_f · (F_r − k·x − c·ẋ)          (the spring-dashpot specimen k, c in the loop)

which is a first-order lag from ``F_r/k`` to ``x``::

    x = (F_r / k) · 1 / (T s + 1),      T = (1 + K_f·c) / (K_f·k)

The specimen's stiffness is in the loop: a stiffer specimen closes the loop faster, a softer one
slower, as on a real rig tuned once. The reference ``F_r`` is the commanded force through the
same pieces as the displacement twin (:mod:`rths_hil.sim_backends.plant`): the actuator model's
dynamics (``servo_lag``: the valve and its electronics), then the fractional transport delay and
the gain of the FEI paper's Fig. 4.1. One step::

    F_r = gain · delay(dynamics(F_c))           # reference of the force loop (N)
    x   = lag_T(F_r / k)                        # achieved displacement (m), first-order hold
    F   = specimen.step(x)                      # k·x + c·ẋ + m·ẍ (N)
    measured = (Q_d(x + n_d), Q_f(F + n_f))     # the displacement twin's sensors

At steady state ``F = gain·F_c`` and ``x = gain·F_c/k``. The specimen's mass (``m``) is not
in the loop: its inertia force ``m·ẍ`` is measured by the load cell but the loop is the
spring-dashpot's (a mass on the rod makes a real force loop second order; keep it small beside
``k·T²``). Sensor noise, quantisation and their seeded streams are the displacement twin's.

The effects catalogue (:mod:`rths_hil.sim_backends.effects`) acts where each effect acts on a
force-controlled rig (:data:`FORCE_EFFECTS`), in the order the model file gives (those on the
reference before the loop):

- on the force reference (N), after the delay and gain: ``offset`` (a set-point or load-cell
  zero error; ``offset`` in N: the force settles at ``gain·F_c + offset``), ``drift`` (``rate``
  in N/s), ``servo_lag`` and ``time_varying_delay`` (times in s, as in the displacement twin);
- on the piston inside the loop (m): ``stroke_limit`` (the end stops: the piston stops there and
  the force is the specimen's at the stop, the loop does not wind up) and ``velocity_limit``
  (the valve's flow saturation, ``|ẋ| ≤ limit``). The loop's state is the limited displacement::

      x[k] = limits(p·x[k−1] + b0·u[k] + b1·u[k−1]),   u = F_r/k   (the lag's first-order hold)

``backlash`` and ``force_feedback`` are refused (:data:`FORCE_REFUSED` says why).

A plant that runs in force mode says so: ``ForcePlant.control == "force"`` (``TwinPlant`` has
no such attribute, or ``"displacement"``); the endpoints pass the decoded set-point (N) to
:meth:`ForcePlant.step` unchanged.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from rths_hil.errors import InputError

from .base import ActuatorModel, check_dt
from .delay import DelayGain
from .effects import FORCE_EFFECTS, FORCE_REFUSED, FORCE_UNITS, Effect, EffectChain
from .first_order import first_order_coeffs
from .models import Series
from .plant import Sensor, TwinPlant
from .specimen import KelvinVoigt

__all__ = [
    "DEFAULT_LOOP_GAIN",
    "FORCE_EFFECTS",
    "FORCE_REFUSED",
    "FORCE_UNITS",
    "ForcePlant",
    "force_loop_time_constant",
    "force_plant",
]

#: Default force-loop gain K_f (m/s per N): a 4.2 ms closed force loop on the RTHS benchmark's
#: 1.19 MN/m specimen (T = 1/(K_f·k)).
DEFAULT_LOOP_GAIN = 2.0e-4


def force_loop_time_constant(loop_gain: float, stiffness: float, damping: float = 0.0) -> float:
    """Time constant of the closed force loop, ``T = (1 + K_f·c)/(K_f·k)`` (s).

    Raises
    ------
    InputError
        ``loop_gain`` or ``stiffness`` not a finite number > 0, ``damping`` < 0.
    """
    for name, value in (("loop_gain", loop_gain), ("specimen stiffness", stiffness)):
        if isinstance(value, bool) or not math.isfinite(float(value)) or float(value) <= 0:
            raise InputError(
                f"{name}: must be a finite number > 0 for a force-controlled twin, got {value!r}"
            )
    if not math.isfinite(float(damping)) or float(damping) < 0:
        raise InputError(f"specimen damping: must be ≥ 0, got {damping!r}")
    return (1.0 + loop_gain * damping) / (loop_gain * stiffness)


class _ForceLoop(ActuatorModel):
    """The closed force loop from its reference ``u = F_r/k`` (m) to the piston (m).

    The first-order lag of time constant ``T`` with a first-order hold, the in-loop limits
    (``stroke_limit``, ``velocity_limit``) applied to each step's displacement before it becomes
    the lag's state. With no limits it is :class:`FirstOrderServo` (vectorised by lfilter).
    """

    def __init__(self, time_constant: float, dt: float, limits: Sequence[Effect] = ()) -> None:
        self.dt = dt
        b, a = first_order_coeffs(1.0, time_constant, dt)
        self.b, self.a = b, a
        self._b0, self._b1, self._p = float(b[0]), float(b[1]), -float(a[1])
        self.limits = EffectChain(limits)
        self.reset()

    def reset(self) -> None:
        self._x = 0.0
        self._u = 0.0
        self.limits.reset()

    def step(self, command: float) -> float:
        x = self._p * self._x + self._b0 * command + self._b1 * self._u
        if self.limits.effects:
            x = self.limits.step(x)
        self._x = x
        self._u = command
        return x

    def simulate(self, command: np.ndarray) -> np.ndarray:
        if self.limits.effects:
            return super().simulate(command)
        # where used: a twin's start-up (twin serve) does without scipy.signal's second
        from scipy.signal import lfilter

        self.reset()
        return np.asarray(lfilter(self.b, self.a, np.asarray(command, dtype=float)))


class _Scale(ActuatorModel):
    """``y = factor·x``."""

    def __init__(self, factor: float, dt: float) -> None:
        self.dt = dt
        self.factor = factor

    def reset(self) -> None:
        return None

    def step(self, command: float) -> float:
        return self.factor * command

    def simulate(self, command: np.ndarray) -> np.ndarray:
        return self.factor * np.asarray(command, dtype=float)


class _Effects(ActuatorModel):
    """An effect chain as a model stage (the reference effects, in N)."""

    def __init__(self, effects: Sequence[Effect], dt: float) -> None:
        self.dt = dt
        self.chain = EffectChain(effects)

    def reset(self) -> None:
        self.chain.reset()

    def step(self, command: float) -> float:
        return self.chain.step(command)

    def simulate(self, command: np.ndarray) -> np.ndarray:
        self.chain.reset()
        out = self.chain.simulate(command)
        self.chain.reset()
        return out


class ForcePlant(TwinPlant):
    """A force-controlled actuator on a spring-dashpot specimen (see the module docstring).

    :meth:`step` takes the force set-point (N) and returns (measured displacement in m,
    measured force in N), the :class:`~rths_hil.sim_backends.base.Plant` protocol.

    Parameters
    ----------
    specimen : KelvinVoigt
        The specimen in the loop; its stiffness must be > 0 (a force loop needs something to
        push against).
    loop_gain : float
        ``K_f`` in m/s per N (> 0).
    delay : float
        Transport delay of the set-point (s, fractional).
    gain : float
        Amplitude gain of the set-point.
    dynamics : ActuatorModel, optional
        Dynamics in front of the delay (e.g. a :class:`FirstOrderServo` valve lag), applied to
        the force set-point; its ``dt`` is the plant's.
    sensor : Sensor, optional
        Noise and quantisation; default noiseless and unquantised.
    effects : sequence of Effect, optional
        Catalogue effects of :data:`FORCE_EFFECTS`, in order: those on the reference act on
        the force (their offset in N, drift in N/s), those in the loop on the piston (m).

    Attributes
    ----------
    time_constant : float
        ``T`` of the closed force loop (s).

    Raises
    ------
    InputError
        An effect the force twin does not take (:data:`FORCE_REFUSED`), or a bad parameter.
    """

    #: the wire mode of the set-point this plant takes (N)
    control = "force"

    def __init__(
        self,
        specimen: KelvinVoigt,
        loop_gain: float = DEFAULT_LOOP_GAIN,
        delay: float = 0.0,
        gain: float = 1.0,
        dynamics: ActuatorModel | None = None,
        sensor: Sensor | None = None,
        effects: Sequence[Effect] = (),
    ) -> None:
        dt = check_dt(specimen.dt)
        self.loop_gain = float(loop_gain)
        self.time_constant = force_loop_time_constant(
            self.loop_gain, specimen.stiffness, specimen.damping
        )
        if not math.isfinite(float(delay)) or float(delay) < 0:
            raise InputError(f"delay: must be ≥ 0 s, got {delay!r}")
        if not math.isfinite(float(gain)):
            raise InputError(f"gain: must be a finite number, got {gain!r}")
        reference: list[Effect] = []
        limits: list[Effect] = []
        for e in effects:
            if e.kind in FORCE_REFUSED:
                raise InputError(
                    f"{e.kind}: a force-controlled twin does not take it ({FORCE_REFUSED[e.kind]})"
                )
            if abs(e.dt - dt) > 1e-12 * dt:
                raise ValueError(f"effect {e.kind} has dt={e.dt}, plant has {dt}")
            (reference if FORCE_EFFECTS[e.kind] == "reference" else limits).append(e)
        # the delay and gain of Fig. 4.1 and the reference effects on the force (N), then the
        # set-point scaled to the displacement it asks of the spring (F_r/k), then the loop
        stages: list[ActuatorModel] = [] if dynamics is None else [dynamics]
        stages.append(DelayGain(float(delay), float(gain), dt))
        if reference:
            stages.append(_Effects(reference, dt))
        stages += [
            _Scale(1.0 / specimen.stiffness, dt),
            _ForceLoop(self.time_constant, dt, limits),
        ]
        self.delay = float(delay)
        self.gain = float(gain)
        self.force_effects = tuple(effects)
        super().__init__(Series(stages), (), specimen, sensor)


def force_plant(
    twin: Mapping[str, Any] | str | os.PathLike[str], dt: float, loop_gain: float
) -> ForcePlant:
    """A :class:`ForcePlant` from a model file's tables (``actuator``, ``specimen``, ``sensor``).

    The ``[actuator]`` table's ``delay``, ``gain`` and ``model`` (``delay_gain`` or
    ``servo_lag``, whose ``time_constant`` lags the set-point) are the force loop's, its
    ``[[actuator.effects]]`` those of :data:`FORCE_EFFECTS` (``offset`` in N, ``drift`` in
    N/s); the ``[specimen]`` is the one in the loop; ``[sensor]`` as the displacement twin's.

    Parameters
    ----------
    twin : mapping or path
        The tables as a parsed model file or a configuration's ``[twin]`` section holds them,
        or a model file.
    dt : float
        Step (s).
    loop_gain : float
        ``K_f`` (m/s per N).

    Raises
    ------
    InputError
        An effect the force twin does not take (:data:`FORCE_REFUSED`, naming why), a model
        other than ``delay_gain`` or ``servo_lag``, or what
        :func:`rths_hil.sim_backends.modelfile.load_model` refuses; the message names the key.
    """
    from .effects import make_effect
    from .modelfile import SpecimenSpec, load_model
    from .models import make_model

    if isinstance(twin, str | os.PathLike):
        spec = load_model(os.fspath(twin), control="force")
    else:
        spec = load_model(
            {k: dict(twin[k]) for k in ("actuator", "specimen", "sensor") if twin.get(k)},
            control="force",
        )
    a = spec.actuator
    if a.model not in ("delay_gain", "servo_lag"):
        raise InputError(
            "actuator.model: a force-controlled twin takes delay_gain or servo_lag, "
            f"not {a.model!r}"
        )
    sp = spec.specimen or SpecimenSpec()
    specimen = KelvinVoigt(sp.stiffness, sp.damping, dt, mass=sp.mass)
    dynamics = None
    if a.model == "servo_lag":
        dynamics = make_model(a.model, dt, **a.params)
    effects = [make_effect(e.kind, dt, **e.params) for e in a.effects]
    return ForcePlant(specimen, loop_gain, a.delay, a.gain, dynamics, spec.sensor, effects)

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
``k·T²``). The ``[[actuator.effects]]`` of the displacement twin act on a displacement the
force loop would correct, so the force twin takes none (:func:`force_plant` refuses them);
sensor noise, quantisation and their seeded streams are the displacement twin's.

A plant that runs in force mode says so: ``ForcePlant.control == "force"`` (``TwinPlant`` has
no such attribute, or ``"displacement"``); the endpoints pass the decoded set-point (N) to
:meth:`ForcePlant.step` unchanged.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Any

from rths_hil.errors import InputError

from .base import ActuatorModel, check_dt
from .delay import DelayGain
from .first_order import FirstOrderServo
from .models import Series
from .plant import Sensor, TwinPlant
from .specimen import KelvinVoigt

__all__ = ["DEFAULT_LOOP_GAIN", "ForcePlant", "force_loop_time_constant", "force_plant"]

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

    Attributes
    ----------
    time_constant : float
        ``T`` of the closed force loop (s).
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
        # the delay and gain of Fig. 4.1, the set-point scaled to the displacement it asks of
        # the spring (F_r/k), then the closed loop's lag
        stages: list[ActuatorModel] = [] if dynamics is None else [dynamics]
        stages += [
            DelayGain(float(delay), float(gain) / specimen.stiffness, dt),
            FirstOrderServo(self.time_constant, dt),
        ]
        self.delay = float(delay)
        self.gain = float(gain)
        super().__init__(Series(stages), (), specimen, sensor)


def force_plant(
    twin: Mapping[str, Any] | str | os.PathLike[str], dt: float, loop_gain: float
) -> ForcePlant:
    """A :class:`ForcePlant` from a model file's tables (``actuator``, ``specimen``, ``sensor``).

    The ``[actuator]`` table's ``delay``, ``gain`` and ``model`` (``delay_gain`` or
    ``servo_lag``, whose ``time_constant`` lags the set-point) are the force loop's; the
    ``[specimen]`` is the one in the loop; ``[sensor]`` as the displacement twin's.

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
        A table the force twin does not take (effects, a model other than ``delay_gain`` or
        ``servo_lag``), or what :func:`rths_hil.sim_backends.modelfile.load_model` refuses; the
        message names the key.
    """
    from .modelfile import SpecimenSpec, load_model
    from .models import make_model

    if isinstance(twin, str | os.PathLike):
        spec = load_model(os.fspath(twin))
    else:
        spec = load_model(
            {k: dict(twin[k]) for k in ("actuator", "specimen", "sensor") if twin.get(k)}
        )
    a = spec.actuator
    if a.effects:
        raise InputError(
            "actuator.effects: a force-controlled twin takes no effects (they act on a "
            "displacement its force loop would correct)"
        )
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
    return ForcePlant(specimen, loop_gain, a.delay, a.gain, dynamics, spec.sensor)

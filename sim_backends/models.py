"""Actuator models: what displacement a servo-hydraulic actuator achieves for a command.

Three families, all :class:`~rths_hil.sim_backends.base.ActuatorModel` subclasses stepped at ``dt``:

* :class:`DelayGain` — the FEI paper's block model (Fig. 4.1): a fractional transport delay followed
  by a gain (re-exported from :mod:`rths_hil.sim_backends.delay`).
* :class:`FirstOrderServo` — a first-order servo lag ``1 / (T s + 1)``; its low-frequency
  equivalent delay is ``T`` and its amplitude at frequency ``f`` is ``1/sqrt(1 + (2π f T)²)``.
* :class:`BenchmarkServo` — the servo-valve / actuator / control-structure-interaction plant of
  the RTHS benchmark problem (Silva, Gomez, Maghareh, Dyke & Spencer, "Benchmark control
  problem for real-time hybrid simulation", *Mechanical Systems and Signal Processing* 135,
  106381, 2020; nominal parameters of their Table 2, see :data:`BENCHMARK_NOMINAL`), with the
  specimen's mass, damping and stiffness as parameters.

:class:`FirstOrderServo` lives in :mod:`rths_hil.sim_backends.first_order` (the ``servo_lag``
effect uses the same filter), :class:`BenchmarkServo` and :class:`StateSpaceModel` in
:mod:`rths_hil.sim_backends.benchmark`; this module re-exports them and builds a model by its
registered name (:func:`make_model`, :data:`rths_hil.sim_backends.registry.MODELS`).

:class:`Series` chains models (the model file's ``model`` dynamics followed by the ``delay`` and
``gain`` of the FEI paper's Fig. 4.1). Continuous models are discretised with
:func:`scipy.signal.cont2discrete` using a first-order (triangle) hold: exact for a command that is
linear between samples, with no frequency warping and no half-sample delay (a zero-order hold would
add ``dt/2`` of delay, Tustin would warp the benchmark's 67 Hz mode). The per-sample
:meth:`~rths_hil.sim_backends.base.ActuatorModel.step` of a state-space model is a matrix-vector
product into preallocated arrays (no allocation per step); :meth:`simulate` runs the same discrete
system as second-order sections (:func:`scipy.signal.sosfilt`) and agrees with the step path to
round-off.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rths_hil.errors import InputError

from .base import ActuatorModel, check_dt
from .benchmark import (
    BENCHMARK_CODE_GAIN,
    BENCHMARK_NOMINAL,
    BenchmarkServo,
    StateSpaceModel,
    benchmark_transfer_function,
)
from .delay import DelayGain
from .first_order import FirstOrderServo
from .registry import model_class, model_entry

__all__ = [
    "BENCHMARK_CODE_GAIN",
    "BENCHMARK_NOMINAL",
    "BenchmarkServo",
    "DelayGain",
    "FirstOrderServo",
    "Identity",
    "Series",
    "StateSpaceModel",
    "benchmark_transfer_function",
    "make_model",
]


class Identity(ActuatorModel):
    """The ideal actuator: achieved displacement = command."""

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)

    def reset(self) -> None:
        """Return to rest (zero state, empty delay lines)."""
        pass

    def step(self, command: float) -> float:
        """Advance one step: the achieved displacement (m) for ``command`` (m)."""
        return float(command)

    def simulate(self, command: np.ndarray) -> np.ndarray:
        """The achieved displacement (m) for a whole command history (m), from rest."""
        return np.array(command, dtype=float)


class Series(ActuatorModel):
    """Models in series: the output of each is the command of the next."""

    def __init__(self, models: Sequence[ActuatorModel]) -> None:
        if not models:
            raise ValueError("Series needs at least one model")
        dts = {m.dt for m in models}
        if len(dts) != 1:
            raise ValueError(f"models in series must share dt, got {sorted(dts)}")
        self.models = list(models)
        self.dt = models[0].dt

    def reset(self) -> None:
        """Return to rest (zero state, empty delay lines)."""
        for m in self.models:
            m.reset()

    def step(self, command: float) -> float:
        """Advance one step: the achieved displacement (m) for ``command`` (m)."""
        x = command
        for m in self.models:
            x = m.step(x)
        return x

    def simulate(self, command: np.ndarray) -> np.ndarray:
        """The achieved displacement (m) for a whole command history (m), from rest."""
        x = np.asarray(command, dtype=float)
        for m in self.models:
            x = m.simulate(x)
        return x


def make_model(
    name: str, dt: float, delay: float = 0.0, gain: float = 1.0, **params: float
) -> ActuatorModel:
    """Build ``name``'s dynamics followed by the delay and gain of the FEI paper's Fig. 4.1.

    Parameters
    ----------
    name : str
        Dynamics in front of the transport delay, a name of
        :data:`rths_hil.sim_backends.registry.MODELS` (``delay_gain``, ``servo_lag``,
        ``benchmark``).
    dt : float
        Step in seconds.
    delay : float
        Transport delay in seconds (≥ 0), fractional (not rounded to samples).
    gain : float
        Amplitude gain applied after the dynamics.
    **params
        The dynamics' parameters (see :data:`rths_hil.sim_backends.registry.MODELS`).
    """
    dt = check_dt(dt)
    name, entry = model_entry(name)
    if not math.isfinite(delay) or delay < 0:
        raise InputError(f"delay: must be ≥ 0 s, got {delay!r}")
    if not math.isfinite(gain):
        raise InputError(f"gain: must be a finite number, got {gain!r}")
    known = entry.params
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise InputError(f"{unknown[0]}: not a parameter of model {name!r}")
    missing = [k for k, (default, _) in known.items() if default is None and k not in params]
    if missing:
        raise InputError(f"{missing[0]}: required by model {name!r}")
    tail = DelayGain(delay, gain, dt)
    cls = model_class(name)
    if cls is None:
        return tail
    return Series([cls(dt=dt, **params), tail])

"""The twin plant: actuator model → effects → specimen → sensors.

:class:`TwinPlant` is the one plant of the twins: every protocol endpoint (CAN, Modbus, serial twin)
drives one, through the :class:`rths_hil.sim_backends.base.Plant` protocol it satisfies (a model
file, a configuration's ``[twin]`` section and :func:`rths_hil.sim_backends.twin.default_plant` all
build it). One step::

    x_a = actuator.step(command)          # achieved displacement of the model (m)
    x   = effects.step(x_a)               # catalogue effects, in order (m)
    F   = specimen.step(x)                # specimen force from the achieved displacement (N)
    measured_disp  = Q_d(x + n_d)         # displacement transducer: noise, then quantisation
    measured_force = Q_f(F + n_f)         # load cell

with ``n_d ~ N(0, σ_d²)``, ``n_f ~ N(0, σ_f²)`` white and independent, drawn from a seeded
:class:`numpy.random.Generator` (two streams spawned from one :class:`numpy.random.SeedSequence`,
so the same seed gives the same record whether stepped or simulated), and
``Q(v) = q·round(v/q)`` (round half to even; ``q = 0`` disables it). :meth:`TwinPlant.reset`
reseeds, so every run from rest is reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rths_hil.errors import InputError

from .base import ActuatorModel
from .effects import Effect, EffectChain
from .specimen import KelvinVoigt

__all__ = ["Sensor", "TwinPlant"]

#: noise samples drawn per refill: small, so that a refill (≈ 5 µs) is not a spike in the
#: reply time; the stream is the same for any block size
_BLOCK = 256


@dataclass(frozen=True)
class Sensor:
    """Measurement chain of the twin: white noise (std) and quantisation step per channel.

    Attributes
    ----------
    displacement_noise : float
        Standard deviation of the displacement noise, m.
    force_noise : float
        Standard deviation of the force noise, N.
    displacement_resolution : float
        Quantisation step of the displacement channel, m (0 = none).
    force_resolution : float
        Quantisation step of the force channel, N (0 = none).
    seed : int
        Seed of the noise generator.
    """

    displacement_noise: float = 0.0
    force_noise: float = 0.0
    displacement_resolution: float = 0.0
    force_resolution: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "displacement_noise",
            "force_noise",
            "displacement_resolution",
            "force_resolution",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not math.isfinite(float(value)) or float(value) < 0:
                raise InputError(f"{name}: must be a finite number ≥ 0, got {value!r}")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise InputError(f"seed: must be a non-negative integer, got {self.seed!r}")


class TwinPlant:
    """Actuator model + effects chain + specimen + sensor noise and quantisation.

    Parameters
    ----------
    actuator : ActuatorModel
        Command → achieved displacement; its ``dt`` is the plant's step.
    effects : sequence of Effect
        Applied in order after the actuator model.
    specimen : KelvinVoigt, optional
        Force from the achieved displacement; ``None`` measures zero force (before noise).
    sensor : Sensor, optional
        Noise and quantisation; default noiseless and unquantised.
    """

    def __init__(
        self,
        actuator: ActuatorModel,
        effects: Sequence[Effect] = (),
        specimen: KelvinVoigt | None = None,
        sensor: Sensor | None = None,
    ) -> None:
        self.actuator = actuator
        self.dt = float(actuator.dt)
        for e in effects:
            if abs(e.dt - self.dt) > 1e-12 * self.dt:
                raise ValueError(f"effect {e.kind} has dt={e.dt}, plant has {self.dt}")
        if specimen is not None and abs(specimen.dt - self.dt) > 1e-12 * self.dt:
            raise ValueError(f"specimen has dt={specimen.dt}, plant has {self.dt}")
        self.effects = EffectChain(effects)
        self.specimen = specimen
        self.sensor = sensor or Sensor()
        self._nd = np.empty(_BLOCK)
        self._nf = np.empty(_BLOCK)
        self.reset()

    # -- noise streams ------------------------------------------------------------------------
    def _reseed(self) -> None:
        disp_seq, force_seq = np.random.SeedSequence(int(self.sensor.seed)).spawn(2)
        self._rng_d = np.random.Generator(np.random.PCG64(disp_seq))
        self._rng_f = np.random.Generator(np.random.PCG64(force_seq))
        self._refill()  # now, not in the first step's reply

    def _refill(self) -> None:
        self._rng_d.standard_normal(out=self._nd)
        self._rng_f.standard_normal(out=self._nf)
        self._i = 0

    # -- Plant protocol -----------------------------------------------------------------------
    def reset(self) -> None:
        """Return to rest and reseed the noise."""
        self.actuator.reset()
        self.effects.reset()
        if self.specimen is not None:
            self.specimen.reset()
        self._reseed()
        self.true_displacement = 0.0
        self.true_force = 0.0

    def step(self, command: float) -> tuple[float, float]:
        """Advance one step; return (measured displacement in m, measured force in N).

        The noiseless achieved displacement and specimen force of the step are kept in
        :attr:`true_displacement` and :attr:`true_force`.
        """
        x = self.effects.step(self.actuator.step(float(command)))
        f = self.specimen.step(x) if self.specimen is not None else 0.0
        self.true_displacement = x
        self.true_force = f
        s = self.sensor
        if not (s.displacement_noise or s.force_noise or s.displacement_resolution):
            if not s.force_resolution:  # noiseless and unquantised: the true values
                return x, f
        if self._i >= _BLOCK:
            self._refill()
        i = self._i
        self._i = i + 1
        md = x + s.displacement_noise * float(self._nd[i])
        mf = f + s.force_noise * float(self._nf[i])
        qd = s.displacement_resolution
        if qd > 0 and math.isfinite(md):
            md = qd * round(md / qd)
        qf = s.force_resolution
        if qf > 0 and math.isfinite(mf):
            mf = qf * round(mf / qf)
        return md, mf

    def simulate(self, command: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Run a command history from rest; return (measured displacement, measured force).

        Vectorised; equal to stepping :meth:`step` from :meth:`reset` (same noise samples).
        The plant is left at rest (reset) afterwards.
        """
        self.reset()
        cmd = np.asarray(command, dtype=float)
        n = len(cmd)
        x = self.effects.simulate(self.actuator.simulate(cmd))
        f = self.specimen.simulate(x) if self.specimen is not None else np.zeros(n)
        # the first block was drawn by reset(); the rest continue the same streams
        nd = np.concatenate([self._nd, self._rng_d.standard_normal(max(n - _BLOCK, 0))])
        nf = np.concatenate([self._nf, self._rng_f.standard_normal(max(n - _BLOCK, 0))])
        s = self.sensor
        md = x + s.displacement_noise * nd[:n]
        mf = f + s.force_noise * nf[:n]
        if s.displacement_resolution > 0:
            md = s.displacement_resolution * np.round(md / s.displacement_resolution)
        if s.force_resolution > 0:
            mf = s.force_resolution * np.round(mf / s.force_resolution)
        self.reset()
        return md, mf

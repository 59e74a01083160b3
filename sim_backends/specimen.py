"""Specimen models: the force the load cell measures for the displacement the actuator achieves.

The default specimen is a linear Kelvin–Voigt element (spring and dashpot in parallel), with an
optional lumped mass moving with the actuator rod::

    F[k] = k·x[k] + c·v[k] + m·a[k]

where ``x`` is the achieved displacement (m), ``v`` and ``a`` its backward-difference velocity
and acceleration (``v[k] = (x[k] - x[k-1])/dt``, ``a[k] = (v[k] - v[k-1])/dt``, from rest).
The backward difference lags by ``dt/2`` (0.5 ms at 1024 Hz) on the damping force, which is
small beside actuator delays of 5-40 ms; it is causal, as a twin must be. The default
parameters are the RTHS benchmark's specimen (Silva et al. 2020, Table 2: k = 1.19e6 N/m,
c = 114.6 N·s/m) without its mass.
"""

from __future__ import annotations

import math

import numpy as np

from rths_hil.errors import InputError

__all__ = ["SPECIMEN_DEFAULTS", "KelvinVoigt"]

#: Default Kelvin–Voigt specimen (benchmark specimen of Silva et al. 2020, Table 2, no mass).
SPECIMEN_DEFAULTS: dict[str, float] = {"stiffness": 1.19e6, "damping": 114.6, "mass": 0.0}


class KelvinVoigt:
    """Linear spring–dashpot (optionally with mass): ``F = k x + c ẋ + m ẍ``.

    Parameters
    ----------
    stiffness : float
        ``k`` in N/m (≥ 0).
    damping : float
        ``c`` in N·s/m (≥ 0).
    dt : float
        Step in seconds.
    mass : float
        ``m`` in kg (≥ 0), default 0.
    """

    def __init__(self, stiffness: float, damping: float, dt: float, mass: float = 0.0) -> None:
        for name, value in (("stiffness", stiffness), ("damping", damping), ("mass", mass)):
            if not math.isfinite(float(value)) or float(value) < 0:
                raise InputError(f"{name}: must be a finite number ≥ 0, got {value!r}")
        if not math.isfinite(float(dt)) or float(dt) <= 0:
            raise InputError(f"dt: must be > 0 s, got {dt!r}")
        self.stiffness = float(stiffness)
        self.damping = float(damping)
        self.mass = float(mass)
        self.dt = float(dt)
        self.reset()

    def reset(self) -> None:
        """Return to rest (previous displacement and velocity zero)."""
        self._x1 = 0.0
        self._v1 = 0.0

    def step(self, displacement: float) -> float:
        """Force (N) for the achieved ``displacement`` (m) of this step."""
        v = (displacement - self._x1) / self.dt
        a = (v - self._v1) / self.dt
        self._x1 = displacement
        self._v1 = v
        return self.stiffness * displacement + self.damping * v + self.mass * a

    def simulate(self, displacement: np.ndarray) -> np.ndarray:
        """Force history for a displacement history from rest (vectorised, same as stepping)."""
        # where used: a twin's start-up (twin serve) does without scipy.signal's second
        from scipy.signal import lfilter

        self.reset()
        x = np.asarray(displacement, dtype=float)
        v = lfilter([1.0, -1.0], [1.0], x) / self.dt
        a = lfilter([1.0, -1.0], [1.0], v) / self.dt
        return self.stiffness * x + self.damping * v + self.mass * a

    def params(self) -> dict[str, float]:
        """Parameters as written in the model file's ``[specimen]`` table."""
        return {"stiffness": self.stiffness, "damping": self.damping, "mass": self.mass}

"""The contract every actuator model and every twin plant satisfies.

An :class:`ActuatorModel` maps the command displacement sent to the actuator controller, one
sample at a time at a fixed step ``dt``, to the displacement the actuator achieves. A
:class:`Plant` is what a protocol endpoint (CAN, Modbus, serial twin) drives: it returns the
measured displacement *and* the measured specimen force for each command. Units are SI
(m, N, s).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Protocol, runtime_checkable

import numpy as np

from rths_hil.units import positive_number


def check_dt(dt: float) -> float:
    """``dt`` as a float, or an input error unless it is a positive number of seconds.

    The check is :func:`rths_hil.units.positive_number`.
    """
    return positive_number(dt, "dt (s)")


class ActuatorModel(ABC):
    """A discrete-time single-input single-output actuator model stepped at ``dt``.

    Subclasses implement :meth:`reset` and :meth:`step`; :meth:`simulate` runs a whole command
    history from rest (subclasses may override it with a vectorised equivalent that must give the
    same result to round-off).
    """

    dt: float

    @abstractmethod
    def reset(self) -> None:
        """Return to rest (zero state, empty delay lines)."""

    @abstractmethod
    def step(self, command: float) -> float:
        """Advance one step with ``command`` (m) and return the achieved displacement (m)."""

    def simulate(self, command: np.ndarray) -> np.ndarray:
        """Run ``command`` (m, one value per step) from rest; return the displacement history."""
        self.reset()
        cmd = np.asarray(command, dtype=float)
        out = np.empty_like(cmd)
        step = self.step
        for i, c in enumerate(cmd.tolist()):
            out[i] = step(c)
        return out


@runtime_checkable
class Plant(Protocol):
    """What a twin endpoint drives: command in, (measured displacement, measured force) out."""

    dt: float

    def reset(self) -> None:
        """Return to rest."""

    def step(self, command: float) -> tuple[float, float]:
        """Advance one step; return (measured displacement in m, measured force in N)."""
        ...

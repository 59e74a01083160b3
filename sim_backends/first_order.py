"""The first-order servo lag ``1 / (T s + 1)`` with a first-order hold.

:func:`first_order_coeffs` gives the discrete filter (used by :class:`FirstOrderServo`, the
``servo_lag`` and ``force_feedback`` effects and the diagnosis): the closed form of
:func:`scipy.signal.cont2discrete` with ``method="foh"``, exact for a command that is linear
between samples, no half-sample delay.
"""

from __future__ import annotations

import math

import numpy as np

from rths_hil.errors import InputError

from .base import ActuatorModel, check_dt

__all__ = ["FirstOrderSection", "FirstOrderServo", "first_order_coeffs"]


def first_order_coeffs(
    gain: float, time_constant: float, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Discrete ``(b, a)`` of ``gain / (T s + 1)`` with a first-order hold (``a[0] = 1``).

    Closed form of :func:`scipy.signal.cont2discrete` with ``method="foh"`` (equal to it to
    round-off): with ``p = exp(−dt/T)`` and ``c = (T/dt)(1 − p)``,
    ``H(z) = gain·(b0 + b1 z⁻¹)/(1 − p z⁻¹)``, ``b0 = 1 − c``, ``b1 = c − p`` (from
    ``H(z) = (z − 1)²/(z dt) · Z{G(s)/s²}``).
    """
    p = math.exp(-dt / time_constant)
    c = (time_constant / dt) * -math.expm1(-dt / time_constant)
    return np.array([gain * (1.0 - c), gain * (c - p)]), np.array([1.0, -p])


class FirstOrderSection:
    """A first-order section ``(b0 + b1 z⁻¹) / (1 + a1 z⁻¹)`` stepped or run on a whole history.

    :meth:`step` is the transposed direct form II recursion that :func:`scipy.signal.lfilter`
    uses, so :meth:`step` and :meth:`simulate` agree to the last bit. The class that takes it
    (:class:`FirstOrderServo`, the ``force_feedback`` effect) sets its coefficients with
    :meth:`_set_section`.
    """

    b: np.ndarray
    a: np.ndarray

    def _set_section(self, b: np.ndarray, a: np.ndarray) -> None:
        """The coefficients ``b = (b0, b1)`` and ``a = (1, a1)``; the state at rest."""
        self.b, self.a = b, a
        self._b0, self._b1, self._a1 = float(b[0]), float(b[1]), float(a[1])
        self._z = 0.0

    def reset(self) -> None:
        """Return to rest (zero state)."""
        self._z = 0.0

    def step(self, x: float) -> float:
        """Advance one step with input ``x``; the output."""
        y = self._b0 * x + self._z
        self._z = self._b1 * x - self._a1 * y
        return y

    def simulate(self, x: np.ndarray) -> np.ndarray:
        """The output for a whole input history, from rest."""
        # where used: a twin's start-up (twin serve) does without scipy.signal's second
        from scipy.signal import lfilter

        self.reset()
        return lfilter(self.b, self.a, np.asarray(x, dtype=float))


class FirstOrderServo(FirstOrderSection, ActuatorModel):
    """First-order servo lag ``G(s) = 1 / (T s + 1)`` discretised with a first-order hold.

    The lag is the dominant dynamics of a servo-hydraulic actuator under proportional control:
    the closed position loop has a pole at ``kp·kq/A`` (valve flow gain over piston area), i.e.
    ``T = A / (kp kq)``, typically 2-20 ms. At low frequency it behaves as a delay of ``T``
    (phase ``-atan(ωT) ≈ -ωT``) with amplitude ``1/sqrt(1 + ω²T²)``.

    Parameters
    ----------
    time_constant : float
        ``T`` in seconds (> 0).
    dt : float
        Step in seconds.

    Notes
    -----
    The step path is the transposed direct form II recursion that :func:`scipy.signal.lfilter`
    uses, so :meth:`step` and :meth:`simulate` agree to the last bit.
    """

    def __init__(self, time_constant: float, dt: float) -> None:
        self.dt = check_dt(dt)
        t = float(time_constant)
        if not math.isfinite(t) or t <= 0:
            raise InputError(f"time_constant: must be > 0 s, got {time_constant!r}")
        self.time_constant = t
        self._set_section(*first_order_coeffs(1.0, t, self.dt))

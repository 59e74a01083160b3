"""Polynomial extrapolation of the target over the compensated delay (Horiuchi et al.).

Horiuchi, Inoue, Konno & Namita ("Real-time hybrid experimental system with actuator delay
compensation and its application to a piping system with energy absorber", *Earthquake
Engineering and Structural Dynamics* 28, 1121–1141, 1999) send the actuator, instead of the
target ``x_t(t)``, its prediction ``x_t(t + τ)`` over the actuator delay ``τ``, from the
n-th order polynomial through the last n + 1 targets; Horiuchi & Konno ("A new method for
compensating actuator delay in real-time hybrid experiments", *Phil. Trans. R. Soc. A* 359,
1893–1909, 2001) discuss the order and its stability. In Lagrange form, with the targets
``x_{k−j}`` at ``t_k − j·Δt`` (j = 0 … n) and ``s = τ/Δt``::

    x_c[k] = a · Σ_j ℓ_j(s) · x_t[k − j],   ℓ_j(s) = Π_{m ≠ j} (s + m) / (m − j)

(exact for a target that is a polynomial of degree ≤ n). ``n = 1`` is inverse compensation with
``α = 1 + s`` (Chen & Ricles 2009). The amplitude error of the prediction of a sinusoid of
frequency f is of order ``(2π f τ)^(n+1)``, so a higher order removes the overshoot that inverse
compensation leaves on a pure delay; the gain at high frequency grows with ``Σ|ℓ_j|``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

from ..errors import InputError
from ..keys import Key
from ..units import positive_number
from .base import Compensator

__all__ = ["PolynomialCompensator", "lagrange_extrapolation"]


def lagrange_extrapolation(order: int, s: float) -> list[float]:
    """Weights ``ℓ_j(s)`` (j = 0 … order) of the targets ``x[k − j]`` for ``x(t_k + s·Δt)``."""
    out = []
    for j in range(order + 1):
        w = 1.0
        for m in range(order + 1):
            if m != j:
                w *= (s + m) / (m - j)
        out.append(w)
    return out


class PolynomialCompensator(Compensator):
    """n-th order polynomial extrapolation over ``delay`` (see the module docstring).

    Parameters
    ----------
    fs : float
        Loop rate (Hz).
    delay : float
        Delay τ to compensate (s, ≥ 0).
    order : int
        n, 1 … 4.
    amplitude : float
        Amplitude factor ``a`` on the command.
    """

    ARGUMENTS: ClassVar[Mapping[str, str]] = {
        "delay": "delay",
        "order": "order",
        "amplitude": "amplitude",
    }
    KEYS: ClassVar[Mapping[str, Key]] = {
        "order": Key("int", 3, doc="polynomial: order n of the extrapolation (1 … 4)", lo=1, hi=4),
    }
    __slots__ = ("_h", "_w", "alpha", "amplitude", "delay", "enabled", "fs", "order")

    def __init__(self, fs: float, delay: float, order: int = 3, amplitude: float = 1.0) -> None:
        if not (isinstance(order, int) and 1 <= order <= 4):
            raise InputError(f"compensation.order: must be 1 … 4, got {order!r}")
        self.fs = float(fs)
        self.delay = positive_number(delay, "compensation.delay (s)", allow_zero=True)
        self.order = order
        self.amplitude = positive_number(amplitude, "compensation.amplitude")
        self.enabled = True
        self.alpha = 1.0 + self.delay * self.fs
        self._w = [self.amplitude * w for w in lagrange_extrapolation(order, self.delay * fs)]
        self._h = [0.0] * order  # x[k−1] … x[k−n]

    def reset(self, target: float = 0.0) -> None:
        """The target has been ``target`` forever."""
        self._h = [float(target)] * self.order

    def step(self, target: float) -> float:
        """Return ``a · Σ ℓ_j x[k − j]``."""
        h = self._h
        w = self._w
        y = w[0] * target
        for j in range(self.order):
            y += w[j + 1] * h[j]
        h.pop()
        h.insert(0, target)
        return y

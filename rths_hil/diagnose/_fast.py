"""Fast simulation of the catalogue effects the fitting evaluates most often.

The diagnosis simulates candidate effects hundreds of times per record, so:

* ``velocity_limit`` — :class:`rths_hil.sim_backends.effects.VelocityLimit` has no closed form and
  its vectorised path loops in Python over every stretch where the limit is active (most of the
  record for the small limits a fit tries); here the same recursion is compiled with numba, with the
  same comparisons in the same order as its ``step``: equal bit for bit.
* ``backlash`` — the catalogue's exact prefix scan costs a dozen numpy passes; the plain
  recursion ``y[k] = clip(y[k-1], x[k] − w/2, x[k] + w/2)`` compiled is one, with the same
  min/max: equal bit for bit.
* ``time_varying_delay`` — the catalogue gathers 4 Lagrange taps per sample with numpy (a dozen
  temporary arrays); compiled, the same formula (``τ[k] = D + a·sin(2πk dt/P)`` in samples,
  ``n0 = max(⌊τ⌋ − 1, 0)``, taps of :func:`rths_hil.sim_backends.delay.lagrange_weights`) is one
  pass, equal to round-off.

``servo_lag``, ``force_feedback`` (:func:`first_order`) and the transport delay
(:func:`rths_hil.sim_backends.delay.fractional_delay`) use the catalogue's own filters.

Every other effect goes through the catalogue itself.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.signal import lfilter

from rths_hil.sim_backends.delay import fractional_delay, lagrange_weights_jit
from rths_hil.sim_backends.effects import make_effect, validate_params
from rths_hil.sim_backends.first_order import first_order_coeffs
from rths_hil.sim_backends.modelfile import EffectSpec

__all__ = [
    "backlash",
    "first_order",
    "fractional_delay",
    "simulate_chain",
    "simulate_effect",
    "time_varying_delay",
    "velocity_limit",
]


@numba.njit(cache=True, nogil=True)
def _velocity_limit(x: np.ndarray, dmax: float) -> np.ndarray:  # pragma: no cover - compiled
    out = np.empty_like(x)
    y = 0.0
    for k in range(x.shape[0]):
        d = x[k] - y
        if d > dmax:
            y += dmax
        elif d < -dmax:
            y -= dmax
        else:
            y = x[k]
        out[k] = y
    return out


@numba.njit(cache=True, nogil=True)
def _backlash(x: np.ndarray, half: float) -> np.ndarray:  # pragma: no cover - compiled
    out = np.empty_like(x)
    y = 0.0
    for k in range(x.shape[0]):
        lo = x[k] - half
        hi = x[k] + half
        if y < lo:
            y = lo
        elif y > hi:
            y = hi
        out[k] = y
    return out


@numba.njit(cache=True, nogil=True)
def _tvd(x: np.ndarray, d0: float, d1: float, w: float) -> np.ndarray:  # pragma: no cover
    n = x.shape[0]
    out = np.zeros(n)
    for k in range(n):
        d = d0 + d1 * math.sin(w * k)
        n0 = max(math.floor(d) - 1.0, 0.0)
        taps = lagrange_weights_jit(d - n0)
        i = k - int(n0)
        acc = 0.0
        for j in range(4):
            if i - j >= 0:
                acc += taps[j] * x[i - j]
        out[k] = acc
    return out


def time_varying_delay(
    x: np.ndarray, delay: float, amplitude: float, period: float, dt: float
) -> np.ndarray:
    """``time_varying_delay`` from rest: ``y(t) = x(t − τ(t))``, ``τ = D + a·sin(2πt/P)``."""
    make_effect("time_varying_delay", dt, delay=delay, amplitude=amplitude, period=period)
    return _tvd(
        np.ascontiguousarray(x, dtype=float),
        delay / dt,
        amplitude / dt,
        2.0 * math.pi * dt / period,
    )


def backlash(x: np.ndarray, width: float, dt: float) -> np.ndarray:
    """``backlash`` from rest (``y[-1] = 0``)."""
    make_effect("backlash", dt, width=width)  # the catalogue's parameter checks
    return _backlash(np.ascontiguousarray(x, dtype=float), 0.5 * float(width))


def velocity_limit(x: np.ndarray, limit: float, dt: float) -> np.ndarray:
    """``velocity_limit`` from rest: ``y[k] = y[k-1] + clip(x[k] - y[k-1], ±limit·dt)``."""
    make_effect("velocity_limit", dt, limit=limit)  # the catalogue's parameter checks
    return _velocity_limit(np.ascontiguousarray(x, dtype=float), float(limit * dt))


def first_order(x: np.ndarray, gain: float, time_constant: float, dt: float) -> np.ndarray:
    """``gain/(T s + 1)`` with a first-order hold, from rest (:func:`first_order_coeffs`)."""
    if time_constant <= 0:
        return gain * np.asarray(x, dtype=float)
    b, a = first_order_coeffs(gain, time_constant, dt)
    return lfilter(b, a, np.asarray(x, dtype=float))


def simulate_effect(kind: str, params: dict[str, float], x: np.ndarray, dt: float) -> np.ndarray:
    """Output of catalogue effect ``kind`` with ``params`` for input ``x``, from rest."""
    if kind == "velocity_limit":
        return velocity_limit(x, params["limit"], dt)
    if kind == "backlash":
        return backlash(x, params["width"], dt)
    if kind == "time_varying_delay":
        p = validate_params(kind, params)
        return time_varying_delay(x, p["delay"], p["amplitude"], p["period"], dt)
    if kind == "servo_lag":
        validate_params(kind, params)
        return first_order(x, 1.0, params["time_constant"], dt)
    if kind == "force_feedback":
        p = validate_params(kind, params)
        total = p["actuator_stiffness"] + p["specimen_stiffness"]
        return first_order(x, p["actuator_stiffness"] / total, p["specimen_damping"] / total, dt)
    return make_effect(kind, dt, **params).simulate(x)


def simulate_chain(effects: list[EffectSpec], x: np.ndarray, dt: float) -> np.ndarray:
    """Effects applied in order."""
    for e in effects:
        x = simulate_effect(e.kind, e.params, x, dt)
    return x

"""The effects catalogue: physical imperfections a twin adds on top of any actuator model.

Each effect maps the displacement coming out of the previous stage (the actuator model or the
previous effect) to a modified displacement, one sample at a time (:meth:`Effect.step`) or over a
whole history (:meth:`Effect.simulate`, vectorised, equal to the step path to round-off). The
same catalogue serves the twin (:mod:`rths_hil.sim_backends.plant`) and the discrepancy-diagnosis
workflow, which fits the parameters of these effects to records; :data:`EFFECT_RANGES` gives
the realistic parameter ranges both draw from. Names, in SI units (``x`` input, ``y`` output,
``t = k·dt`` the time since reset, ``k = 0`` at the first sample):

=====================  =======================================================================
``offset``             ``y = x + offset`` — zero error of the displacement transducer/set point.
``drift``              ``y = x + rate·t`` — thermal drift of the LVDT conditioning, slow leak.
``backlash``           play of total ``width`` in the load train (clevis pins, swivels):
                       ``y[k] = clip(y[k-1], x[k] - width/2, x[k] + width/2)``, ``y[-1] = 0``.
``velocity_limit``     servo-valve flow saturation, ``|ẏ| ≤ limit``:
                       ``y[k] = y[k-1] + clip(x[k] - y[k-1], -limit·dt, limit·dt)``.
``stroke_limit``       end stops / displacement interlock:
                       ``y = clip(x, center - limit, center + limit)``.
``servo_lag``          first-order lag ``1/(T s + 1)`` (first-order hold), ``T = time_constant``.
``time_varying_delay`` ``y(t) = x(t - τ(t))``, ``τ(t) = delay + amplitude·sin(2π t/period)``,
                       fractional (Lagrange, as :mod:`rths_hil.sim_backends.delay`).
``force_feedback``     control-structure interaction through the oil-column compliance:
                       ``k_h (x - y) = k_s y + c_s ẏ`` → ``y = x·k_h/(k_h + k_s)`` lagged by
                       ``T = c_s/(k_h + k_s)``.
=====================  =======================================================================

Backlash is vectorised exactly with a parallel prefix scan of clamp compositions (a composition
of clamps is a clamp), so even that path-dependent effect runs in ``log2(N)`` numpy passes.
The velocity limit has no such closed form and runs a tight scalar loop.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from rths_hil.errors import InputError

from .delay import ORDER, lagrange_split, lagrange_taps, lagrange_weights
from .effect_base import (
    EFFECTS,
    Effect,
    Fitting,
    Param,
    ParamRange,
    _positive,
    validate_params,
)
from .first_order import FirstOrderSection, FirstOrderServo, first_order_coeffs

_MM = 1e-3

__all__ = [
    "EFFECTS",
    "EFFECT_ORDER",
    "EFFECT_RANGES",
    "FORCE_EFFECTS",
    "FORCE_REFUSED",
    "FORCE_UNITS",
    "Backlash",
    "Drift",
    "Effect",
    "EffectChain",
    "Fitting",
    "ForceFeedback",
    "Offset",
    "Param",
    "ParamRange",
    "ServoLag",
    "StrokeLimit",
    "TimeVaryingDelay",
    "VelocityLimit",
    "draw_effect_params",
    "make_effect",
    "validate_params",
]


class _Stateless(Effect):
    """Helper base for effects with no memory beyond the sample counter."""

    def reset(self) -> None:
        self._k = 0


class Offset(_Stateless):
    """Constant displacement error: ``y = x + offset``.

    Physical origin: the transducer zero or the controller set point differs from the
    numerical model's zero (specimen installed at a slightly different position, LVDT re-zeroed
    under load). Realistic magnitude 0.1-2 mm.
    """

    kind = "offset"
    PARAMS = (
        Param(
            "offset",
            "m",
            "constant displacement error",
            typical=ParamRange(
                0.1 * _MM, 2 * _MM, signed=True, log=True, note="transducer zero / set-point error"
            ),
        ),
    )
    CHAIN = 60
    PREFERENCE = 10
    FIT = Fitting("linear", "offset")

    @classmethod
    def regressor(cls, t: np.ndarray) -> np.ndarray:
        return np.ones(len(t))

    def _setup(self) -> None:
        self._offset = self.params["offset"]

    def step(self, x: float) -> float:
        return x + self._offset

    def simulate(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=float) + self._offset


class Drift(_Stateless):
    """Linear drift from reset: ``y[k] = x[k] + rate·k·dt``.

    Physical origin: warm-up of the LVDT conditioning electronics and oil temperature, or a
    slow leak past a worn piston seal under static load. Realistic 0.5-5 mm/min
    (8.3e-6 - 8.3e-5 m/s) over a test of a few minutes.
    """

    kind = "drift"
    PARAMS = (
        Param(
            "rate",
            "m/s",
            "drift velocity",
            typical=ParamRange(
                0.5 * _MM / 60, 5 * _MM / 60, signed=True, log=True, note="0.5-5 mm/min"
            ),
        ),
    )
    CHAIN = 70
    PREFERENCE = 20
    FIT = Fitting("linear", "rate")

    @classmethod
    def regressor(cls, t: np.ndarray) -> np.ndarray:
        return t

    def _setup(self) -> None:
        self._step = self.params["rate"] * self.dt

    def step(self, x: float) -> float:
        y = x + self._step * self._k
        self._k += 1
        return y

    def simulate(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        self._k = len(x)
        return x + self._step * np.arange(len(x), dtype=float)


class StrokeLimit(_Stateless):
    """Saturation at the end stops: ``y = clip(x, center - limit, center + limit)``.

    Physical origin: the actuator's mechanical stroke, or a displacement interlock set in the
    controller. Realistic ``limit`` 5-150 mm (a ±50 to ±250 mm actuator, interlocks set at a
    fraction of it); the effect only shows when the response reaches it.
    """

    kind = "stroke_limit"
    PARAMS = (
        _positive(
            "limit",
            "m",
            "half stroke (distance from center to either stop)",
            ParamRange(5 * _MM, 150 * _MM, log=True, note="end stop or interlock"),
        ),
        Param(
            "center",
            "m",
            "mid-stroke position",
            default=0.0,
            typical=ParamRange(0.0, 2 * _MM, signed=True, note="mid-stroke error"),
            step=1e-3,
        ),
    )
    CHAIN = 40
    PREFERENCE = 70
    FIT = Fitting("stops")

    def _setup(self) -> None:
        self._lo = self.params["center"] - self.params["limit"]
        self._hi = self.params["center"] + self.params["limit"]

    def step(self, x: float) -> float:
        return min(max(x, self._lo), self._hi)

    def simulate(self, x: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(x, dtype=float), self._lo, self._hi)


_SCAN_BLOCK = 64


class Backlash(Effect):
    """Play (dead band) of total ``width`` between actuator and specimen.

    ``y[k] = clip(y[k-1], x[k] - width/2, x[k] + width/2)`` with ``y[-1] = 0``: the output
    follows the input only once the input has crossed the gap, the play operator of hysteresis
    modelling. Physical origin: clearance in clevis pins, swivels and bolted connections.
    Realistic 0.05-0.5 mm.

    :meth:`simulate` is an exact parallel prefix scan: each step is the clamp
    ``y ↦ clip(y, lo_k, hi_k)`` and ``clip(·, lo2, hi2) ∘ clip(·, lo1, hi1)`` is the clamp with
    bounds ``clip(lo1, lo2, hi2)``, ``clip(hi1, lo2, hi2)``. Hillis–Steele doubling composes the
    prefixes inside blocks of 64 samples (6 vectorised passes over the whole record), a scalar
    loop carries the output across the ``N/64`` blocks, and one clamp per sample gives the
    output. Only min/max are used, so it equals stepping bit for bit.
    """

    kind = "backlash"
    PARAMS = (
        Param(
            "width",
            "m",
            "total play",
            minimum=0.0,
            typical=ParamRange(
                0.05 * _MM, 0.5 * _MM, log=True, note="clearance of pins and swivels"
            ),
        ),
    )
    CHAIN = 50
    PREFERENCE = 50
    FIT = Fitting("scalar", "width", 1e-6, 5e-3)

    @classmethod
    def clamp(cls, params: dict[str, float]) -> None:
        params["width"] = max(params["width"], 0.0)

    def _setup(self) -> None:
        self._half = 0.5 * self.params["width"]

    def reset(self) -> None:
        self._y = 0.0

    def step(self, x: float) -> float:
        lo = x - self._half
        hi = x + self._half
        y = self._y
        if y < lo:
            y = lo
        elif y > hi:
            y = hi
        self._y = y
        return y

    def simulate(self, x: np.ndarray) -> np.ndarray:
        self.reset()
        x = np.asarray(x, dtype=float)
        n = len(x)
        if n == 0:
            return x.copy()
        # blocks of _SCAN_BLOCK samples: scan within every block at once (log2 B passes on a
        # 2-D array), then carry the output across blocks with one short scalar loop
        nb = -(-n // _SCAN_BLOCK)
        lo = np.full(nb * _SCAN_BLOCK, -np.inf)
        hi = np.full(nb * _SCAN_BLOCK, np.inf)  # padding: the identity clamp
        np.subtract(x, self._half, out=lo[:n])
        np.add(x, self._half, out=hi[:n])
        lo2 = lo.reshape(nb, _SCAN_BLOCK)
        hi2 = hi.reshape(nb, _SCAN_BLOCK)
        shift = 1
        while shift < _SCAN_BLOCK:
            # compose step j (outer) after the prefix ending at j - shift (inner)
            lo_out = lo2[:, shift:]
            hi_out = hi2[:, shift:]
            new_lo = np.minimum(np.maximum(lo2[:, :-shift], lo_out), hi_out)
            new_hi = np.minimum(np.maximum(hi2[:, :-shift], lo_out), hi_out)
            lo_out[...] = new_lo
            hi_out[...] = new_hi
            shift *= 2
        starts = np.empty((nb, 1))
        y = self._y
        for b, (blo, bhi) in enumerate(zip(lo2[:, -1].tolist(), hi2[:, -1].tolist(), strict=True)):
            starts[b, 0] = y
            y = min(max(y, blo), bhi)
        self._y = y
        return np.minimum(np.maximum(starts, lo2), hi2).ravel()[:n]


class VelocityLimit(Effect):
    """Rate limit ``|ẏ| ≤ limit``: ``y[k] = y[k-1] + clip(x[k] - y[k-1], ±limit·dt)``.

    Physical origin: the servo-valve's rated flow ``Q`` caps the piston speed at ``Q/A``
    (e.g. 57 l/min on a 50 cm² piston: 0.19 m/s). Realistic 0.02-0.2 m/s for RTHS actuators.

    The recursion has no closed form. :meth:`simulate` finds vectorised where the output simply
    tracks the input (``y[k-1] = x[k-1]`` and ``|x[k] - x[k-1]| ≤ limit·dt`` gives
    ``y[k] = x[k]``) and runs a tight scalar loop only from each violation until the output has
    caught up again; with the same comparisons as :meth:`step`, the two agree bit for bit.
    """

    kind = "velocity_limit"
    PARAMS = (
        _positive(
            "limit",
            "m/s",
            "maximum speed",
            ParamRange(0.02, 0.2, log=True, note="rated valve flow / piston area"),
        ),
    )
    CHAIN = 30
    PREFERENCE = 60
    FIT = Fitting("scalar", "limit")

    @staticmethod
    def _peak_speed(x: np.ndarray, fs: float) -> float:
        return float(np.max(np.abs(np.diff(x)))) * fs

    @classmethod
    def fit_bounds(
        cls, x: np.ndarray, fs: float, specimen: tuple[float, float] | None
    ) -> tuple[float, float]:
        """From a fiftieth of the input's peak speed to just above it."""
        vmax = cls._peak_speed(x, fs)
        return vmax / 50.0, vmax * 1.01

    @classmethod
    def fit_note(cls, params: dict[str, float], x: np.ndarray, fs: float) -> str:
        if params["limit"] >= cls._peak_speed(x, fs):
            return "limit above the model's peak speed: inactive"
        return ""

    def _setup(self) -> None:
        self._dmax = self.params["limit"] * self.dt

    def reset(self) -> None:
        self._y = 0.0

    def step(self, x: float) -> float:
        d = x - self._y
        dmax = self._dmax
        if d > dmax:
            self._y += dmax
        elif d < -dmax:
            self._y -= dmax
        else:
            self._y = x
        return self._y

    def simulate(self, x: np.ndarray) -> np.ndarray:
        self.reset()
        x = np.asarray(x, dtype=float)
        n = len(x)
        out = x.copy()
        if n == 0:
            return out
        dmax = self._dmax
        d = np.empty(n)
        d[0] = x[0]  # from rest: y[-1] = x[-1] = 0
        np.subtract(x[1:], x[:-1], out=d[1:])
        viol = np.flatnonzero((d > dmax) | (d < -dmax))
        if len(viol) == 0:
            self._y = float(x[-1])
            return out
        xs = x.tolist()
        vi = 0
        while vi < len(viol):
            j = int(viol[vi])
            y = xs[j - 1] if j > 0 else 0.0  # tracking before j: y[j-1] = x[j-1]
            seg = []
            i = j
            while i < n:
                v = xs[i]
                dv = v - y
                if dv > dmax:
                    y += dmax
                elif dv < -dmax:
                    y -= dmax
                else:
                    break  # caught up: y[i] = x[i], tracking again
                seg.append(y)
                i += 1
            out[j : j + len(seg)] = seg
            vi = int(np.searchsorted(viol, i + 1))
        self._y = float(out[-1])
        return out


class ServoLag(Effect):
    """First-order servo lag ``1/(T s + 1)`` on top of the model, ``T = time_constant``.

    Physical origin: finite bandwidth of the position loop (``T = A/(kp·kq)``); acts as an extra
    delay ≈ ``T`` with amplitude ``1/sqrt(1 + (ωT)²)``. Realistic 2-20 ms. Same discretisation as
    :class:`~rths_hil.sim_backends.first_order.FirstOrderServo` (first-order hold), step and
    :func:`scipy.signal.lfilter` paths identical to the last bit.
    """

    kind = "servo_lag"
    PARAMS = (
        _positive(
            "time_constant",
            "s",
            "lag time constant",
            ParamRange(2e-3, 20e-3, log=True, note="position-loop bandwidth 8-80 Hz"),
        ),
    )
    CHAIN = 10
    PREFERENCE = 30
    FIT = Fitting("scalar", "time_constant", 1e-4, 0.1)

    @classmethod
    def low_frequency(cls, params: dict[str, float]) -> tuple[float, float]:
        """A delay of ``T`` at gain 1."""
        return params["time_constant"], 1.0

    def _setup(self) -> None:
        self._servo = FirstOrderServo(self.params["time_constant"], self.dt)

    def reset(self) -> None:
        self._servo.reset()

    def step(self, x: float) -> float:
        return self._servo.step(x)

    def simulate(self, x: np.ndarray) -> np.ndarray:
        return self._servo.simulate(x)


class TimeVaryingDelay(Effect):
    """Fractional delay that varies in time: ``y(t) = x(t - τ(t))``.

    ``τ(t) = delay + amplitude·sin(2π t / period)``. Physical origin: the actuator's equivalent
    delay changes with oil temperature, amplitude and velocity of the motion (valve opening) and
    specimen stiffness during a test; 10-20 % variation of a 10-30 ms delay is typical.
    Realistic ``delay`` 5-30 ms, ``amplitude`` 0.5-5 ms (must not exceed ``delay``),
    ``period`` 2-60 s. The interpolation is the 4-tap Lagrange FIR of
    :func:`rths_hil.sim_backends.delay.lagrange_taps` evaluated per sample (vectorised gather in
    :meth:`simulate`), from rest (zeros before the first sample).
    """

    kind = "time_varying_delay"
    PARAMS = (
        Param(
            "delay",
            "s",
            "mean delay",
            minimum=0.0,
            typical=ParamRange(5e-3, 30e-3, note="mean equivalent delay"),
            step=1e-3,
        ),
        Param(
            "amplitude",
            "s",
            "amplitude of the sinusoidal variation",
            default=0.0,
            minimum=0.0,
            typical=ParamRange(0.5e-3, 5e-3, note="≤ delay by construction of the ranges"),
        ),
        _positive(
            "period",
            "s",
            "period of the variation",
            ParamRange(2.0, 60.0, log=True, note="slow variation over a test"),
            default=10.0,
        ),
    )
    CHAIN = 0
    PREFERENCE = 80
    FIT = Fitting("modulated_delay")

    @classmethod
    def clamp(cls, params: dict[str, float]) -> None:
        params["amplitude"] = min(max(params["amplitude"], 0.0), max(params["delay"], 0.0))
        params["delay"] = max(params["delay"], 0.0)

    @classmethod
    def check(cls, params: dict[str, float], where: str) -> None:
        if params["amplitude"] > params["delay"]:
            raise InputError(
                f"{where}amplitude: must not exceed delay ({params['delay']} s) or the delay "
                f"would become negative, got {params['amplitude']}"
            )

    def _setup(self) -> None:
        p = self.params
        self._w = 2.0 * math.pi * self.dt / p["period"]
        self._d0 = p["delay"] / self.dt
        self._d1 = p["amplitude"] / self.dt
        n0_max, _ = lagrange_taps(self._d0 + self._d1 + 1.0)
        self._size = n0_max + ORDER + 2

    def reset(self) -> None:
        self._buf = [0.0] * self._size
        self._pos = 0
        self._k = 0

    def step(self, x: float) -> float:
        buf = self._buf
        size = self._size
        buf[self._pos] = x
        newest = self._pos
        self._pos = (newest + 1) % size
        d = self._d0 + self._d1 * math.sin(self._w * self._k)
        self._k += 1
        n0, f = lagrange_split(d)
        taps = lagrange_weights(f)
        base = newest - n0
        return (
            taps[0] * buf[base % size]
            + taps[1] * buf[(base - 1) % size]
            + taps[2] * buf[(base - 2) % size]
            + taps[3] * buf[(base - 3) % size]
        )

    def simulate(self, x: np.ndarray) -> np.ndarray:
        self.reset()
        x = np.asarray(x, dtype=float)
        n = len(x)
        k = np.arange(n, dtype=float)
        d = self._d0 + self._d1 * np.sin(self._w * k)
        n0f = np.maximum(np.floor(d) - 1.0, 0.0)
        taps = lagrange_weights(d - n0f)
        n0 = n0f.astype(np.intp)
        padded = np.concatenate([np.zeros(self._size), x])
        idx = np.arange(n) + self._size - n0
        out = (
            taps[0] * padded[idx]
            + taps[1] * padded[idx - 1]
            + taps[2] * padded[idx - 2]
            + taps[3] * padded[idx - 3]
        )
        # leave the streaming state as if stepped
        self._k = n
        tail = x[-self._size :].tolist()
        for v in tail:
            self._buf[self._pos] = v
            self._pos = (self._pos + 1) % self._size
        return out


class ForceFeedback(FirstOrderSection, Effect):
    """Control-structure interaction: the specimen force compresses the oil column.

    With the hydraulic (oil-column) stiffness ``k_h = 4βA²/V`` in series with the specimen
    ``k_s, c_s``, the rod displacement ``y`` for a commanded ``x`` satisfies
    ``k_h (x - y) = k_s y + c_s ẏ``: a static loss ``y/x = k_h/(k_h + k_s)`` and, with a
    damper specimen, a lag of ``T = c_s/(k_h + k_s)`` (first-order hold; pure gain if
    ``c_s = 0``). Physical origin: a stiff specimen loads the actuator, the outer displacement
    loop sees the error only through its finite gain (Dyke et al. 1995's natural velocity
    feedback). Realistic ``actuator_stiffness`` 2e7-2e8 N/m (β ≈ 0.7-1.4 GPa with air,
    A = 30-100 cm², V = 1-5 l), ``specimen_stiffness`` 1e5-5e6 N/m, ``specimen_damping``
    0-2e5 N·s/m (dampers). In a model file, omitted specimen parameters come from
    ``[specimen]``.
    """

    kind = "force_feedback"
    PARAMS = (
        _positive(
            "actuator_stiffness",
            "N/m",
            "oil-column stiffness k_h",
            ParamRange(2e7, 2e8, log=True, note="oil column 4βA²/V"),
        ),
        Param(
            "specimen_stiffness",
            "N/m",
            "specimen stiffness k_s",
            minimum=0.0,
            typical=ParamRange(1e5, 5e6, log=True, note="specimen"),
            polish=False,
        ),
        Param(
            "specimen_damping",
            "N·s/m",
            "specimen damping c_s",
            default=0.0,
            minimum=0.0,
            typical=ParamRange(0.0, 2e5, note="0 for elastic specimens, dampers up"),
            polish=False,
        ),
    )
    CHAIN = 20
    PREFERENCE = 40
    FIT = Fitting("scalar", "actuator_stiffness", needs_specimen=True)

    @classmethod
    def fit_bounds(
        cls, x: np.ndarray, fs: float, specimen: tuple[float, float] | None
    ) -> tuple[float, float]:
        """From the specimen's stiffness (at least 1 kN/m) to 1e5 times it."""
        k_s = specimen[0] if specimen is not None else 0.0
        return max(k_s, 1e3) * 1.0, max(k_s, 1e3) * 1e5

    @classmethod
    def fit_fixed(cls, specimen: tuple[float, float] | None) -> dict[str, float]:
        """The specimen's stiffness and damping, as regressed from the record."""
        if specimen is None:
            raise InputError("force_feedback: needs the specimen's stiffness and damping")
        return {"specimen_stiffness": specimen[0], "specimen_damping": specimen[1]}

    @classmethod
    def low_frequency(cls, params: dict[str, float]) -> tuple[float, float]:
        """Lag ``c_s/(k_h + k_s)`` and static gain ``k_h/(k_h + k_s)``."""
        k_h, k_s = params["actuator_stiffness"], params["specimen_stiffness"]
        c_s = params["specimen_damping"]
        return c_s / (k_h + k_s), k_h / (k_h + k_s)

    def _setup(self) -> None:
        p = self.params
        total = p["actuator_stiffness"] + p["specimen_stiffness"]
        self.static_gain = p["actuator_stiffness"] / total
        self.time_constant = p["specimen_damping"] / total
        if self.time_constant > 0:
            b, a = first_order_coeffs(self.static_gain, self.time_constant, self.dt)
        else:
            b, a = np.array([self.static_gain, 0.0]), np.array([1.0, 0.0])
        self._set_section(b, a)


class EffectChain:
    """Effects applied in order; an empty chain is the identity."""

    def __init__(self, effects: Sequence[Effect] = ()) -> None:
        self.effects = list(effects)

    def __len__(self) -> int:
        return len(self.effects)

    def reset(self) -> None:
        for e in self.effects:
            e.reset()

    def step(self, x: float) -> float:
        for e in self.effects:
            x = e.step(x)
        return x

    def simulate(self, x: np.ndarray) -> np.ndarray:
        y = np.asarray(x, dtype=float)
        for e in self.effects:
            y = e.simulate(y)
        return y


# the catalogue (EFFECTS, declared beside Effect): by the names the model file and the
# diagnosis workflow use
EFFECTS.update(
    (cls.kind, cls)
    for cls in (
        Offset,
        Drift,
        Backlash,
        VelocityLimit,
        StrokeLimit,
        ServoLag,
        TimeVaryingDelay,
        ForceFeedback,
    )
)

#: The catalogue effects the force-controlled twin (:mod:`rths_hil.sim_backends.force`) takes:
#: kind → where it acts, ``"reference"`` (the force set-point path, N) or ``"loop"`` (the
#: piston inside the force loop, m).
FORCE_EFFECTS: dict[str, str] = {
    "offset": "reference",
    "drift": "reference",
    "servo_lag": "reference",
    "time_varying_delay": "reference",
    "stroke_limit": "loop",
    "velocity_limit": "loop",
}
#: The catalogue effects the force twin refuses, and why (the refusal's message).
FORCE_REFUSED: dict[str, str] = {
    "backlash": (
        "play in the load train, which the force loop pushes through to the set-point; its "
        "transient needs the piston and the specimen as two states, and this loop has one"
    ),
    "force_feedback": (
        "the specimen's force acting back on a displacement loop through the oil column; "
        "the force twin has the specimen in its loop already"
    ),
}
#: Units of the reference effects' parameters in the force twin (the catalogue's are m, m/s).
FORCE_UNITS: dict[str, dict[str, str]] = {"offset": {"offset": "N"}, "drift": {"rate": "N/s"}}

#: Realistic ranges of each effect's parameters (SI), from each :class:`Param`'s ``typical``:
#: the twin's documentation, the random hidden effects of the diagnosis benchmarks and tests.
#: See docs/models.md for the justification of each range.
EFFECT_RANGES: dict[str, dict[str, ParamRange]] = {
    kind: {p.name: p.typical for p in cls.PARAMS if p.typical is not None}
    for kind, cls in EFFECTS.items()
}
#: Physical order of the effects in a chain (each class's ``CHAIN``): kind → position.
EFFECT_ORDER: dict[str, int] = {
    kind: i for i, kind in enumerate(sorted(EFFECTS, key=lambda k: EFFECTS[k].CHAIN))
}


def make_effect(kind: str, dt: float, **params: float) -> Effect:
    """Build the catalogue effect ``kind`` with ``params`` (SI units) at step ``dt``."""
    if kind not in EFFECTS:
        raise InputError(f"kind: unknown effect {kind!r} (known: {', '.join(EFFECTS)})")
    return EFFECTS[kind](dt, **params)


def draw_effect_params(kind: str, rng: np.random.Generator) -> dict[str, float]:
    """Draw realistic random parameters for effect ``kind`` from :data:`EFFECT_RANGES`."""
    if kind not in EFFECT_RANGES:
        raise InputError(f"kind: unknown effect {kind!r} (known: {', '.join(EFFECTS)})")
    out = {}
    for name, r in EFFECT_RANGES[kind].items():
        if r.log and r.low > 0:
            value = float(np.exp(rng.uniform(np.log(r.low), np.log(r.high))))
        else:
            value = float(rng.uniform(r.low, r.high))
        if r.signed and rng.random() < 0.5:
            value = -value
        out[name] = value
    return out

"""Model-based feedforward compensation with optional proportional feedback.

In the manner of Phillips & Spencer ("Model-based feedforward-feedback actuator control for
real-time hybrid simulation", *Journal of Structural Engineering* 139(7), 1205–1214, 2013)
and of the sample controller of the RTHS benchmark (Silva et al. 2020), the command is the
target passed through the inverse of an identified actuator model, made proper by a low-pass,
plus a proportional correction of the tracking error.

Actuator model: ``G(s) = g·e^(−sτ)·R(s)`` with ``R(s) = 1/(T s + 1)`` (``model_time_constant``
T, ``model_gain`` g, transport delay τ = ``model_delay``, or ``delay`` while ``model_delay``
is negative (the default); the first-order servo plus delay that ``rths-hil twin calibrate``
fits), or ``R(s) = num(s)/den(s)`` from ``model_num`` and
``model_den`` (highest power of s first; ``num`` must have its zeros in the left half-plane, or
the inverse would be unstable). The feedforward is

    C(s) = a/g · R(s)⁻¹ · P(s) · L(s),     L(s) = 1/(1 + s/ω_c)^m,

``a`` the amplitude factor, ``ω_c = 2π·model_cutoff``, ``m`` the relative degree of
``R⁻¹·P`` (so ``C`` is proper), and ``P(s)`` the Taylor polynomial of order
``model_order`` of ``e^(sτ)·(1 + s/ω_c)^m``: the prediction over the transport delay that also
cancels the low-pass's own lag at low frequency (``P·L = e^(sτ) + O(s^(order+1))``). ``C`` is
discretised with the bilinear transform at the loop rate and run as second-order sections. The
feedback adds ``model_kp · (x_t[k] − x_m[k])`` of the last reply to the next command.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from ..errors import InputError
from ..keys import Key, seconds
from .base import Compensator

__all__ = ["ModelCompensator", "feedforward_tf"]


def _series_exp(tau: float, n: int) -> np.ndarray:
    """Taylor coefficients of e^(s·tau), lowest power first, up to s^n."""
    return np.array([tau**i / math.factorial(i) for i in range(n + 1)])


def _without_leading_zeros(c: Sequence[float] | np.ndarray) -> np.ndarray:
    """Polynomial coefficients ``c`` (highest power first) as floats, leading zeros dropped."""
    a = np.asarray(c, dtype=float)
    # numpy's stub for trim_zeros does not accept an ndarray (it works on one)
    return np.asarray(np.trim_zeros(a, "f"))  # type: ignore[arg-type]


def feedforward_tf(
    num: Sequence[float] | np.ndarray,
    den: Sequence[float] | np.ndarray,
    gain: float,
    delay: float,
    cutoff: float,
    order: int,
    amplitude: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The continuous feedforward ``C(s)`` (numerator, denominator; highest power first).

    ``R(s) = num/den`` (see the module docstring). Raises :class:`InputError` for a model whose
    inverse is unstable or improper inputs.
    """
    num = _without_leading_zeros(num)
    den = _without_leading_zeros(den)
    if (
        num.size == 0
        or den.size == 0
        or not (np.all(np.isfinite(num)) and np.all(np.isfinite(den)))
    ):
        raise InputError("compensation.model_num/model_den: need finite, non-zero polynomials")
    if num.size > den.size:
        raise InputError("compensation.model_num: the actuator model must be proper")
    if num.size > 1 and np.any(np.roots(num).real >= 0):
        raise InputError(
            "compensation.model_num: the model has a zero in the right half-plane; its inverse "
            "is unstable"
        )
    if not (cutoff > 0 and gain > 0 and delay >= 0 and 0 <= order <= 4):
        raise InputError("compensation: model needs cutoff > 0, gain > 0, delay ≥ 0, order 0 … 4")
    wc = 2.0 * math.pi * cutoff
    m = (den.size - num.size) + order
    # Taylor polynomial of e^(sτ)·(1 + s/ωc)^m up to s^order (lowest power first)
    lp = np.array([math.comb(m, i) / wc**i for i in range(m + 1)])
    p = np.convolve(_series_exp(delay, order), lp)[: order + 1]
    b = np.polymul(den, p[::-1]) * (amplitude / gain)
    a = np.polymul(num, np.poly1d([1.0 / wc, 1.0]) ** m if m > 0 else np.poly1d([1.0]))
    return np.asarray(b, dtype=float), np.asarray(a, dtype=float)


class ModelCompensator(Compensator):
    """Inverse-model feedforward plus proportional feedback (see the module docstring).

    Parameters
    ----------
    fs : float
        Loop rate (Hz).
    delay : float
        Transport delay τ of the model (s).
    time_constant, gain : float
        First-order model ``g/(T s + 1)`` (used when ``num``/``den`` are empty).
    num, den : sequence of float
        Rational model ``R(s)`` instead (then ``gain`` still divides the command).
    cutoff : float
        Low-pass corner (Hz), below fs/2.
    order : int
        Taylor order of the delay prediction.
    kp : float
        Proportional feedback gain on ``target − measured``.
    amplitude : float
        Amplitude factor on the feedforward.
    """

    #: the ``delay``, ``amplitude`` and ``model_*`` keys of the compensation section
    ARGUMENTS: ClassVar[Mapping[str, str]] = {
        "delay": "delay",
        "amplitude": "amplitude",
        "time_constant": "model_time_constant",
        "gain": "model_gain",
        "num": "model_num",
        "den": "model_den",
        "cutoff": "model_cutoff",
        "order": "model_order",
        "kp": "model_kp",
    }
    KEYS: ClassVar[Mapping[str, Key]] = {
        "model_delay": Key(
            "float",
            -1.0,
            unit="s",
            doc="model: transport delay τ of the actuator model; negative: compensation.delay "
            "(a rational model that holds the whole plant takes 0 while another method keeps "
            "delay)",
            hi=1.0,
        ),
        "model_time_constant": seconds(
            0.0, doc="model: servo lag T of the actuator model g·e^(−s·delay)/(T s + 1)"
        ),
        "model_gain": Key(
            "float", 1.0, doc="model: static gain g of the actuator model", lo=0, lo_open=True
        ),
        "model_num": Key(
            "array",
            [],
            doc="model: numerator of a rational actuator model (powers of s, highest first); "
            "with model_den it replaces g/(T s + 1)",
        ),
        "model_den": Key("array", [], doc="model: denominator of the rational actuator model"),
        "model_cutoff": Key(
            "float",
            60.0,
            unit="Hz",
            doc="model: corner of the low-pass that makes the inverse proper",
            lo=0,
            lo_open=True,
        ),
        "model_order": Key(
            "int", 3, doc="model: Taylor order of the delay prediction e^(s·τ)", lo=0, hi=4
        ),
        "model_kp": Key("float", 0.0, doc="model: proportional feedback gain on target − measured"),
    }

    @classmethod
    def from_config(cls, c: Mapping[str, Any], fs: float) -> ModelCompensator:
        """:attr:`ARGUMENTS` of the compensation section; the model's transport delay is
        ``model_delay`` when it is ≥ 0, else ``delay``."""
        args = cls.config_arguments(c)
        tau = c.get("model_delay", -1.0)
        if tau >= 0:
            args["delay"] = tau
        return cls(fs, **args)

    def __init__(
        self,
        fs: float,
        delay: float,
        *,
        time_constant: float = 0.0,
        gain: float = 1.0,
        num: Sequence[float] = (),
        den: Sequence[float] = (),
        cutoff: float = 60.0,
        order: int = 3,
        kp: float = 0.0,
        amplitude: float = 1.0,
    ) -> None:
        fs = float(fs)
        if not cutoff < fs / 2:
            raise InputError(
                f"compensation.model_cutoff: {cutoff:g} Hz is not below fs/2 = {fs / 2:g} Hz"
            )
        if bool(len(num)) != bool(len(den)):
            raise InputError("compensation.model_num and model_den: give both or neither")
        if not len(num):
            num, den = [1.0], ([time_constant, 1.0] if time_constant > 0 else [1.0])
        bs, as_ = feedforward_tf(num, den, gain, delay, cutoff, order, amplitude)
        from scipy.signal import bilinear, tf2sos  # loaded with the first model built

        bz, az = bilinear(bs, as_, fs)
        self.sos = [tuple(float(v) for v in row) for row in tf2sos(bz, az)]
        self.fs = fs
        self.kp = float(kp)
        self.enabled = True
        # the lead the feedforward gives at low frequency: d(phase)/dω of C at 0 (s)
        self.lead = (
            float(delay)
            + float(np.polyval(np.polyder(den), 0) / np.polyval(den, 0))
            - (float(np.polyval(np.polyder(num), 0) / np.polyval(num, 0)))
        )
        self.alpha = 1.0 + self.lead * fs
        self._z = [[0.0, 0.0] for _ in self.sos]
        self._err = 0.0
        self.dc = float(np.polyval(bs, 0) / np.polyval(as_, 0))

    def reset(self, target: float = 0.0) -> None:
        """Filters at steady state for a target held at ``target``; no error."""
        x = float(target)
        for (b0, b1, b2, _a0, a1, a2), z in zip(self.sos, self._z, strict=True):
            y = x * (b0 + b1 + b2) / (1.0 + a1 + a2)  # the section's DC output
            z[1] = b2 * x - a2 * y
            z[0] = b1 * x - a1 * y + z[1]
            x = y
        self._err = 0.0

    def step(self, target: float) -> float:
        """Feedforward of the target plus ``kp`` times the last tracking error."""
        x = target
        for (b0, b1, b2, _a0, a1, a2), z in zip(self.sos, self._z, strict=True):
            y = b0 * x + z[0]
            z[0] = b1 * x - a1 * y + z[1]
            z[1] = b2 * x - a2 * y
            x = y
        return x + self.kp * self._err

    def observe(self, target: float, command: float, measured: float) -> None:
        """Keep the tracking error ``target − measured`` for the feedback."""
        self._err = target - measured

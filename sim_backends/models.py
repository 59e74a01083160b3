"""Actuator models: what displacement a servo-hydraulic actuator achieves for a command.

Three families, all :class:`~sim_backends.base.ActuatorModel` subclasses stepped at ``dt``:

* :class:`DelayGain` — the FEI paper's block model (Fig. 4.1): a fractional transport delay followed
  by a gain (re-exported from :mod:`rths_hil.sim_backends.delay`).
* :class:`FirstOrderServo` — a first-order servo lag ``1 / (T s + 1)``; its low-frequency
  equivalent delay is ``T`` and its amplitude at frequency ``f`` is ``1/sqrt(1 + (2π f T)²)``.
* :class:`BenchmarkServo` — the servo-valve / actuator / control-structure-interaction plant of
  the RTHS benchmark problem (Silva, Gomez, Maghareh, Dyke & Spencer, "Benchmark control
  problem for real-time hybrid simulation", *Mechanical Systems and Signal Processing* 135,
  106381, 2020; nominal parameters of their Table 2, see :data:`BENCHMARK_NOMINAL`), with the
  specimen's mass, damping and stiffness as parameters.

:class:`Series` chains models (the model file's ``model`` dynamics followed by the ``delay`` and
``gain`` of the FEI paper's Fig. 4.1). Continuous models are discretised with
:func:`scipy.signal.cont2discrete` using a first-order (triangle) hold: exact for a command that
is linear between samples, with no frequency warping and no half-sample delay (a zero-order hold
would add ``dt/2`` of delay, Tustin would warp the benchmark's 67 Hz mode). The per-sample
:meth:`~sim_backends.base.ActuatorModel.step` of a state-space model is a matrix-vector product
into preallocated arrays (no allocation per step); :meth:`simulate` runs the same discrete system
as second-order sections (:func:`scipy.signal.sosfilt`) and agrees with the step path to
round-off.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import linalg, signal

from rths_hil.errors import InputError

from .base import ActuatorModel
from .delay import DelayGain

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

#: Nominal parameters of the RTHS benchmark plant, Silva et al. (2020), Table 2. The servo-valve
#: with the proportional controller is ``a1β0 / (s² + β1 s + β2)``; the actuator is
#: ``1 / (s + a3)`` with the control-structure-interaction (load pressure) feedback ``a2·s``;
#: the specimen is ``1 / (m s² + c s + k)``. Units: a1β0 in m/(V·s³)-equivalent (the plant is
#: normalised so that its DC gain is close to 1), a2 in N/m·s-equivalent, a3 in 1/s, β1 in 1/s,
#: β2 in 1/s², specimen mass in kg, damping in N·s/m, stiffness in N/m. (Table 2 also gives
#: the uncertainty of a3 (σ = 1.3), β1 (σ = 3.3), β2 (σ = 3.3e3) and the specimen stiffness
#: (σ = 5e4 N/m); values cross-checked against a public MATLAB implementation of the benchmark's
#: adaptive-compensation example.)
BENCHMARK_NOMINAL: dict[str, float] = {
    "a1b0": 2.13e13,
    "a2": 4.23e6,
    "a3": 3.3,
    "beta1": 425.0,
    "beta2": 1.0e5,
    "specimen_mass": 29.1,
    "specimen_damping": 114.6,
    "specimen_stiffness": 1.19e6,
}

#: Gain the benchmark's distributed code multiplies the plant by (``gain = 1.0261`` in
#: ``F1_input_file.m``, lines 106–129, ``G_plant = gain*feedback(Gs*G0,1,-1)``), the plant the
#: participants run; ``plant_gain = 1`` is the paper's Eq. 21. The default of
#: :class:`BenchmarkServo` and of the model file's ``benchmark`` model.
BENCHMARK_CODE_GAIN = 1.0261


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0:
        raise InputError(f"dt: must be a positive number of seconds, got {dt!r}")
    return dt


class Identity(ActuatorModel):
    """The ideal actuator: achieved displacement = command."""

    def __init__(self, dt: float) -> None:
        self.dt = _check_dt(dt)

    def reset(self) -> None:
        pass

    def step(self, command: float) -> float:
        return float(command)

    def simulate(self, command: np.ndarray) -> np.ndarray:
        return np.array(command, dtype=float)


class FirstOrderServo(ActuatorModel):
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
        self.dt = _check_dt(dt)
        t = float(time_constant)
        if not math.isfinite(t) or t <= 0:
            raise InputError(f"time_constant: must be > 0 s, got {time_constant!r}")
        self.time_constant = t
        b, a = _first_order_coeffs(1.0, t, self.dt)
        self.b = b
        self.a = a
        self._b0, self._b1 = float(b[0]), float(b[1])
        self._a1 = float(a[1])
        self._z = 0.0

    def reset(self) -> None:
        self._z = 0.0

    def step(self, command: float) -> float:
        y = self._b0 * command + self._z
        self._z = self._b1 * command - self._a1 * y
        return y

    def simulate(self, command: np.ndarray) -> np.ndarray:
        self.reset()
        return signal.lfilter(self.b, self.a, np.asarray(command, dtype=float))


def _first_order_coeffs(
    gain: float, time_constant: float, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Discrete ``(b, a)`` of ``gain / (T s + 1)`` with a first-order hold (``a[0] = 1``)."""
    num, den, _ = signal.cont2discrete(([gain], [time_constant, 1.0]), dt, method="foh")
    b = np.atleast_1d(np.squeeze(num)).astype(float)
    a = np.asarray(den, dtype=float)
    b, a = b / a[0], a / a[0]
    if len(b) < 2:
        b = np.concatenate([b, np.zeros(2 - len(b))])
    return b[:2], a[:2]


class StateSpaceModel(ActuatorModel):
    """A SISO discrete state-space model ``x[k+1] = A x[k] + B u[k]``, ``y[k] = C x[k] + D u[k]``.

    The step path computes ``[A B]·[x; u]`` into a preallocated buffer (one :func:`numpy.dot`
    with ``out=``, no allocation per step). :meth:`simulate` uses the equivalent second-order
    sections with :func:`scipy.signal.sosfilt`.

    Parameters
    ----------
    a, b, c, d : array_like
        Discrete matrices, shapes (n, n), (n, 1), (1, n), (1, 1).
    dt : float
        Step in seconds.
    """

    def __init__(self, a: Any, b: Any, c: Any, d: Any, dt: float) -> None:
        self.dt = _check_dt(dt)
        a = np.atleast_2d(np.asarray(a, dtype=float))
        n = a.shape[0]
        b = np.asarray(b, dtype=float).reshape(n, 1)
        c = np.asarray(c, dtype=float).reshape(1, n)
        d = np.asarray(d, dtype=float).reshape(1, 1)
        self.A, self.B, self.C, self.D = a, b, c, d
        self.order = n
        self._ab = np.ascontiguousarray(np.hstack([a, b]))
        self._cd = np.ascontiguousarray(np.concatenate([c[0], d[0]]))
        self._xu = np.zeros(n + 1)
        self._next = np.zeros(n)
        z, p, k = signal.ss2zpk(a, b, c, d)
        self.sos = signal.zpk2sos(z, p, k)

    def reset(self) -> None:
        self._xu[:] = 0.0

    def step(self, command: float) -> float:
        xu = self._xu
        n = self.order
        xu[n] = command
        y = float(self._cd.dot(xu))
        np.dot(self._ab, xu, out=self._next)
        xu[:n] = self._next
        return y

    def simulate(self, command: np.ndarray) -> np.ndarray:
        self.reset()
        return signal.sosfilt(self.sos, np.asarray(command, dtype=float))

    def frequency_response(self, freqs: np.ndarray) -> np.ndarray:
        """Complex response of the discrete model at ``freqs`` (Hz)."""
        _, h = signal.freqz_sos(self.sos, worN=2 * np.pi * np.asarray(freqs) * self.dt)
        return h


def benchmark_transfer_function(
    a1b0: float = BENCHMARK_NOMINAL["a1b0"],
    a2: float = BENCHMARK_NOMINAL["a2"],
    a3: float = BENCHMARK_NOMINAL["a3"],
    beta1: float = BENCHMARK_NOMINAL["beta1"],
    beta2: float = BENCHMARK_NOMINAL["beta2"],
    specimen_mass: float = BENCHMARK_NOMINAL["specimen_mass"],
    specimen_damping: float = BENCHMARK_NOMINAL["specimen_damping"],
    specimen_stiffness: float = BENCHMARK_NOMINAL["specimen_stiffness"],
    plant_gain: float = BENCHMARK_CODE_GAIN,
) -> tuple[np.ndarray, np.ndarray]:
    """Continuous transfer function (num, den) from command to achieved displacement.

    The default ``plant_gain`` is the benchmark code's :data:`BENCHMARK_CODE_GAIN` (1.0261), as
    :class:`BenchmarkServo`; ``plant_gain = 1`` is the paper's Eq. 21.

    Silva et al. (2020): with the servo-valve ``Gsv = a1β0/(s² + β1 s + β2)``, the actuator
    ``Ga = 1/(s + a3)``, the specimen ``Ge = 1/(m s² + c s + k)`` and the control-structure
    interaction ``Gcsi = a2·s``, the open loop is ``Gsv·Ga·Ge/(1 + Ga·Ge·Gcsi)`` and the
    unity-feedback closed loop is::

        Gxu(s) = a1β0 / [ (s² + β1 s + β2)·((s + a3)(m s² + c s + k) + a2 s) + a1β0 ]
    """
    servo_valve = np.array([1.0, beta1, beta2])
    actuator = np.polyadd(
        np.polymul([1.0, a3], [specimen_mass, specimen_damping, specimen_stiffness]),
        [a2, 0.0],
    )
    den = np.polyadd(np.polymul(servo_valve, actuator), [a1b0])
    return np.array([plant_gain * a1b0]), den


class BenchmarkServo(StateSpaceModel):
    """The RTHS benchmark's servo-hydraulic transfer system with control-structure interaction.

    Plant of Silva et al. (2020), "Benchmark control problem for real-time hybrid simulation",
    Mech. Syst. Signal Process. 135:106381, with the nominal parameters of their Table 2
    (:data:`BENCHMARK_NOMINAL`); see :func:`benchmark_transfer_function` for the closed loop.
    With the nominal specimen (m = 29.1 kg, c = 114.6 N·s/m, k = 1.19e6 N/m) the plant has a DC
    gain of 0.982 and an equivalent delay of about 25 ms below 2 Hz (24.9 ms, amplitude 0.974
    at 1 Hz); a stiffer specimen lowers the gain and lengthens the delay (5e6 N/m: 0.905 and
    40 ms at 1 Hz). The discrete model's frequency response is the continuous one times
    ``sinc²(f·dt)``, the first-order hold's, i.e. exact to 1e-8 relative after that factor.

    Parameters
    ----------
    dt : float
        Step in seconds.
    a1b0, a2, a3, beta1, beta2 : float
        Servo-valve / actuator parameters (Table 2 defaults).
    specimen_mass, specimen_damping, specimen_stiffness : float
        Specimen seen by the actuator (kg, N·s/m, N/m), Table 2 defaults.
    plant_gain : float
        Gain multiplying the plant: default :data:`BENCHMARK_CODE_GAIN` (1.0261, the
        benchmark's code, which the participants run); 1 is the paper's Eq. 21, whose magnitude
        is 2.5 % lower at every frequency (same phase). The DC gain and 1 Hz amplitude quoted
        above are for ``plant_gain = 1``.
    """

    PARAMS: tuple[str, ...] = (*BENCHMARK_NOMINAL, "plant_gain")

    def __init__(self, dt: float, plant_gain: float = BENCHMARK_CODE_GAIN, **params: float) -> None:
        plant_gain = float(plant_gain)
        if not math.isfinite(plant_gain) or plant_gain <= 0:
            raise InputError(f"plant_gain: must be a positive finite number, got {plant_gain!r}")
        unknown = sorted(set(params) - set(BENCHMARK_NOMINAL))
        if unknown:
            raise InputError(
                f"{unknown[0]}: unknown benchmark parameter (known: {', '.join(BENCHMARK_NOMINAL)})"
            )
        values = {**BENCHMARK_NOMINAL, **{k: float(v) for k, v in params.items()}}
        for key, value in values.items():
            if not math.isfinite(value) or value < 0 or (value == 0 and key != "specimen_damping"):
                raise InputError(f"{key}: must be a positive finite number, got {value!r}")
        self.params = {**values, "plant_gain": plant_gain}
        num, den = benchmark_transfer_function(**values, plant_gain=plant_gain)
        a, b, c, d = signal.tf2ss(num, den)
        # Balance the companion form (coefficients span 1 … 2e13) before discretising.
        a_bal, t = linalg.matrix_balance(a, permute=False)
        b_bal = np.linalg.solve(t, b)
        c_bal = c @ t
        ad, bd, cd, dd, _ = signal.cont2discrete((a_bal, b_bal, c_bal, d), _check_dt(dt), "foh")
        if np.max(np.abs(np.linalg.eigvals(ad))) >= 1.0:
            raise InputError("model: the benchmark plant with these parameters is unstable")
        self.num, self.den = num, den
        super().__init__(ad, bd, cd, dd, dt)

    def dc_gain(self) -> float:
        """Static gain of the continuous plant, ``a1β0 / (β2·a3·k + a1β0)``."""
        return float(self.num[-1] / self.den[-1])


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
        for m in self.models:
            m.reset()

    def step(self, command: float) -> float:
        x = command
        for m in self.models:
            x = m.step(x)
        return x

    def simulate(self, command: np.ndarray) -> np.ndarray:
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
    from .registry import model_class, model_entry

    dt = _check_dt(dt)
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

"""The servo-hydraulic plant of the RTHS benchmark problem, a state-space actuator model.

Silva, Gomez, Maghareh, Dyke & Spencer, "Benchmark control problem for real-time hybrid
simulation", *Mechanical Systems and Signal Processing* 135, 106381, 2020: the servo-valve,
actuator and control-structure-interaction plant with the nominal parameters of their Table 2
(:data:`BENCHMARK_NOMINAL`), discretised with a first-order hold as a :class:`StateSpaceModel`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rths_hil.errors import InputError

from .base import ActuatorModel, check_dt

__all__ = [
    "BENCHMARK_CODE_GAIN",
    "BENCHMARK_NOMINAL",
    "BenchmarkServo",
    "StateSpaceModel",
    "benchmark_transfer_function",
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
        self.dt = check_dt(dt)
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
        # where used: a twin's start-up (twin serve) does without scipy.signal's second
        from scipy import signal

        z, p, k = signal.ss2zpk(a, b, c, d)
        self.sos = signal.zpk2sos(z, p, k)

    def reset(self) -> None:
        """Return to rest (zero state, empty delay lines)."""
        self._xu[:] = 0.0

    def step(self, command: float) -> float:
        """Advance one step: the achieved displacement (m) for ``command`` (m)."""
        xu = self._xu
        n = self.order
        xu[n] = command
        y = float(self._cd.dot(xu))
        np.dot(self._ab, xu, out=self._next)
        xu[:n] = self._next
        return y

    def simulate(self, command: np.ndarray) -> np.ndarray:
        """The achieved displacement (m) for a whole command history (m), from rest."""
        from scipy import signal

        self.reset()
        return signal.sosfilt(self.sos, np.asarray(command, dtype=float))

    def frequency_response(self, freqs: np.ndarray) -> np.ndarray:
        """Complex response of the discrete model at ``freqs`` (Hz)."""
        from scipy import signal

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
        # where used: a twin's start-up (twin serve) does without scipy.signal's second
        from scipy import linalg, signal

        a, b, c, d = signal.tf2ss(num, den)
        # Balance the companion form (coefficients span 1 … 2e13) before discretising.
        a_bal, t = linalg.matrix_balance(a, permute=False)
        b_bal = np.linalg.solve(t, b)
        c_bal = c @ t
        ad, bd, cd, dd, _ = signal.cont2discrete((a_bal, b_bal, c_bal, d), check_dt(dt), "foh")
        if np.max(np.abs(np.linalg.eigvals(ad))) >= 1.0:
            raise InputError("model: the benchmark plant with these parameters is unstable")
        self.num, self.den = num, den
        super().__init__(ad, bd, cd, dd, dt)

    def dc_gain(self) -> float:
        """Static gain of the continuous plant, ``a1β0 / (β2·a3·k + a1β0)``."""
        return float(self.num[-1] / self.den[-1])

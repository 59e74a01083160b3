"""Records with hidden effects, for testing the diagnosis workflow and measuring its confusion.

A case is an RTHS-like record: the command is the displacement response of a linear SDOF structure
(the FEI paper's Section 4: 2-5 % damping, CR integration,
:func:`rths_hil.structures.sdof.simulate_sdof`)
to the strong-motion part of a bundled ground motion; the measured displacement and force come from
a twin (:class:`rths_hil.sim_backends.plant.TwinPlant`) whose actuator is the FEI paper's delay +
gain block (Fig. 4.1) followed by one or more *hidden* catalogue effects of random size drawn from
:data:`rths_hil.sim_backends.effects.EFFECT_RANGES`, a Kelvin-Voigt specimen and sensor noise. The
diagnosis receives only the record and the *base* model (the twin without the hidden effects).

Two effects are only visible when the drive reaches them, so the drive is scaled to reach them
(an unreached limit leaves no trace in the record and the right answer is then ``none``):

* ``stroke_limit``: the command's peak is 1.05-1.5 times the stop's distance from the centre,
  with the stop's half-stroke ``limit`` drawn from its range;
* ``velocity_limit``: the base actuator's peak speed is 1.1-2 times the drawn ``limit`` (with
  both, the stop is then placed where the rescaled drive reaches it).

``force_feedback`` takes the specimen of the twin (the one producing the force column) for its
``specimen_stiffness`` and ``specimen_damping``, so the record is physically consistent.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from rths_hil.errors import InputError
from rths_hil.groundmotion import bundled_path, load
from rths_hil.sim_backends.effects import EFFECT_ORDER, EFFECT_RANGES, EFFECTS, draw_effect_params
from rths_hil.sim_backends.modelfile import ActuatorSpec, EffectSpec, ModelSpec, SpecimenSpec
from rths_hil.sim_backends.plant import Sensor
from rths_hil.structures.sdof import simulate_sdof

__all__ = ["GROUND_MOTIONS", "SyntheticCase", "make_case"]

#: The bundled ground motions the cases are drawn from.
GROUND_MOTIONS: tuple[str, ...] = (
    "RSN6_IMPVALL.I_I-ELC180-hor1",
    "el_centro_1940_NS_chopra_0p02",
    "kobe_1995_nishi_akashi_NIS000",
    "chichi_1999_TCU045_N",
)


@dataclass
class SyntheticCase:
    """A generated record, the base model given to the diagnosis and the hidden truth.

    Attributes
    ----------
    time, command, measured, force : ndarray
        The record (s, m, m, N).
    truth : ndarray
        Noiseless achieved displacement of the twin (m), for scoring only.
    base : ModelSpec
        The twin without its hidden effects (what the diagnosis is told).
    twin : ModelSpec
        The full twin, hidden effects included.
    hidden : list of EffectSpec
        The hidden effects, in the twin's order.
    info : dict
        Drawn record parameters (ground motion, fn, zeta, peak, noise, …) and the RMS of each
        hidden effect's contribution to the noiseless output (``effect_rms``, m).
    """

    time: np.ndarray
    command: np.ndarray
    measured: np.ndarray
    force: np.ndarray
    truth: np.ndarray
    base: ModelSpec
    twin: ModelSpec
    hidden: list[EffectSpec]
    info: dict = field(default_factory=dict)

    @property
    def fs(self) -> float:
        """Sampling rate (Hz)."""
        return 1.0 / (self.time[1] - self.time[0])

    @property
    def names(self) -> list[str]:
        """Kinds of the hidden effects."""
        return [e.kind for e in self.hidden]


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _drive(name: str, fs: float, duration: float, fn: float, zeta: float) -> np.ndarray:
    """SDOF relative displacement (unscaled) over ``duration`` s from 2 s before the 5 % Arias
    time of ``name`` (so the record contains the strong motion and starts from rest)."""
    gm = load(bundled_path(name)).resampled(fs)
    a = np.asarray(gm.accel)
    arias = np.cumsum(a * a)
    start = max(0, int(np.searchsorted(arias, 0.05 * arias[-1])) - int(2 * fs))
    n = round(duration * fs)
    seg = a[start : start + n]
    if seg.size < n:
        seg = np.concatenate([seg, np.zeros(n - seg.size)])
    return simulate_sdof(seg, fs, fn, zeta)


def _predict(spec: ModelSpec, command: np.ndarray, dt: float) -> np.ndarray:
    plant = ModelSpec(spec.actuator, spec.specimen, Sensor(), spec.source).build(dt)
    return plant.effects.simulate(plant.actuator.simulate(command))


def make_case(
    effects: Sequence[str],
    rng: np.random.Generator | int,
    duration: float = 30.0,
    fs: float = 1024.0,
    ground_motion: str | None = None,
    params: dict[str, dict[str, float]] | None = None,
) -> SyntheticCase:
    """Draw a record with the hidden ``effects`` (catalogue kinds, in twin order).

    Parameters
    ----------
    effects : sequence of str
        Hidden effect kinds, possibly empty (a record with no hidden effect); the twin applies
        them in the physical order :data:`rths_hil.sim_backends.effects.EFFECT_ORDER`.
    rng : Generator or int
        Random generator (or seed) for every draw.
    duration : float
        Record length (s).
    fs : float
        Sampling rate (Hz).
    ground_motion : str, optional
        One of :data:`GROUND_MOTIONS`; drawn when omitted.
    params : dict, optional
        Fixed parameters per effect kind, overriding the draw (tests of a given size).

    Returns
    -------
    SyntheticCase

    Notes
    -----
    Record parameters: structure ``fn`` log-uniform 0.5-3 Hz, ``zeta`` 2-5 %, command peak
    log-uniform 5-40 mm; base actuator delay 5-30 ms and gain 0.95-1.02; specimen stiffness and
    damping from the ``force_feedback`` ranges; displacement noise log-uniform 5-20 µm rms with
    1 µm quantisation, force noise 2 N rms with 0.1 N quantisation.
    """
    rng = np.random.default_rng(rng)
    for kind in effects:
        if kind not in EFFECTS:
            raise InputError(f"unknown effect {kind!r} (known: {', '.join(EFFECTS)})")
    if len(set(effects)) != len(effects):
        raise InputError(f"each hidden effect may appear once, got {list(effects)}")
    effects = sorted(effects, key=lambda k: EFFECT_ORDER[k])
    dt = 1.0 / fs
    gm = ground_motion or GROUND_MOTIONS[int(rng.integers(len(GROUND_MOTIONS)))]
    fn = _log_uniform(rng, 0.5, 3.0)
    zeta = float(rng.uniform(0.02, 0.05))
    peak = _log_uniform(rng, 5e-3, 40e-3)
    delay = float(rng.uniform(5e-3, 30e-3))
    gain = float(rng.uniform(0.95, 1.02))
    ff = EFFECT_RANGES["force_feedback"]
    k_s = _log_uniform(rng, ff["specimen_stiffness"].low, ff["specimen_stiffness"].high)
    c_s = float(rng.uniform(ff["specimen_damping"].low, ff["specimen_damping"].high))
    noise = _log_uniform(rng, 5e-6, 20e-6)
    sensor_seed = int(rng.integers(2**31))
    drawn = {kind: draw_effect_params(kind, rng) for kind in effects}
    fixed = params or {}
    for kind in effects:
        drawn[kind].update(fixed.get(kind, {}))
    if "force_feedback" in drawn:
        drawn["force_feedback"].update(specimen_stiffness=k_s, specimen_damping=c_s)
    shape = _drive(gm, fs, duration, fn, zeta)
    shape = shape / np.max(np.abs(shape))
    if "stroke_limit" in drawn:
        p = drawn["stroke_limit"]
        reach = float(rng.uniform(1.05, 1.5)) if "limit" not in fixed.get("stroke_limit", {}) else 0
        if reach:
            # the farther stop (from zero) is reached by the factor `reach`
            peak = (p["limit"] + abs(p["center"])) * reach
    command = shape * peak
    base_act = ActuatorSpec(delay=delay, gain=gain)
    if "velocity_limit" in drawn and "limit" not in fixed.get("velocity_limit", {}):
        # scale the drive so that the base actuator's peak speed exceeds the drawn limit
        base_out = _predict(ModelSpec(base_act), command, dt)
        vmax = float(np.max(np.abs(np.diff(base_out)))) * fs
        want = drawn["velocity_limit"]["limit"] * float(rng.uniform(1.1, 2.0))
        scale = min(max(want / vmax * peak, 3e-3), 0.1) / peak
        command = command * scale
        if scale * vmax <= drawn["velocity_limit"]["limit"]:  # peak clipped at 3-100 mm
            drawn["velocity_limit"]["limit"] = scale * vmax / 1.1
        if "stroke_limit" in drawn and "limit" not in fixed.get("stroke_limit", {}):
            # both limits: the stop is placed where the rescaled drive reaches it
            p = drawn["stroke_limit"]
            p["limit"] = max(float(np.max(np.abs(command))) / reach - abs(p["center"]), 1e-3)
    hidden = [EffectSpec(kind, drawn[kind]) for kind in effects]
    specimen = SpecimenSpec(stiffness=k_s, damping=c_s, mass=0.0)
    sensor = Sensor(
        displacement_noise=noise,
        force_noise=2.0,
        displacement_resolution=1e-6,
        force_resolution=0.1,
        seed=sensor_seed,
    )
    twin = ModelSpec(
        ActuatorSpec(delay=delay, gain=gain, effects=list(hidden)), specimen, sensor, "twin"
    )
    base = ModelSpec(ActuatorSpec(delay=delay, gain=gain), specimen, sensor, "base")
    plant = twin.build(dt)
    measured, force = plant.simulate(command)
    truth = _predict(twin, command, dt)
    effect_rms = {}
    for i, e in enumerate(hidden):
        without = ModelSpec(
            ActuatorSpec(delay=delay, gain=gain, effects=hidden[:i] + hidden[i + 1 :])
        )
        effect_rms[e.kind] = float(np.sqrt(np.mean((truth - _predict(without, command, dt)) ** 2)))
    info = {
        "ground_motion": gm,
        "fn": fn,
        "zeta": zeta,
        "peak": float(np.max(np.abs(command))),
        "delay": delay,
        "gain": gain,
        "specimen_stiffness": k_s,
        "specimen_damping": c_s,
        "noise": noise,
        "effect_rms": effect_rms,
    }
    time = np.arange(len(command)) * dt
    return SyntheticCase(time, command, measured, force, truth, base, twin, hidden, info)

"""Run configuration: a TOML schema with types, units, ranges and defaults.

A configuration file names the structure and the ground motion, the loop rate and mode, the
driver and its connection, the twin model (when not on hardware), the compensation, the limits
and e-stop rules, the evaluator windows and the output directory. Every key is declared in
:data:`SCHEMA` with its type, unit, allowed range and default; the defaults together are the
**embedded default configuration**, the FEI paper's NEES project 711 setup (Section 5): SDOF moment
resisting frame of 503.4 t, fn = 0.77 Hz, 2 % damping, Bouc-Wen restoring force (Eq. 4.1–4.2),
the bundled El Centro 1940 record scaled to PGA 0.322 m/s² (the FEI paper's scaling), 1024 Hz,
CAN driver on python-can's virtual bus to an in-process twin with a 20 ms servo lag plus 5 ms
transport delay, inverse compensation on, online FEI on.

Values with units
    A float key accepts a plain number in its SI unit (``fs = 1024``, ``delay_tol = 0.015``) or
    a string with a unit (``"15ms"``, ``"50mm"``, ``"0.0328g"``, ``"2%"``); see
    :mod:`rths_hil.units`. The FEI window also accepts natural periods (``"3T"``, using
    ``structure.fn``).
Overrides
    ``--set section.key=value`` (repeatable) overrides any key. The value is read with TOML
    syntax (``--set loop.fs=2048``, ``--set compensation.enabled=false``,
    ``--set 'driver.connection={interface="virtual"}'``); text that is not valid TOML is taken as
    a string (``--set driver.name=modbus``, ``--set safety.fei_delay_tol=10ms``).
Errors
    Unknown keys, wrong types, units or ranges raise :class:`~rths_hil.errors.InputError`
    naming the file (or the ``--set`` argument) and the key path, e.g.
    ``run.toml: loop.fs: must be ≤ 100000 Hz, got 1e+06``.

``docs/config.md`` is generated from :data:`SCHEMA` by :func:`rths_hil.config.schema_markdown`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from ..errors import InputError
from ..keys import CONTROL_MODES, MASS_RANGE, STIFFNESS_RANGE, Key, seconds
from .channel_schema import CHANNEL_SCHEMA

if TYPE_CHECKING:  # pragma: no cover
    from .model import Config

__all__ = [
    "CHANNEL_KEYS",
    "CHANNEL_SECTIONS",
    "CONTROL_MODES",
    "MASS_RANGE",
    "SCHEMA",
    "STEP_KEYS",
    "STEP_PAIR",
    "STIFFNESS_RANGE",
    "Key",
    "check_compensation_units",
    "derive_steps",
    "set_compensation",
    "steps_to_time",
]


SCHEMA: dict[str, dict[str, Key]] = {
    "structure": {
        "kind": Key(
            "choice",
            "sdof",
            doc="numerical substructure: sdof (the keys below), shear_building (storeys: "
            "masses, stiffnesses), matrices (M, K, C from files) or openfresco (an OpenSees "
            "model drives the test through [openfresco])",
            choices=("sdof", "shear_building", "matrices", "openfresco"),
        ),
        "mass": Key(
            "float",
            503.4e3,
            unit="kg",
            doc="mass of the SDOF moment resisting frame (physically plausible: 1 g to 10 Mt)",
            lo=MASS_RANGE[0],
            hi=MASS_RANGE[1],
        ),
        "fn": Key(
            "float",
            0.77,
            unit="Hz",
            doc="elastic natural frequency (sets k = m·(2π·fn)²)",
            lo=0,
            lo_open=True,
        ),
        "damping": Key(
            "float",
            0.02,
            doc="inherent viscous damping ratio (c = 2ζ√(k·m))",
            lo=0,
            hi=1,
            hi_open=True,
        ),
        "bouc_wen": Key(
            "bool",
            True,
            doc="Bouc-Wen restoring force (the FEI paper's Eq. 4.1–4.2) instead of linear k·x",
        ),
        "x_y": Key(
            "float", 0.010, unit="m", doc="Bouc-Wen yield displacement x_y", lo=0, lo_open=True
        ),
        "eta": Key("float", 0.0, doc="Bouc-Wen post- to pre-yield stiffness ratio η", lo=0, hi=1),
        "beta": Key("float", 0.55, doc="Bouc-Wen shape parameter β"),
        "gamma": Key("float", 0.45, doc="Bouc-Wen shape parameter γ"),
        "q": Key("float", 2.0, doc="Bouc-Wen sharpness exponent q", lo=0, lo_open=True),
        "k_specimen": Key(
            "float",
            1.19e6,
            unit="N/m",
            doc="estimated specimen stiffness, used in the CR integration parameter "
            "(at most 1 TN/m)",
            lo=0,
            hi=STIFFNESS_RANGE[1],
        ),
        "masses": Key(
            "array",
            [],
            unit="kg",
            doc="shear_building: storey masses, first storey first (1 g to 10 Mt each)",
            lo=MASS_RANGE[0],
            hi=MASS_RANGE[1],
        ),
        "stiffnesses": Key(
            "array",
            [],
            unit="N/m",
            doc="shear_building: storey (inter-storey) stiffnesses, first storey first "
            "(1 mN/m to 1 TN/m each)",
            lo=STIFFNESS_RANGE[0],
            hi=STIFFNESS_RANGE[1],
        ),
        "rayleigh": Key(
            "array",
            [],
            doc="Rayleigh damping [α (1/s), β (s)], C = α·M + β·K; empty: ζ = damping on "
            "modes 1 and 2",
        ),
        "matrices": Key(
            "table",
            {},
            doc="matrices: {file = 'model.npz'} with arrays M, K and C (or zeta), or "
            "{M = 'M.csv', K = 'K.csv', C = 'C.csv'}; paths relative to the config file",
        ),
    },
    "ground_motion": {
        "record": Key(
            "str",
            "default",
            doc="record file (PEER .AT2 or CSV; relative to the config file) or the "
            "name of a bundled record; 'default' = El Centro 1940 (RSN 6, ELC180)",
        ),
        "pga": Key(
            "float",
            0.322,
            unit="m/s²",
            doc="scale the record to this peak ground acceleration (0 = unscaled)",
            lo=0,
        ),
        "tail": seconds(0.0, doc="seconds of zero acceleration appended (free vibration)"),
    },
    "loop": {
        "fs": Key("float", 1024.0, unit="Hz", doc="loop (integration) rate", lo=1, hi=100_000),
        "mode": Key(
            "choice",
            "paced",
            doc="paced: wall clock, one step per period; lockstep: virtual time, as fast "
            "as the actuator answers",
            choices=("paced", "lockstep"),
        ),
        "after_stall": Key(
            "choice",
            "slip",
            doc="paced: after a stall of the bridge, slip: shift the time base and go on at "
            "the normal rate (the actuator held during the stall); catch_up: run the missed "
            "steps back to back, no faster than the velocity limit allows",
            choices=("slip", "catch_up"),
        ),
        "duration": seconds(30.0, doc="simulated time to run (0 = the whole record plus tail)"),
        "spin": seconds(
            3e-4,
            doc="paced: sleep until this long before the deadline, then busy-wait (at most 0.4 "
            "period is used)",
            hi=0.01,
        ),
        "priority": Key(
            "int",
            10,
            doc="paced: SCHED_FIFO real-time priority of the loop and its threads (0 = leave the "
            "scheduler alone); needs root or CAP_SYS_NICE, else the run goes on without it",
            lo=0,
            hi=99,
        ),
        "cpu": Key(
            "int",
            -1,
            doc="paced: pin the loop (and the threads it starts) to this CPU, -1 = leave it to "
            "the scheduler; the exact-FEI worker and the live view of `run --watch` keep off it",
            lo=-1,
        ),
        "overrun_threshold": Key(
            "float",
            0.5,
            doc="paced: a step is an overrun when its command leaves later "
            "than this fraction of a period after its deadline",
            lo=0,
            lo_open=True,
        ),
        "feedback_timeout": seconds(
            0.0,
            doc="paced: wait for a reply at most this long after the send (0 = auto: until the "
            "step's work after the reply still ends before the next deadline)",
            hi=10,
        ),
        "lockstep_timeout": seconds(
            5.0,
            doc="lockstep: wait this long (wall clock) for each reply; none by then trips the "
            "watchdog",
            hi=60,
            positive=True,
        ),
        "heartbeat": seconds(0.1, doc="driver heartbeat interval (0 = never)"),
        "console": seconds(0.5, doc="live console line interval (0 = off)"),
        "confirm_hardware": Key(
            "bool",
            False,
            doc="this configuration may drive real hardware (a channel without a twin) without "
            "--confirm-hardware on the command line (for a lab's own configurations)",
        ),
    },
    "start": {
        "mode": Key(
            "choice",
            "ramp",
            doc="ramp: move each actuator from where it is to the first target along a cosine "
            "ramp; offset: run the test about where it is (commands + start position, "
            "measurements − start position)",
            choices=("ramp", "offset"),
        ),
        "ramp_time": seconds(
            2.0,
            doc="shortest start ramp (longer when start.velocity needs it)",
            positive=True,
            hi=600,
        ),
        "velocity": Key(
            "float",
            0.01,
            unit="m/s",
            doc="peak velocity of the start and end ramps (at most half safety.velocity_limit)",
            lo=0,
            lo_open=True,
        ),
        "hold": seconds(
            0.2, doc="hold at the first target after the start ramp, before step 0", hi=60
        ),
        "tolerance": Key(
            "float",
            5e-5,
            unit="m",
            doc="no start ramp when the actuator is this close to the first target",
            lo=0,
        ),
    },
    "end": {
        "rest": Key(
            "choice",
            "hold",
            doc="after a completed run or an operator stop: hold where the test ended, or ramp "
            "to end.rest_position; then the controller is disabled (a trip e-stops instead)",
            choices=("hold", "position"),
        ),
        "rest_position": Key(
            "float", 0.0, unit="m", doc="end.rest = position: where to ramp to (absolute)"
        ),
        "hold": seconds(
            0.0,
            doc="keep commanding the rest position this long before disabling (0: disable at "
            "once; a disabled controller holds where it is)",
            hi=60,
        ),
    },
    **CHANNEL_SCHEMA,
    # structure.kind = "openfresco": OpenSees (genericClient) or OpenFresco (GenericTCP) sends
    # the targets; see docs/opensees.md and rths_hil/openfresco
    "openfresco": {
        "host": Key("str", "127.0.0.1", doc="address to listen on (other than 127.0.0.1: warned)"),
        "port": Key("int", 8090, doc="TCP port to listen on (0 = any free port)", lo=0, hi=65535),
        "protocol": Key(
            "choice",
            "elem-server",
            doc="client: elem-server (OpenSees genericClient) or generic-tcp (OpenFresco "
            "expControl GenericTCP)",
            choices=("elem-server", "generic-tcp"),
        ),
        "timing": Key(
            "choice",
            "lockstep",
            doc="lockstep (virtual time), predictor-corrector (real time) or ramp-hold (slow)",
            choices=("lockstep", "predictor-corrector", "ramp-hold"),
        ),
        "transform": Key(
            "array",
            [],
            doc="element DOF weights per actuator, row-major (default for n actuators: "
            "u_{i+1} − u_i on an element of n + 1 DOFs, e.g. [-1, 1] for one actuator on a "
            "two-node element; the identity on n DOFs)",
        ),
        "stiffness": Key(
            "array",
            [],
            unit="N/m",
            doc="specimen stiffness per actuator (n values, or n×n row-major) for the "
            "stiffness replies",
        ),
        "damping": Key("array", [], unit="N·s/m", doc="damping reply per actuator (default zero)"),
        "mass": Key("array", [], unit="kg", doc="mass reply per actuator (default zero)"),
        "order": Key("int", 2, doc="predictor–corrector polynomial order (1, 2 or 3)", lo=1, hi=3),
        "wait": Key(
            "float",
            0.4,
            doc="predictor–corrector: fraction of a loop period to wait for a target due next",
            lo=0,
            hi=0.8,
        ),
        "hold_after": seconds(
            0.02, doc="predictor–corrector: hold when OpenSees is this late past a cycle's end"
        ),
        "estop_after": seconds(
            0.25,
            doc="predictor–corrector: e-stop when OpenSees is this late past a cycle's end",
            positive=True,
        ),
        "ramp_time": seconds(
            0.0,
            doc="ramp-hold: ramp per target; lockstep: ramp for trials without time "
            "(0 = 0.5 s and 0.01 s)",
        ),
        "hold_time": seconds(0.1, doc="ramp-hold: hold before the force"),
        "max_trials_per_step": Key(
            "int",
            -1,
            doc="distinct trials OpenSees may send per time step before the site stops "
            "(-1 = the timing's own: 1 for lockstep and ramp-hold, no limit for "
            "predictor-corrector; 0 = no limit)",
            lo=-1,
        ),
        "element_dt": seconds(
            0.0, doc="OpenSees' step when the trials carry no time (0 = from the time block)"
        ),
        "start_timeout": seconds(60.0, doc="wait this long for the first trial (0 = forever)"),
        "client_timeout": seconds(
            60.0, doc="lockstep, ramp-hold: wait this long for a later trial (0 = forever)"
        ),
        "connect_timeout": seconds(0.0, doc="wait this long for the client (0 = forever)"),
        "quickack": Key(
            "bool", True, doc="re-arm TCP_QUICKACK after every recv (off only to measure it)"
        ),
        "max_duration": seconds(
            3600.0,
            doc="longest test when loop.duration = 0 (the client ends it with DIE)",
            positive=True,
        ),
    },
    "commission": {
        "amplitude": Key(
            "float",
            0.001,
            unit="m",
            doc="amplitude of the ramp–hold–ramp motion of `rths-hil commission`",
            lo=0,
            lo_open=True,
        ),
        "velocity": Key(
            "float",
            0.005,
            unit="m/s",
            doc="peak velocity of the commissioning motion",
            lo=0,
            lo_open=True,
        ),
        "latency_time": seconds(
            2.0,
            doc="length of the round-trip latency measurement (actuator disabled)",
            positive=True,
        ),
        "chirp_time": Key(
            "float",
            4.0,
            unit="s",
            doc="length of the plant step's identification chirp (0.5 Hz up to min(20 Hz, fs/16)); "
            "shorter is a quicker, coarser fit",
            lo=0.5,
            hi=60.0,
        ),
        "watchdog_test": Key(
            "bool",
            True,
            doc="stop the heartbeat and check that the controller latches within its timeout",
        ),
        "watchdog_timeout": seconds(
            0.0,
            doc="the controller's heartbeat timeout (0 = twin.watchdog for a twin; without it "
            "the watchdog step is skipped on hardware)",
        ),
    },
    "output": {
        "dir": Key(
            "str",
            "runs/{timestamp}",
            doc="run directory ({timestamp} is replaced by the start time)",
        ),
        "flush_interval": seconds(
            0.05, doc="record flush interval (≤ 0.1 s)", hi=0.1, positive=True
        ),
        "plot": Key(
            "bool",
            True,
            doc="write the figures at the end (run: report.png; commission: one PNG per channel)",
        ),
    },
}

#: Sections an ``[[actuators]]`` entry may set for its channel; the top-level ones are the
#: defaults every channel inherits.
CHANNEL_SECTIONS = ("control", "driver", "twin", "compensation", "fei", "kalman", "safety")
#: Keys of an ``[[actuators]]`` entry besides its sections.
CHANNEL_KEYS = ("name", "dof", "transform")


#: Compensation keys in loop steps and the time key each stands for:
#: ``steps = offset + time·fs`` (``alpha = 1 + delay·fs``, ``rate = delay_rate·fs``).
STEP_KEYS: dict[str, tuple[str, float]] = {
    "alpha": ("delay", 1.0),
    "alpha_min": ("delay_min", 1.0),
    "alpha_max": ("delay_max", 1.0),
    "rate": ("delay_rate", 0.0),
}
#: Every step key and time key → its step key.
STEP_PAIR = {**{s: s for s in STEP_KEYS}, **{t: s for s, (t, _) in STEP_KEYS.items()}}


def steps_to_time(sec: dict[str, Any], given: Mapping[str, Any], fs: float, where: str) -> None:
    """Set the time keys of ``sec`` from the step keys ``given`` sets, read at ``fs``.

    ``given`` is a compensation table as one source wrote it (a file's, an ``[[actuators]]``
    entry's). A step key and its time key both given must agree.
    """
    for sk, (tk, off) in STEP_KEYS.items():
        if sk not in given:
            continue
        t = (given[sk] - off) / fs
        if tk in given and not math.isclose(given[tk], t, rel_tol=1e-9, abs_tol=1e-12):
            raise InputError(
                f"{where}: compensation.{sk} = {given[sk]:g} and compensation.{tk} = "
                f"{given[tk]:g} disagree at loop.fs = {fs:g} Hz ({sk} = {off:g} + {tk}·fs): "
                "give one of them"
            )
        sec[tk] = t


def derive_steps(sec: dict[str, Any], fs: float) -> None:
    """Set every step key of a compensation section from its time key at ``fs``."""
    for sk, (tk, off) in STEP_KEYS.items():
        sec[sk] = off + sec[tk] * fs


def set_compensation(sec: dict[str, Any], key: str, value: float, fs: float) -> None:
    """Set a compensation key in a resolved section and keep its step/time partner in step.

    ``set_compensation(cfg["compensation"], "alpha", 15, 1024)`` also sets ``delay`` to
    ``14/1024`` s; the compensators read the time keys (``delay``, ``delay_min``, …).
    """
    sec[key] = float(value)
    sk = STEP_PAIR.get(key)
    if sk is None:
        return
    tk, off = STEP_KEYS[sk]
    if key == sk:
        sec[tk] = (float(value) - off) / fs
    else:
        sec[sk] = off + float(value) * fs


def check_compensation_units(cfg: Config) -> None:
    """Raise if a step key and its time key of ``cfg``'s top-level compensation disagree.

    A resolved configuration keeps both consistent at ``loop.fs``; code that edits one of them
    must use :func:`set_compensation`.
    """
    sec, fs = cfg["compensation"], cfg["loop"]["fs"]
    for sk, (tk, off) in STEP_KEYS.items():
        if sk in sec and tk in sec:
            want = off + sec[tk] * fs
            if not math.isclose(sec[sk], want, rel_tol=1e-9, abs_tol=1e-9):
                raise InputError(
                    f"{cfg.source}: compensation.{sk} = {sec[sk]:g} disagrees with "
                    f"compensation.{tk} = {sec[tk]:g} at loop.fs = {fs:g} Hz ({sk} = {off:g} + "
                    f"{tk}·fs); set them with rths_hil.config.set_compensation"
                )

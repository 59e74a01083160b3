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

``docs/config.md`` is generated from :data:`SCHEMA` by :func:`schema_markdown`.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import Any

from .errors import InputError
from .formats import read_toml
from .formats import toml_value as _toml_value
from .units import (
    parse_accel,
    parse_force,
    parse_fraction,
    parse_length,
    parse_time,
    parse_velocity,
    parse_window,
)

__all__ = [
    "CHANNEL_SECTIONS",
    "SCHEMA",
    "STEP_KEYS",
    "ChannelConfig",
    "Config",
    "Key",
    "check_compensation_units",
    "default_config",
    "load_config",
    "parse_override",
    "schema_markdown",
    "set_compensation",
    "to_toml",
]


@dataclass(frozen=True)
class Key:
    """One configuration key.

    Attributes
    ----------
    kind : str
        ``float`` (a quantity in ``unit``), ``int``, ``bool``, ``str``, ``choice``, ``window``
        (seconds or natural periods), ``array`` (a list of quantities in ``unit``) or
        ``table`` (free-form, checked by its consumer).
    default : Any
        Default value (already in SI units).
    unit : str
        SI unit of the value (``s``, ``m``, ``Hz``, ``N``, ``kg``, ``N/m``, ``m/s``, ``m/s²``,
        ``1/s``, ``-``, ``steps``, ``windows``).
    doc : str
        One-line description.
    lo, hi : float or None
        Allowed range; ``lo_open``/``hi_open`` make the bound exclusive.
    choices : tuple of str
        Allowed values of a ``choice`` key.
    """

    kind: str
    default: Any
    _: KW_ONLY
    unit: str = "-"
    doc: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()


#: The schema: section → key → :class:`Key`. The defaults form the embedded NEES-711 setup.
#: Physically plausible masses (kg) of a numerical substructure: 1 g (a bench model's storey)
#: to 10 Mt (ten times a 100-storey tower's floor). Beyond them the structure's matrices are
#: numerically singular (1e-300 kg) or its response overflows: refused with the key and value.
MASS_RANGE = (1e-3, 1e10)
#: Physically plausible storey stiffnesses (N/m): 1 mN/m to 1 TN/m (a stiff concrete core
#: storey is of order 1e10 N/m).
STIFFNESS_RANGE = (1e-3, 1e12)

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
            unit="-",
            doc="inherent viscous damping ratio (c = 2ζ√(k·m))",
            lo=0,
            hi=1,
            hi_open=True,
        ),
        "bouc_wen": Key(
            "bool",
            True,
            unit="-",
            doc="Bouc-Wen restoring force (the FEI paper's Eq. 4.1–4.2) instead of linear k·x",
        ),
        "x_y": Key(
            "float", 0.010, unit="m", doc="Bouc-Wen yield displacement x_y", lo=0, lo_open=True
        ),
        "eta": Key(
            "float", 0.0, unit="-", doc="Bouc-Wen post- to pre-yield stiffness ratio η", lo=0, hi=1
        ),
        "beta": Key("float", 0.55, unit="-", doc="Bouc-Wen shape parameter β"),
        "gamma": Key("float", 0.45, unit="-", doc="Bouc-Wen shape parameter γ"),
        "q": Key("float", 2.0, unit="-", doc="Bouc-Wen sharpness exponent q", lo=0, lo_open=True),
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
            unit="-",
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
            unit="-",
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
        "tail": Key(
            "float",
            0.0,
            unit="s",
            doc="seconds of zero acceleration appended (free vibration)",
            lo=0,
        ),
    },
    "loop": {
        "fs": Key("float", 1024.0, unit="Hz", doc="loop (integration) rate", lo=1, hi=100_000),
        "mode": Key(
            "choice",
            "paced",
            unit="-",
            doc="paced: wall clock, one step per period; lockstep: virtual time, as fast "
            "as the actuator answers",
            choices=("paced", "lockstep"),
        ),
        "after_stall": Key(
            "choice",
            "slip",
            unit="-",
            doc="paced: after a stall of the bridge, slip: shift the time base and go on at "
            "the normal rate (the actuator held during the stall); catch_up: run the missed "
            "steps back to back, no faster than the velocity limit allows",
            choices=("slip", "catch_up"),
        ),
        "duration": Key(
            "float",
            30.0,
            unit="s",
            doc="simulated time to run (0 = the whole record plus tail)",
            lo=0,
        ),
        "spin": Key(
            "float",
            3e-4,
            unit="s",
            doc="paced: sleep until this long before the deadline, then busy-wait (at most 0.4 "
            "period is used)",
            lo=0,
            hi=0.01,
        ),
        "priority": Key(
            "int",
            10,
            unit="-",
            doc="paced: SCHED_FIFO real-time priority of the loop and its threads (0 = leave the "
            "scheduler alone); needs root or CAP_SYS_NICE, else the run goes on without it",
            lo=0,
            hi=99,
        ),
        "cpu": Key(
            "int",
            -1,
            unit="-",
            doc="paced: pin the loop (and the threads it starts) to this CPU, -1 = leave it to "
            "the scheduler; the exact-FEI worker and the live view of `run --watch` keep off it",
            lo=-1,
        ),
        "overrun_threshold": Key(
            "float",
            0.5,
            unit="-",
            doc="paced: a step is an overrun when its command leaves later "
            "than this fraction of a period after its deadline",
            lo=0,
            lo_open=True,
        ),
        "feedback_timeout": Key(
            "float",
            0.0,
            unit="s",
            doc="paced: wait for a reply at most this long (0 = auto: 0.8 period)",
            lo=0,
            hi=10,
        ),
        "lockstep_timeout": Key(
            "float",
            5.0,
            unit="s",
            doc="lockstep: wait this long (wall clock) for each reply; none by then trips the "
            "watchdog",
            lo=0,
            hi=60,
            lo_open=True,
        ),
        "heartbeat": Key("float", 0.1, unit="s", doc="driver heartbeat interval (0 = never)", lo=0),
        "console": Key("float", 0.5, unit="s", doc="live console line interval (0 = off)", lo=0),
        "confirm_hardware": Key(
            "bool",
            False,
            unit="-",
            doc="this configuration may drive real hardware (a channel without a twin) without "
            "--confirm-hardware on the command line (for a lab's own configurations)",
        ),
    },
    "start": {
        "mode": Key(
            "choice",
            "ramp",
            unit="-",
            doc="ramp: move each actuator from where it is to the first target along a cosine "
            "ramp; offset: run the test about where it is (commands + start position, "
            "measurements − start position)",
            choices=("ramp", "offset"),
        ),
        "ramp_time": Key(
            "float",
            2.0,
            unit="s",
            doc="shortest start ramp (longer when start.velocity needs it)",
            lo=0,
            lo_open=True,
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
        "hold": Key(
            "float",
            0.2,
            unit="s",
            doc="hold at the first target after the start ramp, before step 0",
            lo=0,
            hi=60,
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
            unit="-",
            doc="after a completed run or an operator stop: hold where the test ended, or ramp "
            "to end.rest_position; then the controller is disabled (a trip e-stops instead)",
            choices=("hold", "position"),
        ),
        "rest_position": Key(
            "float", 0.0, unit="m", doc="end.rest = position: where to ramp to (absolute)"
        ),
        "hold": Key(
            "float",
            0.0,
            unit="s",
            doc="keep commanding the rest position this long before disabling (0: disable at "
            "once; a disabled controller holds where it is)",
            lo=0,
            hi=60,
        ),
    },
    "driver": {
        "name": Key(
            "str",
            "can",
            unit="-",
            doc="driver name in the registry (can, modbus, serial, canopen, or a lab's entry "
            "point)",
        ),
        "connection": Key(
            "table",
            {},
            unit="-",
            doc="driver connection settings (e.g. interface/channel for CAN, "
            "host/port for Modbus, url for serial, eds/node_id/profile for CANopen: "
            "docs/canopen.md); with a twin they go to the twin, which hands the driver its "
            "endpoint",
        ),
        "profile": Key(
            "str",
            "rths-hil",
            unit="-",
            doc="controller profile: 'rths-hil' (the driver's own protocol) or a profile file "
            "(TOML: the lab's register map or DBC, docs/profiles.md); the twin speaks it too",
        ),
        "stepped": Key(
            "bool",
            False,
            unit="-",
            doc="the controller advances one step per command (virtual time), so a lockstep "
            "run against it without a twin is allowed",
        ),
    },
    "twin": {
        "enabled": Key(
            "bool",
            True,
            unit="-",
            doc="run an in-process virtual twin (false: real controller at the connection)",
        ),
        "inline": Key(
            "bool",
            True,
            unit="-",
            doc="serve a twin on python-can's in-process virtual bus from the loop thread "
            "(same frames and controller, no thread hand-off); false: in its own thread",
        ),
        "model": Key(
            "str",
            "",
            unit="-",
            doc="twin model file (TOML, [actuator] ...); empty: the tables below",
        ),
        "actuator": Key(
            "table",
            {"model": "first_order", "time_constant": 0.020, "delay": 0.005, "gain": 1.0},
            unit="-",
            doc="actuator model as in a model file's [actuator] table",
        ),
        "specimen": Key(
            "table",
            {},
            unit="-",
            doc="specimen model as in a model file's [specimen] table (empty: the model "
            "file default)",
        ),
        "sensor": Key(
            "table",
            {"displacement_noise": 2e-6, "force_noise": 5.0, "seed": 0},
            unit="-",
            doc="sensor noise and quantisation as in a model file's [sensor] table",
        ),
        "watchdog": Key(
            "float",
            0.5,
            unit="s",
            doc="paced: the in-process twin's controller-side watchdog: no command or heartbeat "
            "for this long while enabled → it holds and latches its e-stop (0 = off; off in "
            "lockstep)",
            lo=0,
        ),
        "faults": Key(
            "str",
            "",
            unit="-",
            doc="fault plan for tests and dry runs, e.g. 'stuck_from=3000' "
            "(rths_hil.sim_backends.faults)",
        ),
        "initial_position": Key(
            "float",
            0.0,
            unit="m",
            doc="where the twin's actuator sits at rest (an actuator left off centre)",
        ),
    },
    "compensation": {
        "enabled": Key("bool", True, unit="-", doc="actuator delay compensation on"),
        "method": Key(
            "str",
            "inverse",
            unit="-",
            doc="compensator: inverse, polynomial, ats, model or a lab's own registered under "
            "the entry-point group rths_hil.compensators (docs/compensation.md)",
        ),
        "delay": Key(
            "float",
            0.025,
            unit="s",
            doc="delay to compensate (inverse: α = 1 + delay·fs; polynomial: extrapolation "
            "horizon; ats: initial a1; model: the model's transport delay)",
            lo=0,
        ),
        "alpha": Key(
            "float",
            26.6,
            unit="steps",
            doc="inverse compensation α = 1 + delay·fs, another way to give delay: a file's α "
            "is read at that file's loop.fs, a --set α at the final loop.fs (26.6 = 25 ms at "
            "1024 Hz)",
            lo=1,
        ),
        "amplitude": Key(
            "float", 1.0, unit="-", doc="amplitude factor on the command", lo=0, lo_open=True
        ),
        "adaptive": Key(
            "bool", False, unit="-", doc="inverse: adapt α online from the online FEI delay"
        ),
        "time_constant": Key(
            "float",
            6.0,
            unit="s",
            doc="adaptive: time constant of the α update",
            lo=0,
            lo_open=True,
        ),
        "delay_rate": Key(
            "float",
            0.0048828125,
            unit="s/s",
            doc="adaptive: maximum rate of change of the compensated delay (5 steps/s at 1024 Hz)",
            lo=0,
            lo_open=True,
        ),
        "rate": Key(
            "float",
            5.0,
            unit="1/s",
            doc="adaptive: maximum |dα/dt|, another way to give delay_rate (rate = delay_rate·fs)",
            lo=0,
            lo_open=True,
        ),
        "delay_min": Key("float", 0.0, unit="s", doc="adaptive: lower bound of delay", lo=0),
        "delay_max": Key(
            "float", 0.0966796875, unit="s", doc="adaptive: upper bound of delay", lo=0
        ),
        "alpha_min": Key(
            "float", 1.0, unit="steps", doc="adaptive: lower bound of α (1 + delay_min·fs)", lo=1
        ),
        "alpha_max": Key(
            "float", 100.0, unit="steps", doc="adaptive: upper bound of α (1 + delay_max·fs)", lo=1
        ),
        "order": Key(
            "int", 3, unit="-", doc="polynomial: order n of the extrapolation (1 … 4)", lo=1, hi=4
        ),
        "ats_window": Key(
            "float",
            1.0,
            unit="s",
            doc="ats: length of the moving least-squares window",
            lo=0,
            lo_open=True,
        ),
        "ats_interval": Key(
            "float",
            0.015625,
            unit="s",
            doc="ats: time between window samples and coefficient updates (16 steps at 1024 Hz)",
            lo=0,
            lo_open=True,
        ),
        "ats_cutoff": Key(
            "float",
            20.0,
            unit="Hz",
            doc="ats: cut-off of the 6th-order Butterworth on command and measured",
            lo=0,
            lo_open=True,
        ),
        "ats_threshold": Key(
            "float",
            0.000254,
            unit="m",
            doc="ats: coefficients adapt only while the window's RMS measured displacement "
            "exceeds this",
            lo=0,
        ),
        "ats_min": Key(
            "array", [0.7, 0.0, 0.0], unit="-", doc="ats: lower bounds of a0 (-), a1 (s), a2 (s²)"
        ),
        "ats_max": Key(
            "array",
            [1.3, 0.08, 0.0032],
            unit="-",
            doc="ats: upper bounds of a0 (-), a1 (s), a2 (s²)",
        ),
        "ats_rate": Key(
            "array",
            [2.0, 0.05, 0.001],
            unit="-",
            doc="ats: maximum rate of change of a0 (1/s), a1 (s/s), a2 (s²/s)",
        ),
        "model_time_constant": Key(
            "float",
            0.0,
            unit="s",
            doc="model: servo lag T of the actuator model g·e^(−s·delay)/(T s + 1)",
            lo=0,
        ),
        "model_gain": Key(
            "float",
            1.0,
            unit="-",
            doc="model: static gain g of the actuator model",
            lo=0,
            lo_open=True,
        ),
        "model_num": Key(
            "array",
            [],
            unit="-",
            doc="model: numerator of a rational actuator model (powers of s, highest first); "
            "with model_den it replaces g/(T s + 1)",
        ),
        "model_den": Key(
            "array", [], unit="-", doc="model: denominator of the rational actuator model"
        ),
        "model_cutoff": Key(
            "float",
            60.0,
            unit="Hz",
            doc="model: corner of the low-pass that makes the inverse proper",
            lo=0,
            lo_open=True,
        ),
        "model_order": Key(
            "int",
            3,
            unit="-",
            doc="model: Taylor order of the delay prediction e^(s·τ)",
            lo=0,
            hi=4,
        ),
        "model_kp": Key(
            "float", 0.0, unit="-", doc="model: proportional feedback gain on target − measured"
        ),
        "options": Key(
            "table", {}, unit="-", doc="a lab compensator's own keys (passed to its from_config)"
        ),
    },
    "fei": {
        "enabled": Key("bool", True, unit="-", doc="online FEI (streaming every sample)"),
        "pair": Key(
            "choice",
            "target",
            unit="-",
            doc="evaluated pair: measured vs target (as in the FEI paper) or measured vs command",
            choices=("target", "command"),
        ),
        "window": Key(
            "window",
            "3T",
            unit="s",
            doc="window length t_w in s, or in natural periods ('3T' = 3/fn)",
            lo=0,
            lo_open=True,
        ),
        "exact_hop": Key(
            "int",
            256,
            unit="steps",
            doc="exact FEI cross-check every this many samples (0 = off)",
            lo=0,
        ),
    },
    "kalman": {
        "enabled": Key("bool", True, unit="-", doc="Kalman gain/delay estimator beside the FEI"),
        "pair": Key(
            "choice",
            "command",
            unit="-",
            doc="input of the estimator: command (the actuator's own delay) or target",
            choices=("target", "command"),
        ),
        "every": Key("int", 1, unit="steps", doc="run the estimator every this many steps", lo=1),
        "options": Key(
            "table", {}, unit="-", doc="estimator keyword arguments (rths_hil.estimation)"
        ),
    },
    "safety": {
        "displacement_limit": Key(
            "float", 0.050, unit="m", doc="|target|, |command|, |measured| limit (0 = off)", lo=0
        ),
        "velocity_limit": Key(
            "float",
            0.5,
            unit="m/s",
            doc="|structure velocity| and |measured velocity| limit (0 = off)",
            lo=0,
        ),
        "force_limit": Key("float", 100e3, unit="N", doc="|measured force| limit (0 = off)", lo=0),
        "fei_amplitude_tol": Key(
            "float", 0.2, unit="-", doc="FEI rule: tolerance on |A − 1| (0 = off)", lo=0
        ),
        "fei_delay_tol": Key(
            "float", 0.015, unit="s", doc="FEI rule: tolerance on |d| (0 = off)", lo=0
        ),
        "fei_consecutive": Key(
            "int",
            256,
            unit="windows",
            doc="FEI rule: consecutive valid windows out of tolerance that trip",
            lo=1,
        ),
        "kf_gain_min": Key("float", 0.5, unit="-", doc="Kalman rule: lowest gain estimate"),
        "kf_gain_max": Key("float", 1.5, unit="-", doc="Kalman rule: highest gain estimate"),
        "kf_delay_max": Key(
            "float", 0.1, unit="s", doc="Kalman rule: |delay estimate| limit (0 = off)", lo=0
        ),
        "watchdog_missed": Key(
            "int",
            0,
            unit="steps",
            doc="consecutive missed replies that also trip (0 = none beyond watchdog_timeout; "
            "lockstep counts watchdog_timeout in steps of virtual time)",
            lo=0,
        ),
        "watchdog_timeout": Key(
            "float",
            0.02,
            unit="s",
            doc="controller silence that trips: time without a good reply while the bridge "
            "ran (paced: wall clock, stalls of the bridge not counted; lockstep: virtual time)",
            lo=0,
            lo_open=True,
        ),
        "max_stall": Key(
            "float",
            0.2,
            unit="s",
            doc="paced: a stall of the bridge itself (this process or computer not running "
            "the loop) longer than this trips; shorter ones are events and the test goes on",
            lo=0,
            lo_open=True,
        ),
        "max_sequence_gaps": Key(
            "int", 0, unit="-", doc="sequence gaps tolerated before a trip", lo=0
        ),
        "controller_status": Key(
            "bool",
            True,
            unit="-",
            doc="trip on the controller's alarm bits (e-stop, fault, watchdog)",
        ),
        "max_overruns": Key(
            "int", 100, unit="steps", doc="consecutive paced overruns that trip", lo=1
        ),
        "stuck_steps": Key(
            "int",
            50,
            unit="steps",
            doc="identical measured values while the command moves that trip (0 = off)",
            lo=0,
        ),
        "stuck_motion": Key(
            "float",
            1e-4,
            unit="m",
            doc="stuck rule: command travel needed over those steps",
            lo=0,
            lo_open=True,
        ),
        "warmup": Key(
            "float", 0.0, unit="s", doc="FEI and Kalman rules start after this loop time", lo=0
        ),
    },
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
        "hold_after": Key(
            "float",
            0.02,
            unit="s",
            doc="predictor–corrector: hold when OpenSees is this late past a cycle's end",
            lo=0,
        ),
        "estop_after": Key(
            "float",
            0.25,
            unit="s",
            doc="predictor–corrector: e-stop when OpenSees is this late past a cycle's end",
            lo=0,
            lo_open=True,
        ),
        "ramp_time": Key(
            "float",
            0.0,
            unit="s",
            doc="ramp-hold: ramp per target; lockstep: ramp for trials without time "
            "(0 = 0.5 s and 0.01 s)",
            lo=0,
        ),
        "hold_time": Key("float", 0.1, unit="s", doc="ramp-hold: hold before the force", lo=0),
        "max_trials_per_step": Key(
            "int",
            -1,
            unit="-",
            doc="distinct trials OpenSees may send per time step before the site stops "
            "(-1 = the timing's own: 1 for lockstep and ramp-hold, no limit for "
            "predictor-corrector; 0 = no limit)",
            lo=-1,
        ),
        "element_dt": Key(
            "float",
            0.0,
            unit="s",
            doc="OpenSees' step when the trials carry no time (0 = from the time block)",
            lo=0,
        ),
        "start_timeout": Key(
            "float", 60.0, unit="s", doc="wait this long for the first trial (0 = forever)", lo=0
        ),
        "client_timeout": Key(
            "float",
            60.0,
            unit="s",
            doc="lockstep, ramp-hold: wait this long for a later trial (0 = forever)",
            lo=0,
        ),
        "connect_timeout": Key(
            "float", 0.0, unit="s", doc="wait this long for the client (0 = forever)", lo=0
        ),
        "quickack": Key(
            "bool", True, doc="re-arm TCP_QUICKACK after every recv (off only to measure it)"
        ),
        "max_duration": Key(
            "float",
            3600.0,
            unit="s",
            doc="longest test when loop.duration = 0 (the client ends it with DIE)",
            lo=0,
            lo_open=True,
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
        "latency_time": Key(
            "float",
            2.0,
            unit="s",
            doc="length of the round-trip latency measurement (actuator disabled)",
            lo=0,
            lo_open=True,
        ),
        "watchdog_test": Key(
            "bool",
            True,
            unit="-",
            doc="stop the heartbeat and check that the controller latches within its timeout",
        ),
        "watchdog_timeout": Key(
            "float",
            0.0,
            unit="s",
            doc="the controller's heartbeat timeout (0 = twin.watchdog for a twin; without it "
            "the watchdog step is skipped on hardware)",
            lo=0,
        ),
    },
    "output": {
        "dir": Key(
            "str",
            "runs/{timestamp}",
            unit="-",
            doc="run directory ({timestamp} is replaced by the start time)",
        ),
        "flush_interval": Key(
            "float",
            0.05,
            unit="s",
            doc="record flush interval (≤ 0.1 s)",
            lo=0,
            hi=0.1,
            lo_open=True,
        ),
        "plot": Key("bool", True, unit="-", doc="write report.png at the end"),
    },
}

_QUANTITY_UNITS = {"kg", "N", "N/m", "m/s", "1/s", "Hz", "s/s"}
_NUM_RE = re.compile(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S*)\s*")
_PREFIX = {"": 1.0, "k": 1e3, "M": 1e6}


def _describe(v: Any) -> str:
    if isinstance(v, str):
        if len(v) > 60:  # a message stays one readable line
            return f"{v[:40]!r}… ({len(v)} characters)"
        return repr(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, list):
        return "an array"
    return repr(v)


def _quantity(value: Any, unit: str, path: str) -> float:
    """Read a float in ``unit`` from a number or a string with a unit."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise InputError(f"{path}: expected a number in {unit}, got {_describe(value)}")
    if isinstance(value, int | float):
        return float(value)
    try:
        if unit == "s":
            return parse_time(value, path)
        if unit == "m":
            return parse_length(value, path)
        if unit == "N":
            return parse_force(value, path)
        if unit == "m/s":
            return parse_velocity(value, path)
        if unit == "m/s²":
            return parse_accel(value, path)
        if unit == "-":
            return parse_fraction(value, path)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    m = _NUM_RE.fullmatch(value)
    if m:
        num, u = float(m.group(1)), m.group(2)
        if u in ("", unit):
            return num
        for p, f in _PREFIX.items():
            if p and u == p + unit:
                return num * f
    raise InputError(f"{path}: cannot read {value!r} as a quantity in {unit}")


def _check_range(key: Key, v: float, path: str) -> None:
    if not math.isfinite(v):
        raise InputError(f"{path}: must be a finite number, got {v!r}")
    unit = "" if key.unit in ("-", "steps", "windows") else f" {key.unit}"
    if key.lo is not None and (v < key.lo or (key.lo_open and v == key.lo)):
        op = ">" if key.lo_open else "≥"
        raise InputError(f"{path}: must be {op} {key.lo:g}{unit}, got {v:g}")
    if key.hi is not None and (v > key.hi or (key.hi_open and v == key.hi)):
        op = "<" if key.hi_open else "≤"
        raise InputError(f"{path}: must be {op} {key.hi:g}{unit}, got {v:g}")


def _coerce(key: Key, value: Any, path: str) -> Any:
    kind = key.kind
    if kind == "float":
        v = _quantity(value, key.unit, path)
        _check_range(key, v, path)
        return v
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{path}: expected an integer, got {_describe(value)}")
        _check_range(key, value, path)
        return int(value)
    if kind == "bool":
        if not isinstance(value, bool):
            raise InputError(f"{path}: expected true or false, got {_describe(value)}")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise InputError(f"{path}: expected a string, got {_describe(value)}")
        return value
    if kind == "choice":
        if not isinstance(value, str) or value not in key.choices:
            raise InputError(
                f"{path}: must be one of {', '.join(key.choices)}, got {_describe(value)}"
            )
        return value
    if kind == "window":
        if isinstance(value, str) and value.strip().endswith("T"):
            try:
                parse_window(value, 1.0)  # syntax check; resolved with structure.fn later
            except InputError as exc:
                raise InputError(f"{path}: {exc}") from None
            return value.strip()
        v = _quantity(value, "s", path)
        _check_range(key, v, path)
        return v
    if kind == "array":
        if not isinstance(value, list):
            raise InputError(f"{path}: expected an array of numbers, got {_describe(value)}")
        out = []
        for i, item in enumerate(value):
            v = _quantity(item, key.unit, f"{path}[{i}]")
            _check_range(key, v, f"{path}[{i}]")
            out.append(v)
        return out
    if kind == "table":
        if not isinstance(value, dict):
            raise InputError(f"{path}: expected a table, got {_describe(value)}")
        return copy.deepcopy(value)
    raise AssertionError(kind)  # pragma: no cover


def _unknown(path: str, name: str, known: Iterable[str]) -> InputError:
    known = list(known)
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.5)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return InputError(f"{path}: unknown key{hint}; known keys: {', '.join(known)}")


class Config(dict):
    """A resolved configuration: ``cfg["loop"]["fs"]``, all values in SI units.

    Attributes
    ----------
    source : str
        Where it came from (a file path or ``<embedded default>``).
    base_dir : Path
        Directory relative paths in the configuration are resolved against.
    """

    source: str = "<embedded default>"
    base_dir: Path = Path(".")

    @property
    def window_s(self) -> float:
        """The FEI window in seconds (natural periods resolved with ``structure.fn``)."""
        w = self["fei"]["window"]
        return parse_window(w, self["structure"]["fn"]) if isinstance(w, str) else float(w)

    def resolve_path(self, text: str) -> Path:
        """A path from the configuration, relative to the config file's directory."""
        p = Path(text).expanduser()
        return p if p.is_absolute() else self.base_dir / p

    def as_dict(self) -> dict:
        """A plain nested dict (JSON-ready)."""
        return copy.deepcopy(dict(self))

    def channels(self) -> list[ChannelConfig]:
        """The test's channels, each with its sections resolved (see :func:`resolve_channel`).

        No ``[[actuators]]`` entry: one unnamed channel on DOF 1 with the top-level sections
        (the single-actuator test).
        """
        entries = self.get("actuators") or [{"name": ""}]
        return [resolve_channel(self, e) for e in entries]


@dataclass
class ChannelConfig:
    """One channel (``[[actuators]]`` entry) with its sections resolved.

    Attributes
    ----------
    name : str
        Channel name (``""`` for the implicit single channel).
    dof : int or None
        1-based degree of freedom the actuator acts on (``None`` when ``transform`` is given).
    transform : list of float or None
        Row of the transformation matrix: actuator displacement = T·u, force returned as Tᵀ·f.
    config : Config
        A full configuration whose channel sections (:data:`CHANNEL_SECTIONS`) are this
        channel's: the top-level values overridden by the channel's own.
    """

    name: str
    dof: int | None
    transform: list[float] | None
    config: Config


#: Sections an ``[[actuators]]`` entry may set for its channel; the top-level ones are the
#: defaults every channel inherits.
CHANNEL_SECTIONS = ("driver", "twin", "compensation", "fei", "kalman", "safety")
_CHANNEL_KEYS = ("name", "dof", "transform")
_NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}\Z")


#: Compensation keys in loop steps and the time key each stands for:
#: ``steps = offset + time·fs`` (``alpha = 1 + delay·fs``, ``rate = delay_rate·fs``).
STEP_KEYS: dict[str, tuple[str, float]] = {
    "alpha": ("delay", 1.0),
    "alpha_min": ("delay_min", 1.0),
    "alpha_max": ("delay_max", 1.0),
    "rate": ("delay_rate", 0.0),
}
_PAIR = {**{s: s for s in STEP_KEYS}, **{t: s for s, (t, _) in STEP_KEYS.items()}}


def _steps_to_time(sec: dict[str, Any], given: Mapping[str, Any], fs: float, where: str) -> None:
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


def _derive_steps(sec: dict[str, Any], fs: float) -> None:
    """Set every step key of a compensation section from its time key at ``fs``."""
    for sk, (tk, off) in STEP_KEYS.items():
        sec[sk] = off + sec[tk] * fs


def set_compensation(sec: dict[str, Any], key: str, value: float, fs: float) -> None:
    """Set a compensation key in a resolved section and keep its step/time partner in step.

    ``set_compensation(cfg["compensation"], "alpha", 15, 1024)`` also sets ``delay`` to
    ``14/1024`` s; the compensators read the time keys (``delay``, ``delay_min``, …).
    """
    sec[key] = float(value)
    sk = _PAIR.get(key)
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


def resolve_channel(cfg: Config, entry: Mapping[str, Any]) -> ChannelConfig:
    """A channel's configuration: the top-level sections with the channel's keys over them.

    A key the channel sets replaces the top-level value (tables too: a channel's
    ``twin.actuator`` is its whole actuator model), except ``driver.connection``, which is
    merged key by key so that a channel can set only its ``node`` or ``device_id`` (a channel
    on another driver than the top-level one starts from an empty connection).
    """
    out = Config(copy.deepcopy({k: v for k, v in cfg.items() if k != "actuators"}))
    out.source, out.base_dir = cfg.source, cfg.base_dir
    own_driver = entry.get("driver", {}).get("name")
    if own_driver is not None and own_driver != cfg["driver"]["name"]:
        out["driver"]["connection"] = {}
    for section in CHANNEL_SECTIONS:
        for key, value in entry.get(section, {}).items():
            if section == "driver" and key == "connection":
                out[section][key] = {**out[section][key], **copy.deepcopy(value)}
            else:
                out[section][key] = copy.deepcopy(value)
    check_compensation_units(cfg)
    fs = out["loop"]["fs"]
    own = entry.get("compensation", {})
    _steps_to_time(out["compensation"], {k: v for k, v in own.items() if k in STEP_KEYS}, fs, "")
    _derive_steps(out["compensation"], fs)
    return ChannelConfig(
        name=entry.get("name", ""),
        dof=entry.get("dof"),
        transform=copy.deepcopy(entry.get("transform")),
        config=out,
    )


def default_config() -> Config:
    """The embedded default configuration (the FEI paper's NEES-711 setup, see module docstring)."""
    cfg = Config(
        {
            s: {k: copy.deepcopy(key.default) for k, key in keys.items()}
            for s, keys in SCHEMA.items()
        }
    )
    cfg["actuators"] = []
    return cfg


def _actuator(entry: Any, i: int, where: str) -> dict[str, Any]:
    """Validate one ``[[actuators]]`` entry (its own keys, not the cross-channel rules)."""
    path = f"actuators[{i}]"
    if not isinstance(entry, dict):
        raise InputError(f"{where}: {path}: expected a table [[actuators]], got {_describe(entry)}")
    out: dict[str, Any] = {}
    for key, value in entry.items():
        kp = f"{path}.{key}"
        if key == "name":
            if not isinstance(value, str) or not _NAME_RE.match(value):
                raise InputError(
                    f"{where}: {kp}: expected a name of 1 to 32 letters, digits and _ starting "
                    f"with a letter, got {_describe(value)}"
                )
            out["name"] = value
        elif key == "dof":
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InputError(
                    f"{where}: {kp}: expected a storey/DOF number ≥ 1, got {_describe(value)}"
                )
            out["dof"] = value
        elif key == "transform":
            if (
                not isinstance(value, list)
                or not value
                or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
                or not all(math.isfinite(v) for v in value)
            ):
                raise InputError(
                    f"{where}: {kp}: expected a non-empty array of finite numbers (a row of T), "
                    f"got {_describe(value)}"
                )
            out["transform"] = [float(v) for v in value]
        elif key in CHANNEL_SECTIONS:
            if not isinstance(value, dict):
                raise InputError(f"{where}: {kp}: expected a table, got {_describe(value)}")
            keys = SCHEMA[key]
            sec: dict[str, Any] = {}
            for name, v in value.items():
                if name not in keys:
                    raise InputError(f"{where}: {_unknown(f'{kp}.{name}', name, keys)}")
                try:
                    sec[name] = _coerce(keys[name], v, f"{kp}.{name}")
                except InputError as exc:
                    raise InputError(f"{where}: {exc}") from None
            out[key] = sec
        else:
            raise InputError(
                f"{where}: {_unknown(kp, key, (*_CHANNEL_KEYS, *CHANNEL_SECTIONS))} "
                "(an actuator sets name, dof or transform and the sections it overrides)"
            )
    if "name" not in out:
        raise InputError(f"{where}: {path}.name: every [[actuators]] entry needs a name")
    if "dof" in out and "transform" in out:
        raise InputError(f"{where}: {path}.transform: give dof or transform, not both")
    return out


def _merge(cfg: Config, data: Mapping[str, Any], where: str) -> None:
    for section, table in data.items():
        if section == "actuators":
            if not isinstance(table, list):
                raise InputError(
                    f"{where}: actuators: expected an array of tables [[actuators]], "
                    f"got {_describe(table)}"
                )
            cfg["actuators"] = [_actuator(e, i, where) for i, e in enumerate(table)]
            continue
        if section not in SCHEMA:
            raise InputError(f"{where}: {_unknown(section, section, SCHEMA)}")
        if not isinstance(table, dict):
            raise InputError(
                f"{where}: {section}: expected a table [{section}], got {_describe(table)}"
            )
        keys = SCHEMA[section]
        for name, value in table.items():
            path = f"{section}.{name}"
            if name not in keys:
                raise InputError(f"{where}: {_unknown(path, name, keys)}")
            try:
                cfg[section][name] = _coerce(keys[name], value, path)
            except InputError as exc:
                raise InputError(f"{where}: {exc}") from None
    # α and the other step keys of this source are read at this source's loop rate
    fs = cfg["loop"]["fs"]
    comp = data.get("compensation")
    if isinstance(comp, dict):
        _steps_to_time(cfg["compensation"], {k: cfg["compensation"][k] for k in comp}, fs, where)
    for entry in cfg.get("actuators") or []:
        own = entry.get("compensation")
        if own:
            _steps_to_time(own, own, fs, f"{where}: actuators.{entry['name']}")
            for sk in STEP_KEYS:
                own.pop(sk, None)


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``section.key=value`` into the key path and the value (TOML, else a string).

    Raises
    ------
    InputError
        No ``=`` or an empty key.
    """
    name, sep, raw = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise InputError(f"--set {text}: expected section.key=value")
    parts = name.split(".")
    if any(not p for p in parts) or len(parts) < 2:
        raise InputError(f"--set {text}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return parts, value


def _apply_channel_override(cfg: Config, parts: list[str], value: Any, where: str) -> None:
    """``--set actuators.NAME.key=value`` or ``--set actuators.NAME.section.key=value``."""
    chans = cfg.get("actuators") or []
    names = [c["name"] for c in chans]
    if len(parts) < 3:
        raise InputError(f"{where}: expected actuators.NAME.key=value")
    name = parts[1]
    if name not in names:
        known = ", ".join(names) if names else "none: the configuration has no [[actuators]]"
        raise InputError(f"{where}: actuators.{name}: no channel of that name (channels: {known})")
    i = names.index(name)
    entry = dict(chans[i])
    key = parts[2]
    if key in ("dof", "transform"):
        if len(parts) != 3:
            raise InputError(f"{where}: actuators.{name}.{key} is not a table")
        entry[key] = value
        entry.pop("transform" if key == "dof" else "dof", None)
    elif key in CHANNEL_SECTIONS:
        if len(parts) < 4:
            raise InputError(f"{where}: expected actuators.{name}.{key}.KEY=value")
        sec = copy.deepcopy(entry.get(key, {}))
        kname = parts[3]
        if kname not in SCHEMA[key]:
            raise InputError(
                f"{where}: {_unknown(f'actuators.{name}.{key}.{kname}', kname, SCHEMA[key])}"
            )
        if len(parts) > 4:
            if SCHEMA[key][kname].kind != "table":
                raise InputError(f"{where}: actuators.{name}.{key}.{kname} is not a table")
            node = sec.setdefault(kname, copy.deepcopy(cfg[key][kname]))
            for p in parts[4:-1]:
                node = node.setdefault(p, {})
                if not isinstance(node, dict):
                    raise InputError(f"{where}: {'.'.join(parts[:-1])} is not a table")
            node[parts[-1]] = value
        else:
            sec[kname] = value
        entry[key] = sec
    else:
        known = (*_CHANNEL_KEYS[1:], *CHANNEL_SECTIONS)
        raise InputError(f"{where}: {_unknown(f'actuators.{name}.{key}', key, known)}")
    chans[i] = _actuator(entry, i, where)


def _apply_override(cfg: Config, text: str, where: str | None = None) -> None:
    parts, value = parse_override(text)
    where = where or f"--set {text}"
    section, name = parts[0], parts[1]
    if section == "actuators":
        _apply_channel_override(cfg, parts, value, where)
        return
    if section in CHANNEL_SECTIONS and len(parts) == 2:
        # a top-level --set applies to every channel: the channels' own values give way
        # (driver.connection is merged key by key: the channels keep their node / unit id)
        if (section, name) != ("driver", "connection"):
            names = [name]
            if section == "compensation" and name in _PAIR:
                names = [_PAIR[name], STEP_KEYS[_PAIR[name]][0]]  # α and delay alike
            for entry in cfg.get("actuators") or []:
                for n in names:
                    entry.get(section, {}).pop(n, None)
    if section not in SCHEMA:
        raise InputError(f"{where}: {_unknown(section, section, SCHEMA)}")
    keys = SCHEMA[section]
    if name not in keys:
        raise InputError(f"{where}: {_unknown(section + '.' + name, name, keys)}")
    key = keys[name]
    if len(parts) > 2:
        if key.kind != "table":
            raise InputError(f"{where}: {section}.{name} is not a table")
        node = cfg[section][name]
        for p in parts[2:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise InputError(f"{where}: {'.'.join(parts[:-1])} is not a table")
        node[parts[-1]] = value
        return
    try:
        cfg[section][name] = _coerce(key, value, f"{section}.{name}")
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _cross_check(cfg: Config, note: str = "") -> None:
    where = cfg.source + note
    _cross_check_one(cfg, where)
    st = cfg["structure"]
    if st["kind"] == "shear_building":
        if not st["masses"] or len(st["masses"]) != len(st["stiffnesses"]):
            raise InputError(
                f"{where}: structure.stiffnesses: a shear building needs one mass and one "
                f"stiffness per storey, got {len(st['masses'])} masses and "
                f"{len(st['stiffnesses'])} stiffnesses"
            )
    if st["rayleigh"] and len(st["rayleigh"]) != 2:
        raise InputError(f"{where}: structure.rayleigh: expected [alpha, beta] or []")
    if st["kind"] == "matrices" and not st["matrices"]:
        raise InputError(f"{where}: structure.matrices: kind = 'matrices' needs the files")
    chans = cfg.get("actuators") or []
    seen: set[str] = set()
    for i, e in enumerate(chans):
        if e["name"] in seen:
            raise InputError(f"{where}: actuators[{i}].name: duplicate channel name {e['name']!r}")
        seen.add(e["name"])
    n_dof = structure_dofs(cfg)
    for i, e in enumerate(chans):
        path = f"{where}: actuators[{i}] ({e['name']})"
        if n_dof is not None and "dof" in e and not e["dof"] <= n_dof:
            raise InputError(
                f"{path}.dof: {e['dof']} is out of range: the structure has {n_dof} DOF "
                f"(1..{n_dof})"
            )
        if n_dof is not None and "transform" in e and len(e["transform"]) != n_dof:
            raise InputError(
                f"{path}.transform: {len(e['transform'])} entries, the structure has {n_dof} DOF"
            )
        site = st["kind"] == "openfresco"  # its DOFs are its actuators: channel i on DOF i
        if n_dof is not None and n_dof > 1 and "dof" not in e and "transform" not in e and not site:
            raise InputError(
                f"{path}: say where the actuator acts: dof = 1..{n_dof} or transform = [...]"
            )
        if any(section in e for section in CHANNEL_SECTIONS):
            _cross_check_one(resolve_channel(cfg, e).config, f"{path}")


def structure_dofs(cfg: Config) -> int | None:
    """Number of DOF of the configured structure (None when only the model file knows)."""
    s = cfg["structure"]
    if s["kind"] == "sdof":
        return 1
    if s["kind"] == "shear_building":
        return len(s["masses"])
    if s["kind"] == "openfresco":  # the site's DOFs are its actuators
        return len(cfg.get("actuators") or []) or 1
    return None


def _cross_check_one(cfg: Config, where: str) -> None:
    s, lp, c, sf = cfg["structure"], cfg["loop"], cfg["compensation"], cfg["safety"]
    if s["fn"] >= lp["fs"] / 2:
        raise InputError(
            f"{where}: structure.fn: {s['fn']:g} Hz is not below the Nyquist "
            f"frequency of loop.fs ({lp['fs'] / 2:g} Hz)"
        )
    if s["bouc_wen"] and not (s["beta"] + s["gamma"] > 0):
        raise InputError(f"{where}: structure.beta + structure.gamma must be > 0")
    if c["alpha_min"] > c["alpha_max"]:
        raise InputError(
            f"{where}: compensation.alpha_min ({c['alpha_min']:g}) exceeds "
            f"compensation.alpha_max ({c['alpha_max']:g})"
        )
    if sf["kf_gain_min"] >= sf["kf_gain_max"]:
        raise InputError(f"{where}: safety.kf_gain_min must be below safety.kf_gain_max")
    w = cfg["fei"]["window"]
    try:
        ws = cfg.window_s
    except InputError as exc:
        raise InputError(f"{where}: fei.window: {exc}") from None
    if not ws * lp["fs"] >= 8:
        raise InputError(f"{where}: fei.window: {w!r} is fewer than 8 samples at {lp['fs']:g} Hz")
    if c["adaptive"] and not cfg["fei"]["enabled"]:
        raise InputError(f"{where}: compensation.adaptive needs fei.enabled = true")


#: Largest configuration file read (bytes): a real one is a few kB.
MAX_CONFIG_BYTES = 1 << 20


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> Config:
    """Read a configuration file over the defaults, then apply ``--set`` overrides.

    Parameters
    ----------
    path : str or Path, optional
        TOML file. ``None`` gives the embedded default.
    overrides : iterable of str
        ``section.key=value`` items, applied in order.

    Returns
    -------
    Config

    Raises
    ------
    InputError
        Unreadable file, TOML syntax error, unknown key, wrong type, unit or range — naming
        the file (or ``--set`` item) and the key path.
    """
    cfg = default_config()
    if path is not None:
        p = Path(path)
        data = read_toml(p, "config", str(path), max_bytes=MAX_CONFIG_BYTES)
        cfg.source = str(path)
        cfg.base_dir = p.resolve().parent
        _merge(cfg, data, str(path))
    else:
        cfg.base_dir = Path.cwd()
    return apply_overrides(cfg, overrides)


def apply_overrides(cfg: Config, overrides: Iterable[str], where: str | None = None) -> Config:
    """Apply ``section.key=value`` items to ``cfg`` in place as ``--set`` does (α read at the
    final loop rate), then cross-check; ``where`` labels errors (default ``--set ITEM``)."""
    overrides = list(overrides)
    # (channel name or None, step key) → the key of the pair the last --set gave
    last: dict[tuple[str | None, str], str] = {}
    for item in overrides:
        _apply_override(cfg, item, where)
        parts = parse_override(item)[0]
        if parts[0] == "compensation" and len(parts) == 2 and parts[1] in _PAIR:
            sk = _PAIR[parts[1]]
            last = {k: v for k, v in last.items() if k[1] != sk}  # the channels' gave way
            last[(None, sk)] = parts[1]
        elif parts[0] == "actuators" and len(parts) == 4 and parts[2] == "compensation":
            if parts[3] in _PAIR:
                last[(parts[1], _PAIR[parts[3]])] = parts[3]
    # a --set α is read at the final loop rate; the time keys carry over a change of rate
    fs = cfg["loop"]["fs"]
    for (chan, sk), key in last.items():
        tk, off = STEP_KEYS[sk]
        if chan is None:
            sec = cfg["compensation"]
        else:
            sec = next(e for e in cfg["actuators"] if e["name"] == chan)["compensation"]
        if key == sk:
            sec[tk] = (sec[sk] - off) / fs
        if chan is not None:
            sec.pop(sk, None)
    _derive_steps(cfg["compensation"], fs)
    _cross_check(cfg, " (with --set overrides)" if overrides else "")
    return cfg


# --------------------------------------------------------------------------------------------
# rendering


def to_toml(cfg: Mapping[str, Mapping[str, Any]], comments: bool = True) -> str:
    """Render a configuration as TOML (with each key's unit and description as comments)."""
    lines: list[str] = []
    for section, keys in SCHEMA.items():
        lines.append(f"[{section}]")
        for name, key in keys.items():
            value = cfg.get(section, {}).get(name, key.default)
            line = f"{name} = {_toml_value(value)}"
            if comments:
                unit = "" if key.unit == "-" else f"[{key.unit}] "
                line = f"{line:<44} # {unit}{key.doc}"
            lines.append(line)
        lines.append("")
    for entry in cfg.get("actuators") or []:
        lines.append("[[actuators]]")
        for key in _CHANNEL_KEYS:
            if key in entry:
                lines.append(f"{key} = {_toml_value(entry[key])}")
        for section in CHANNEL_SECTIONS:
            if entry.get(section):
                lines.append(f"[actuators.{section}]")
                lines += [f"{k} = {_toml_value(v)}" for k, v in entry[section].items()]
        lines.append("")
    return "\n".join(lines)


def schema_markdown() -> str:
    """The configuration reference (``docs/config.md``) generated from :data:`SCHEMA`."""
    out = [
        "# Configuration reference",
        "",
        "<!-- generated by rths_hil.config.schema_markdown(); do not edit by hand -->",
        "",
        "`rths-hil run [CONFIG.toml] [--set section.key=value]...` reads a TOML file over the",
        "embedded defaults (the FEI paper's NEES project 711 setup), then applies the `--set`",
        "overrides in order. Every key is optional. Floats take a plain number in the SI unit",
        'shown, or a string with a unit (`"15ms"`, `"50mm"`, `"2 in"`, `"0.0328g"`, `"2%"`,',
        '`"100 kN"`, `"20 kip"`, `"200 mm/s"`): lengths in m, mm, cm, um, in or ft, forces in N,',
        "kN, MN, lbf or kip, velocities in any of those lengths per s (`rths_hil/units.py`).",
        "A `--set` value is read as TOML (`--set loop.fs=2048`, `--set fei.enabled=false`,",
        "`--set 'driver.connection={port=1502}'`); text that is not TOML is taken as a string",
        "(`--set driver.name=modbus`, `--set safety.fei_delay_tol=10ms`). Keys inside a table",
        "key can be set one by one (`--set twin.actuator.delay=0.01`).",
        "",
        "Errors (unknown key, wrong type, unit or range) are one line naming the file or the",
        "`--set` item and the key path; `rths-hil run` then exits with code 2.",
        "`rths-hil run --show-config` prints the resolved configuration as TOML (values written",
        "by `tomli_w`: strings with newlines, quotes or control characters read back unchanged).",
        "",
        "A configuration file must be a regular file of at most 1 MiB (a FIFO or a device such",
        "as `/dev/zero` is refused before it is read). Masses and stiffnesses of the numerical",
        "substructure must be physically plausible: 1 g to 10 Mt, 1 mN/m to 1 TN/m (beyond",
        "them the structure's matrices are singular or its response overflows). Before anything",
        "is allocated the run estimates what it needs and refuses, naming the figure, a duration",
        "whose per-step arrays (32 bytes a step) exceed half the available memory, a record",
        "(rows × row size) larger than the free disk space of `output.dir`, and a",
        "`fei.exact_hop` longer than both the run and the record (`rths_hil/resources.py`).",
        "",
    ]
    for section, keys in SCHEMA.items():
        out += [
            f"## [{section}]",
            "",
            "| key | type | unit | range | default | description |",
            "|---|---|---|---|---|---|",
        ]
        for name, key in keys.items():
            if key.kind == "choice":
                rng = " / ".join(key.choices)
            elif key.lo is not None or key.hi is not None:
                lo = "" if key.lo is None else f"{'(' if key.lo_open else '['}{key.lo:g}"
                hi = "" if key.hi is None else f"{key.hi:g}{')' if key.hi_open else ']'}"
                rng = f"{lo or '(−∞'}, {hi or '∞)'}"
            else:
                rng = ""
            kind = {"window": 'float or "nT"', "table": "table", "array": "array"}.get(
                key.kind, key.kind
            )
            out.append(
                f"| `{name}` | {kind} | {key.unit} | {rng} | "
                f"`{_toml_value(key.default)}` | {key.doc} |"
            )
        out.append("")
    out += [
        "## [[actuators]]",
        "",
        "Several actuators (channels) in one test: one `[[actuators]]` table per channel. Without",
        "any, the test has one channel made of the top-level sections (a single-actuator test).",
        "The top-level `driver`, `twin`, `compensation`, `fei`, `kalman` and `safety` sections are",
        "the defaults every channel inherits; a channel overrides any of their keys in its own",
        "sub-tables (`[actuators.compensation]`, …). A key a channel sets replaces the top-level",
        "value (tables too), except `driver.connection`, merged key by key (a channel sets only",
        "its `node` or `device_id`; a channel on another driver starts from an empty",
        "connection). `--set section.key=value` sets a key on every channel;",
        "`--set actuators.NAME.section.key=value` on one. See `docs/channels.md`.",
        "",
        "| key | type | description |",
        "|---|---|---|",
        "| `name` | str | channel name (letters, digits, _); record columns carry `_NAME` |",
        "| `dof` | int | 1-based DOF (storey) the actuator acts on |",
        "| `transform` | array | row of T: actuator displacement = T·u, force returned as Tᵀ·f "
        "(`[-1, 1, 0]`: between storeys 1 and 2); instead of `dof` |",
        "",
    ]
    return "\n".join(out)

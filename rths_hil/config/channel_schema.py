"""The sections of the schema a channel (``[[actuators]]``) may override: ``control``,
``driver``, ``twin``, ``compensation``, ``fei``, ``kalman``, ``safety``
(:data:`rths_hil.config.schema.SCHEMA` holds them in this order between ``end`` and
``openfresco``)."""

from __future__ import annotations

import importlib

from rths_hil.compensators import BUILTIN as BUILTIN_COMPENSATORS
from rths_hil.drivers.registry import DEFAULT as DEFAULT_DRIVER

from ..keys import CONTROL_MODES, Key, seconds, steps

__all__ = ["CHANNEL_SCHEMA"]


def _pair(default: str, doc: str) -> Key:
    """The signals an estimator compares with the measured one: the target (as in the FEI
    paper) or the command."""
    return Key("choice", default, doc=doc, choices=("target", "command"))


#: The keys every compensation method shares; then the keys each built-in method declares
#: (:attr:`Compensator.KEYS <rths_hil.compensators.base.Compensator.KEYS>`), then
#: :data:`_COMPENSATION_TAIL`.
_COMPENSATION_COMMON: dict[str, Key] = {
    "enabled": Key("bool", True, doc="actuator delay compensation on"),
    "method": Key(
        "str",
        "inverse",
        doc="compensator: inverse, polynomial, ats, model or a lab's own registered under "
        "the entry-point group rths_hil.compensators (docs/compensation.md)",
    ),
    "delay": seconds(
        0.025,
        doc="delay to compensate (inverse: α = 1 + delay·fs; polynomial: extrapolation "
        "horizon; ats: initial a1; model: the model's transport delay)",
        hi=1.0,
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
    "amplitude": Key("float", 1.0, doc="amplitude factor on the command", lo=0, lo_open=True),
}
_COMPENSATION_TAIL: dict[str, Key] = {
    "options": Key("table", {}, doc="a lab compensator's own keys (passed to its from_config)"),
}


def _compensation() -> dict[str, Key]:
    """The ``compensation`` section: the shared keys, the keys of each built-in compensator
    (:data:`rths_hil.compensators.BUILTIN`, in its order), ``options``.

    Raises
    ------
    TypeError
        Two methods declare one key differently, or a method redeclares a shared key.
    """
    keys = dict(_COMPENSATION_COMMON)
    for name, target in BUILTIN_COMPENSATORS.items():
        module, _, attr = target.partition(":")
        cls = getattr(importlib.import_module(module), attr)
        for key, spec in cls.KEYS.items():
            if key in _COMPENSATION_COMMON or keys.get(key, spec) != spec:
                raise TypeError(f"compensator {name!r}: compensation.{key} is declared twice")
            keys[key] = spec
    return {**keys, **_COMPENSATION_TAIL}


#: section → key → :class:`~rths_hil.keys.Key` of the per-channel sections.
CHANNEL_SCHEMA: dict[str, dict[str, Key]] = {
    "control": {
        "mode": Key(
            "choice",
            "displacement",
            doc="what the channel's actuator follows: displacement (the structure's trial "
            "displacement; tracked: the measured displacement), force (a force from the "
            "numerical substructure, force-based substructuring: docs/channels.md; tracked: the "
            "measured force) or load (a constant or scheduled force held through the test, "
            "control.load or control.load_schedule; tracked: the measured force). "
            'control = "force" is read as control.mode = "force"',
            choices=CONTROL_MODES,
        ),
        "load": Key(
            "float",
            0.0,
            unit="N",
            doc="load: the constant force held through the test",
        ),
        "load_schedule": Key(
            "schedule",
            [],
            unit="s, N",
            doc="load: [[t, F], …] the force held, piecewise linear in the test's time t from "
            "step 0 (held before the first and after the last point); instead of control.load",
        ),
        "load_ramp": seconds(
            0.0,
            doc="force and load: the ramp of the force up from where it is to the first load "
            "after arming, and down to 0 N before the hand-back (0 = start.ramp_time)",
            hi=600,
        ),
    },
    "driver": {
        "name": Key(
            "str",
            DEFAULT_DRIVER,
            doc="driver name in the registry (can, modbus, serial, canopen, or a lab's entry "
            "point)",
        ),
        "connection": Key(
            "table",
            {},
            doc="driver connection settings (e.g. interface/channel for CAN, "
            "host/port for Modbus, url for serial, eds/node_id/profile for CANopen: "
            "docs/canopen.md); with a twin they go to the twin, which hands the driver its "
            "endpoint",
        ),
        "profile": Key(
            "str",
            "rths-hil",
            doc="controller profile: 'rths-hil' (the driver's own protocol) or a profile file "
            "(TOML: the lab's register map or DBC, docs/profiles.md); the twin speaks it too",
        ),
        "stepped": Key(
            "bool",
            False,
            doc="the controller advances one step per command (virtual time), so a lockstep "
            "run against it without a twin is allowed",
        ),
    },
    "twin": {
        "enabled": Key(
            "bool",
            True,
            doc="run an in-process virtual twin (false: real controller at the connection)",
        ),
        "inline": Key(
            "bool",
            True,
            doc="serve a twin on python-can's in-process virtual bus from the loop thread "
            "(same frames and controller, no thread hand-off; a CANopen twin's own thread "
            "still answers the SDO exchanges); false: in its own thread",
        ),
        "model": Key(
            "str", "", doc="twin model file (TOML, [actuator] ...); empty: the tables below"
        ),
        "actuator": Key(
            "table",
            {"model": "first_order", "time_constant": 0.020, "delay": 0.005, "gain": 1.0},
            doc="actuator model as in a model file's [actuator] table",
        ),
        "specimen": Key(
            "table",
            {},
            doc="specimen model as in a model file's [specimen] table (empty: the model "
            "file default)",
        ),
        "sensor": Key(
            "table",
            {"displacement_noise": 2e-6, "force_noise": 5.0, "seed": 0},
            doc="sensor noise and quantisation as in a model file's [sensor] table",
        ),
        "watchdog": seconds(
            0.5,
            doc="paced: the in-process twin's controller-side watchdog: no command or heartbeat "
            "for this long while enabled → it holds and latches its e-stop (0 = off; off in "
            "lockstep)",
        ),
        "faults": Key(
            "str",
            "",
            doc="fault plan for tests and dry runs, e.g. 'stuck_from=3000' "
            "(rths_hil.sim_backends.faults)",
        ),
        "initial_position": Key(
            "float",
            0.0,
            unit="m",
            doc="where the twin's actuator sits at rest (an actuator left off centre)",
        ),
        "force_loop_gain": Key(
            "float",
            2.0e-4,
            unit="m/(s·N)",
            doc="force and load channels: the twin's force-loop gain K_f (piston velocity per N "
            "of force error); its closed loop lags by T = (1 + K_f·c)/(K_f·k) on the twin's "
            "specimen k, c (4.2 ms on the default 1.19 MN/m specimen)",
            lo=0,
            lo_open=True,
        ),
    },
    "compensation": _compensation(),
    "fei": {
        "enabled": Key("bool", True, doc="online FEI (streaming every sample)"),
        "pair": _pair(
            "target",
            doc="evaluated pair: measured vs target (as in the FEI paper) or measured vs command",
        ),
        "window": Key(
            "window",
            "3T",
            unit="s",
            doc="window length t_w in s, or in natural periods ('3T' = 3/fn)",
            lo=0,
            lo_open=True,
        ),
        "exact_hop": steps(256, doc="exact FEI cross-check every this many samples (0 = off)"),
    },
    "kalman": {
        "enabled": Key("bool", True, doc="Kalman gain/delay estimator beside the FEI"),
        "pair": _pair(
            "command", doc="input of the estimator: command (the actuator's own delay) or target"
        ),
        "every": steps(1, doc="run the estimator every this many steps", lo=1),
        "options": Key("table", {}, doc="estimator keyword arguments (rths_hil.estimation)"),
    },
    "safety": {
        "displacement_limit": Key(
            "float",
            0.050,
            unit="m",
            doc="|target|, |command|, |measured| limit (0 = off); on a force or load channel "
            "the |measured| and the structure's |trial| displacement",
            lo=0,
        ),
        "velocity_limit": Key(
            "float",
            0.5,
            unit="m/s",
            doc="|structure velocity| and |measured velocity| limit (0 = off)",
            lo=0,
        ),
        "force_limit": Key(
            "float",
            100e3,
            unit="N",
            doc="|measured force| limit (0 = off); on a force or load channel also the limit "
            "of its target and commanded force",
            lo=0,
        ),
        "fei_amplitude_tol": Key(
            "float", 0.2, doc="FEI rule: tolerance on |A − 1| (0 = off)", lo=0
        ),
        "fei_delay_tol": seconds(0.015, doc="FEI rule: tolerance on |d| (0 = off)"),
        "fei_consecutive": Key(
            "int",
            256,
            unit="windows",
            doc="FEI rule: consecutive valid windows out of tolerance that trip",
            lo=1,
        ),
        "kf_gain_min": Key("float", 0.5, doc="Kalman rule: lowest gain estimate"),
        "kf_gain_max": Key("float", 1.5, doc="Kalman rule: highest gain estimate"),
        "kf_delay_max": seconds(0.1, doc="Kalman rule: |delay estimate| limit (0 = off)"),
        "watchdog_missed": steps(
            0,
            doc="consecutive missed replies that also trip (0 = none beyond watchdog_timeout; "
            "lockstep counts watchdog_timeout in steps of virtual time)",
        ),
        "watchdog_timeout": seconds(
            0.1,
            doc="controller silence that trips: time without a good reply while the bridge "
            "ran (paced: wall clock, stalls of the bridge not counted; lockstep: virtual time); "
            "shorter gaps hold the measurement and are counted, not tripped. Keep it above the "
            "controller's own reply pauses and below its heartbeat watchdog (rths-hil "
            "commission measures both)",
            positive=True,
        ),
        "max_stall": seconds(
            0.2,
            doc="paced: a stall of the bridge itself (this process or computer not running "
            "the loop) longer than this trips; shorter ones are events and the test goes on",
            positive=True,
        ),
        "max_sequence_gaps": Key("int", 0, doc="sequence gaps tolerated before a trip", lo=0),
        "controller_status": Key(
            "bool", True, doc="trip on the controller's alarm bits (e-stop, fault, watchdog)"
        ),
        "max_overruns": steps(100, doc="consecutive paced overruns that trip", lo=1),
        "stuck_steps": steps(
            50, doc="identical measured values while the command moves that trip (0 = off)"
        ),
        "stuck_motion": Key(
            "float",
            1e-4,
            unit="m",
            doc="stuck rule: command travel needed over those steps",
            lo=0,
            lo_open=True,
        ),
        "warmup": seconds(0.0, doc="FEI, Kalman and stability rules start after this loop time"),
        "stability": Key(
            "choice",
            "warn",
            doc="energy stability indicator S (docs/stability.md): off, warn (a stability "
            "event when S crosses stability_warn) or trip (also the e-stop above "
            "stability_limit)",
            choices=("off", "warn", "trip"),
        ),
        "stability_warn": Key(
            "float",
            1.0,
            doc="S (energy the tracking error injects over what the structure's damping "
            "dissipates) above which a stability event is recorded; 1 is the linear stability "
            "boundary",
            lo=0,
            lo_open=True,
        ),
        "stability_limit": Key(
            "float",
            1.5,
            doc="S above which stability = 'trip' stops the test (at least stability_warn)",
            lo=0,
            lo_open=True,
        ),
        "stability_window": Key(
            "window",
            "3T",
            unit="s",
            doc="time constant of the indicator's exponential window, in s or natural periods "
            "('3T' = 3/fn)",
            lo=0,
            lo_open=True,
        ),
        "stability_min_velocity": Key(
            "float",
            2e-4,
            unit="m/s",
            doc="RMS structure velocity over the window below which S is not valid (at rest)",
            lo=0,
        ),
        "stability_damping": Key(
            "float",
            0.0,
            unit="N·s/m",
            doc="viscous damping of the structure along the actuator c_a (0 = from the "
            "structure: SDOF c, several DOFs the coupled fundamental mode's; needed for "
            "structure.kind = openfresco)",
            lo=0,
        ),
    },
}

"""Configuration → test plan: every decision about what runs, made once, before any I/O.

:func:`build_plan` reads a resolved :class:`~rths_hil.config.Config` and returns a
:class:`TestPlan`: the ground motion, the structure stage, one :class:`ChannelPlan` per
actuator (where it acts, its driver and twin, compensator, evaluators and safety rules) and the
record's columns. All validation of a configuration beyond single keys happens here, so a
reader who asks "where does this key go" reads this module only; what happens at each step is
in :mod:`rths_hil.hybrid.runner`.

Which twin a channel gets is decided in one function, :func:`choose_plant`.
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import groundmotion
from ..compensators.base import Compensator
from ..compensators.inverse import AdaptiveAlpha, InverseCompensator
from ..config import ChannelConfig, Config, check_window_samples
from ..errors import InputError
from ..records import columns
from ..resources import check_disk, check_memory
from ..safety import (
    ControllerRule,
    FEIRule,
    KalmanRule,
    SafetyMonitor,
    SequenceRule,
    StabilityRule,
    StuckRule,
    WatchdogRule,
)
from ..structures.stages import StructureStage, TrialColumns
from ..units import parse_window
from .setup import channel_row
from .substructure import (
    build_ground_motion,
    build_structure,
    choose_plant,
    structure_size,
)

log = logging.getLogger(__name__)

__all__ = [
    "ChannelPlan",
    "LoadSchedule",
    "TestPlan",
    "build_plan",
    "new_run_dir",
    "record_columns",
]


def new_run_dir(pattern: str, base: Path | None = None) -> Path:
    """Expand ``{timestamp}`` in ``pattern``; add a suffix if the directory already has a run."""
    if not str(pattern).strip():
        raise InputError("output.dir is empty: give a run directory such as 'runs/{timestamp}'")
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    p = Path(pattern.replace("{timestamp}", stamp)).expanduser()
    if base is not None and not p.is_absolute():
        p = base / p
    out, i = p, 1
    try:
        while any((out / f).exists() for f in ("record.npy", "events.jsonl", "meta.json")):
            out = p.with_name(f"{p.name}-{i}")
            i += 1
    except OSError as exc:  # a path component over 255 characters, no permission
        raise InputError(f"output.dir: {p}: {exc.strerror or exc}") from None
    return out


# ----------------------------------------------------------------------------------------------
# record columns


def record_columns(
    channels: list[str], n_dof: int, structure: StructureStage | None = None
) -> list[tuple[str, str, str, str]]:
    """The record's columns (name, dtype, unit, description), in file order.

    The table of :mod:`rths_hil.records.columns` laid out for ``channels`` (their names;
    ``[""]`` for one channel) on ``n_dof`` DOFs, then the structure stage's own columns.
    """
    cols = columns.specs(channels, n_dof)
    if structure is not None:
        cols += [(col[0], col[2], col[3], col[4]) for col in structure.record_columns]
    return cols


# ----------------------------------------------------------------------------------------------
# plans


class LoadSchedule:
    """The force a load channel holds: constant, or piecewise linear in time.

    Parameters
    ----------
    load : float
        The constant force (N), used when ``schedule`` is empty.
    schedule : list of [t, F]
        Times (s from step 0, non-decreasing) and forces (N); held before the first point and
        after the last.

    Examples
    --------
    >>> s = LoadSchedule(0.0, [[0.0, 100.0], [2.0, 300.0]])
    >>> s.at(1.0), s.at(5.0)
    (200.0, 300.0)
    """

    def __init__(self, load: float, schedule: list[list[float]] | None = None) -> None:
        pts = np.array(schedule if schedule else [[0.0, load]], dtype=float).reshape(-1, 2)
        self.times = pts[:, 0]
        self.forces = pts[:, 1]
        self.constant = float(self.forces[0]) if np.all(self.forces == self.forces[0]) else None

    def at(self, t: float) -> float:
        """The force (N) at time ``t`` (s)."""
        if self.constant is not None:
            return self.constant
        return float(np.interp(t, self.times, self.forces))

    @property
    def peak(self) -> float:
        """The largest magnitude of the schedule (N)."""
        return float(np.max(np.abs(self.forces)))


@dataclass
class ChannelPlan:
    """One actuator channel, planned (no I/O yet).

    Attributes
    ----------
    name : str
        Channel name (``""``: the single unnamed channel).
    suffix : str
        Column suffix (``""`` for a single channel, else ``_<name>``).
    row : ndarray
        Row of the transformation matrix T (n_dof).
    dof : int
        0-based DOF when the row is a unit vector, else -1.
    cfg : Config
        The channel's resolved configuration.
    """

    name: str
    suffix: str
    row: np.ndarray
    dof: int
    cfg: Config
    driver_name: str
    connection: dict[str, Any]
    twin_enabled: bool
    twin_inline: bool
    twin_watchdog: float | None
    plant: Any
    faults: Any
    compensator: Compensator
    adaptive: AdaptiveAlpha | None
    fei_enabled: bool
    window_s: float
    fei_pair: str
    exact_hop: int
    kalman: Any
    kalman_pair: str
    kalman_every: int
    monitor: SafetyMonitor
    warmup_steps: int
    #: the energy stability indicator (:mod:`rths_hil.stability`): window (s), damping along
    #: the actuator (N·s/m; 0: no indicator) and lowest RMS velocity (m/s)
    stability_window: float = 0.0
    stability_damping: float = 0.0
    stability_min_velocity: float = 0.0
    #: ``control.mode``: displacement, force (the force target from the structure) or load
    #: (the force from :attr:`load`); the wire mode is force for both of the latter
    control: str = "displacement"
    #: force: the specimen stiffness along the actuator its force targets are computed with
    #: (``structure.k_specimen``, N/m; docs/channels.md)
    k_force: float = 0.0
    #: load: the force held at a time from step 0 (N)
    load: LoadSchedule | None = None
    #: force and load: the force ramps' shortest duration (s)
    load_ramp: float = 0.0

    @property
    def wire_control(self) -> str:
        """The driver's control mode: ``displacement`` or ``force`` (a load channel too)."""
        return "displacement" if self.control == "displacement" else "force"


@dataclass
class TestPlan:
    """Everything a run needs, decided (see :func:`build_plan`)."""

    cfg: Config
    mode: str
    fs: float
    dt: float
    n_steps: int
    ag: np.ndarray
    ground_motion: groundmotion.GroundMotion
    run_dir: Path
    structure: StructureStage
    fn1: float
    channels: list[ChannelPlan]
    columns: list[tuple[str, str, str, str]]
    timeout: float
    spin: float
    overrun_threshold: float
    max_overruns: int
    heartbeat_steps: int
    console_interval: float
    priority: int
    links: list = field(default_factory=list)
    cpu: int = -1
    max_stall: float = 0.2
    after_stall: str = "slip"
    extra: dict = field(default_factory=dict)

    @property
    def n_dof(self) -> int:
        """Number of DOFs of the structure."""
        return self.structure.n_dof

    @property
    def transform(self) -> np.ndarray:
        """T: one row per channel (channels × DOFs; :mod:`.setup`)."""
        return np.array([ch.row for ch in self.channels])


#: The Kalman estimator's options in the tracked signal's unit and their defaults in m; a force
#: channel's are these times the specimen stiffness (``structure.k_specimen``, N/m).
KALMAN_SIGNAL_SCALES = {"measurement_noise": 5e-5, "offset_std0": 1e-3, "offset_rate": 1e-4}


def _window(ch_cfg: Config, fn1: float) -> float:
    w = ch_cfg["fei"]["window"]
    return parse_window(w, fn1) if isinstance(w, str) else float(w)


def _where(cc: ChannelConfig, i: int) -> str:
    return cc.config.source + (f": actuators[{i}] ({cc.name})" if cc.name else "")


def _plan_channel(  # noqa: C901
    cc: ChannelConfig,
    i: int,
    n_chan: int,
    row: np.ndarray,
    fs: float,
    fn1: float,
    plant,
    mode: str,
    c_along: float | None = None,
) -> ChannelPlan:
    cfg = cc.config
    dt = 1.0 / fs
    where = _where(cc, i)
    nz = np.flatnonzero(row)
    dof = int(nz[0]) if nz.size == 1 and row[nz[0]] == 1.0 else -1

    name = cfg["driver"]["name"]
    from rths_hil.drivers.registry import protocol

    try:
        proto = protocol(name)
    except InputError as exc:
        raise InputError(f"{where}: driver.name: {exc}") from None
    tw = cfg["twin"]
    if tw["enabled"]:
        from rths_hil.sim_backends.registry import available_twins

        twins = available_twins()
        if name not in twins:
            raise InputError(
                f"{where}: twin.enabled: there is no twin for driver {name!r} (twins exist "
                f"for {', '.join(sorted(twins))}); set twin.enabled = false to use the real "
                "controller"
            )
    conn = dict(cfg["driver"]["connection"])
    for key in proto.path_keys:  # files (a DBC, an EDS): relative to the config file
        if isinstance(conn.get(key), str) and conn[key]:
            conn[key] = str(cfg.resolve_path(conn[key]))
    profile = cfg["driver"]["profile"]
    from rths_hil.drivers.profile import is_builtin, load_profile

    control = cfg["control"]["mode"]
    wire = "displacement" if control == "displacement" else "force"  # a load is a force
    if not is_builtin(profile):
        path = cfg.resolve_path(profile)
        try:
            prof = load_profile(path)
        except InputError as exc:
            raise InputError(f"{where}: driver.profile: {exc}") from None
        if prof.protocol != proto.profile_protocol:
            speaks = proto.profile_protocol or "no profile"
            raise InputError(
                f"{where}: driver.profile: {path} is a {prof.protocol} profile; driver "
                f"{name!r} takes {speaks}"
            )
        try:  # every command within the displacement (force) limit must fit the set-point
            if wire == "force" and hasattr(prof, "for_control"):
                prof = prof.for_control("force")
                prof.check_setpoint_range(float(cfg["safety"]["force_limit"]))
            else:
                prof.check_setpoint_range(float(cfg["safety"]["displacement_limit"]))
        except InputError as exc:
            raise InputError(f"{where}: driver.profile: {exc}") from None
        conn["profile"] = str(path)
    # the driver that speaks the channel (its profile's, when it has one) runs its wire mode
    wcls = proto.driver if is_builtin(profile) else proto.profile_driver_class()
    from rths_hil.drivers.registry import check_connection

    # the connection as the driver declares it (types, SI units, ranges) and, with a twin, as
    # the twin's endpoint declares it (the twin fills in the line and the files)
    given = {k: v for k, v in conn.items() if k != "profile"}
    twin_keys = None
    if tw["enabled"]:
        from rths_hil.sim_backends.twin import twin_keys as endpoint_keys

        try:
            twin_keys = endpoint_keys(name, profile=not is_builtin(profile))
        except InputError as exc:
            raise InputError(f"{where}: twin.enabled: {exc}") from None
    checked = check_connection(
        wcls, given, where, defaults=False, twin=tw["enabled"], twin_keys=twin_keys
    )
    conn = {**checked, **({"profile": conn["profile"]} if "profile" in conn else {})}
    modes = tuple(getattr(wcls, "control_modes", ("displacement",)))
    if wire not in modes:
        hint = ""
        if proto.profile_protocol is not None and is_builtin(profile):
            hint = f"; a {proto.profile_protocol} profile (driver.profile) with a force role can"
        raise InputError(
            f"{where}: control.mode = {control!r}: driver {name!r} cannot run a "
            f"force-controlled channel (its control modes: {', '.join(modes)}){hint}"
        )
    if tw["enabled"] and plant is None:
        plant = choose_plant(cfg, dt)
    faults = None
    if tw["faults"]:
        from rths_hil.sim_backends.faults import Faults

        try:
            faults = Faults.parse(tw["faults"])
        except InputError as exc:
            raise InputError(f"{where}: twin.faults: {exc}") from None
    inline = bool(tw["inline"] and tw["enabled"] and proto.inline_twin(conn))

    # in time units (delay, delay_rate, …): the same at any loop.fs
    comp_cfg = cfg["compensation"]
    from ..compensators import build_compensator

    try:
        comp = build_compensator(comp_cfg, fs)
    except InputError as exc:
        raise InputError(f"{where}: compensation: {exc}") from None
    fe = cfg["fei"]
    adaptive = None
    if comp_cfg["adaptive"] and comp_cfg["enabled"]:
        if comp_cfg["method"] != "inverse":
            raise InputError(
                f"{where}: compensation.adaptive adapts the inverse method's α; method "
                f"{comp_cfg['method']!r} does not take it (ats adapts on its own)"
            )
        assert isinstance(comp, InverseCompensator)  # method "inverse" (checked above)
        adaptive = AdaptiveAlpha(
            comp,
            dt,
            fe["pair"],
            comp_cfg["time_constant"],
            comp_cfg["delay_rate"] * fs,
            1.0 + comp_cfg["delay_min"] * fs,
            1.0 + comp_cfg["delay_max"] * fs,
        )
    try:
        window_s = _window(cfg, fn1)
    except InputError as exc:
        raise InputError(f"{where}: fei.window: {exc}") from None
    check_window_samples(cfg["fei"]["window"], window_s, fs, where)  # "nT" with the model's fn1
    kc = cfg["kalman"]
    kalman = None
    if kc["enabled"]:
        from ..estimation import DelayGainEstimator

        opts = dict(kc["options"])
        if kc["pair"] == "command":
            opts.setdefault(
                "delay0", min((comp.alpha - 1.0) * dt, 0.09) if comp_cfg["enabled"] else 0.0
            )
        if wire == "force":  # the signal is a force: its noise and offset scales in N
            scale = float(cfg["structure"]["k_specimen"]) or 1.0e6  # N per m of the defaults
            for key, default in KALMAN_SIGNAL_SCALES.items():
                opts.setdefault(key, default * scale)
        try:
            kalman = DelayGainEstimator(fs, **opts)
        except (TypeError, InputError) as exc:
            raise InputError(f"{where}: kalman.options: {exc}") from None

    sf = cfg["safety"]
    monitor = SafetyMonitor(
        dt,
        displacement_limit=sf["displacement_limit"] or None,
        velocity_limit=sf["velocity_limit"] or None,
        force_limit=sf["force_limit"] or None,
        fei=(
            FEIRule(
                sf["fei_amplitude_tol"] or math.inf,
                sf["fei_delay_tol"] or math.inf,
                sf["fei_consecutive"],
            )
            if fe["enabled"] and (sf["fei_amplitude_tol"] or sf["fei_delay_tol"])
            else None
        ),
        kalman=(
            KalmanRule(sf["kf_gain_min"], sf["kf_gain_max"], sf["kf_delay_max"] or math.inf)
            if kc["enabled"]
            else None
        ),
        watchdog=WatchdogRule(
            # paced: silence in wall-clock time while the bridge ran (+ an explicit step
            # count); lockstep: the silence limit in steps of virtual time, and the generous
            # wall-clock bound of the wait for each reply
            sf["watchdog_missed"]
            if mode == "paced"
            else sf["watchdog_missed"] or max(1, math.ceil(sf["watchdog_timeout"] * fs - 1e-9)),
            sf["watchdog_timeout"] if mode == "paced" else cfg["loop"]["lockstep_timeout"],
        ),
        sequence=SequenceRule(sf["max_sequence_gaps"]),
        overrun=None,  # one rule for the whole loop (TestPlan.max_overruns)
        stuck=StuckRule(sf["stuck_steps"], sf["stuck_motion"]) if sf["stuck_steps"] else None,
        controller=ControllerRule() if sf["controller_status"] else None,
        control=control,
    )
    stab_window = stab_damping = 0.0
    if sf["stability"] != "off" and control != "load":  # a load is not from the structure
        w = sf["stability_window"]
        try:
            stab_window = parse_window(w, fn1) if isinstance(w, str) else float(w)
        except InputError as exc:
            raise InputError(f"{where}: safety.stability_window: {exc}") from None
        stab_damping = sf["stability_damping"] or c_along or 0.0
        if not stab_damping:
            why = (
                f"{where}: safety.stability: the damping of the structure along the actuator is "
                "not known here (structure.kind = openfresco, or the actuator does not move in "
                "the fundamental mode); give safety.stability_damping (N·s/m)"
            )
            if sf["stability"] == "trip":
                raise InputError(why)
            log.warning("%s; the stability indicator is off", why)
        else:
            try:
                monitor.stability = StabilityRule(
                    sf["stability_warn"], sf["stability_limit"], sf["stability"] == "trip", cc.name
                )
            except InputError as exc:
                raise InputError(f"{where}: {exc}") from None
    return ChannelPlan(
        name=cc.name,
        suffix=columns.channel_suffix(cc.name if n_chan > 1 else None),
        row=row,
        dof=dof,
        cfg=cfg,
        driver_name=name,
        connection=conn,
        twin_enabled=bool(tw["enabled"]),
        twin_inline=inline,
        # lockstep is virtual time: a stalled bridge is not a dead one
        twin_watchdog=(tw["watchdog"] or None) if mode == "paced" else None,
        plant=plant,
        faults=faults,
        compensator=comp,
        adaptive=adaptive,
        fei_enabled=bool(fe["enabled"]),
        window_s=window_s,
        fei_pair=fe["pair"],
        exact_hop=fe["exact_hop"] if fe["enabled"] else 0,
        kalman=kalman,
        kalman_pair=kc["pair"],
        kalman_every=kc["every"],
        monitor=monitor,
        warmup_steps=round(sf["warmup"] * fs),
        stability_window=stab_window,
        stability_damping=stab_damping,
        stability_min_velocity=sf["stability_min_velocity"],
        control=control,
        k_force=float(cfg["structure"]["k_specimen"]) if control == "force" else 0.0,
        load=(
            LoadSchedule(cfg["control"]["load"], cfg["control"]["load_schedule"])
            if control == "load"
            else None
        ),
        load_ramp=float(cfg["control"]["load_ramp"] or cfg["start"]["ramp_time"]),
    )


def damping_along_rows(
    cfg: Config, structure: StructureStage, model: Any, rows: list[np.ndarray]
) -> list[float | None]:
    """Each actuator's viscous damping along it, ``c_a`` (N·s/m; None: not known here).

    SDOF: the structure's ``c`` over the square of the transform (``v_a = row·v``); several
    DOFs: the coupled structure's fundamental mode (``K`` stiffened by
    ``structure.k_specimen`` along every actuator) referred to the actuator
    (:func:`rths_hil.stability.damping_along`); an OpenSees site: None.
    """
    kind = cfg["structure"]["kind"]
    if kind == "openfresco":
        return [None] * len(rows)
    if kind == "sdof":
        c = float(structure.stepper.c)  # type: ignore[attr-defined]
        return [c / float(r[0]) ** 2 for r in rows]
    from ..stability import damping_along

    ks = float(cfg["structure"]["k_specimen"])
    K = np.array(model.K, dtype=float)
    for r in rows:
        K = K + ks * np.outer(r, r)
    out: list[float | None] = []
    for r in rows:
        try:
            out.append(damping_along(model.C, K, model.M, r))
        except ValueError:  # the actuator does not move in the fundamental mode
            out.append(None)
    return out


def build_plan(  # noqa: C901
    cfg: Config,
    run_dir: str | Path | None = None,
    *,
    plant: Any = None,
    mode: str | None = None,
    duration: float | None = None,
) -> TestPlan:
    """Validate ``cfg`` and decide everything a run needs (no I/O).

    Parameters
    ----------
    cfg : Config
        Resolved configuration.
    run_dir : str or Path, optional
        Run directory; default from ``output.dir``.
    plant : Plant or dict, optional
        The twin's plant instead of the configured one: one plant (single channel) or
        ``{channel name: plant}``.
    mode, duration : optional
        Override ``loop.mode`` and ``loop.duration``.

    Raises
    ------
    InputError
        Anything wrong in the configuration, naming the key.
    """
    lp = cfg["loop"]
    site = cfg["structure"]["kind"] == "openfresco"
    if site:  # the timing mode decides the loop mode; OpenSees applies the ground motion
        timing = cfg["openfresco"]["timing"]
        need = "lockstep" if timing == "lockstep" else "paced"
        if mode is not None and mode != need:
            raise InputError(
                f"{cfg.source}: openfresco.timing = {timing!r} runs the loop {need}, not {mode}"
            )
        mode = need
    mode = mode or lp["mode"]
    if mode not in ("paced", "lockstep"):
        raise InputError(f"mode must be 'paced' or 'lockstep', got {mode!r}")
    fs = float(lp["fs"])
    dt = 1.0 / fs
    dur = lp["duration"] if duration is None else float(duration)
    if not (math.isfinite(dur) and dur >= 0):
        raise InputError(f"duration must be >= 0 s, got {duration!r}")
    if site and dur == 0:
        dur = cfg["openfresco"]["max_duration"]
    run_dir = Path(run_dir) if run_dir is not None else new_run_dir(cfg["output"]["dir"])

    gm = build_ground_motion(cfg)
    ag = np.asarray(gm.accel, dtype=float)
    n = round(dur * fs) if dur > 0 else ag.size
    if n < 2:
        raise InputError(f"duration {dur:g} s is shorter than two steps at {fs:g} Hz")
    # the loop's per-step arrays (ground motion, its padding and copy): refuse before allocating
    key = "loop.duration" if duration is None else "duration"
    check_memory(4 * 8 * n, f"{key} = {dur:g} s at {fs:g} Hz ({n:.3g} steps)")
    if n > ag.size:
        ag = np.concatenate([ag, np.zeros(n - ag.size)])
    ag = ag[:n].copy()
    if site:
        ag[:] = 0.0  # the record is OpenSees' business

    n_dof, model = structure_size(cfg)
    chans_cfg = cfg.channels()
    if n_dof > 1 and not cfg.get("actuators"):
        raise InputError(
            f"{cfg.source}: actuators: a structure of {n_dof} DOF needs [[actuators]] entries "
            "saying where each actuator acts (dof or transform)"
        )
    # a load channel's force comes from its schedule: it acts on no DOF (a zero row of T)
    loads = [cc.config["control"]["mode"] == "load" for cc in chans_cfg]
    for i, cc in enumerate(chans_cfg):
        if loads[i] and (cc.dof is not None or cc.transform is not None):
            key = "dof" if cc.dof is not None else "transform"
            raise InputError(
                f"{_where(cc, i)}.{key}: a control.mode = 'load' channel holds its load "
                "(control.load), it acts on no DOF of the structure: remove the key"
            )
    if all(loads):
        raise InputError(
            f"{cfg.source}: control.mode: every channel holds a load; a test needs a channel "
            "the structure drives (displacement or force)"
        )
    rows = [
        np.zeros(n_dof)
        if loads[i]
        # a site's DOFs are its actuators: channel i drives site DOF i + 1 by default
        else channel_row(cc.transform, cc.dof, n_dof, _where(cc, i), i + 1 if site else 1)
        for i, cc in enumerate(chans_cfg)
    ]
    coupled = [r for i, r in enumerate(rows) if not loads[i]]
    structure, fn1 = build_structure(cfg, dt, float(ag[0]), np.array(coupled), model)
    plants: dict[str, Any] = {}
    if plant is not None:
        if isinstance(plant, dict):
            plants = dict(plant)
        elif len(chans_cfg) == 1:
            plants = {chans_cfg[0].name: plant}
        else:
            raise InputError("plant=: several channels: pass {channel name: plant}")
    c_coupled = iter(damping_along_rows(cfg, structure, model, coupled))
    c_along = [None if loads[i] else next(c_coupled) for i in range(len(rows))]
    channels = [
        _plan_channel(
            cc, i, len(chans_cfg), rows[i], fs, fn1, plants.get(cc.name), mode, c_along[i]
        )
        for i, cc in enumerate(chans_cfg)
    ]
    for i, ch in enumerate(channels):
        if ch.exact_hop > max(n, gm.npts):  # its block buffer alone would be 16·hop bytes
            raise InputError(
                f"{_where(chans_cfg[i], i)}: fei.exact_hop = {ch.exact_hop} steps is longer than "
                f"the run ({n} steps) and the record: the exact cross-check would never run "
                "(0 turns it off)"
            )
        if ch.exact_hop > n:  # a run shortened below one hop: no exact window, nothing held
            log.warning(
                "%s: fei.exact_hop = %d steps is longer than this run (%d steps): no exact "
                "cross-check in it",
                _where(chans_cfg[i], i),
                ch.exact_hop,
                n,
            )
            ch.exact_hop = 0
        N = round(ch.window_s * fs)
        if ch.fei_enabled and N > min(n, gm.npts):
            longer = "record" if gm.npts < n else "run"
            what = (
                f"FEI window fei.window = {ch.window_s:g} s is longer than the {longer} "
                f"({min(n, gm.npts) / fs:g} s): no FEI window completes and the FEI rule "
                "never arms"
            )
            where = _where(chans_cfg[i], i)
            if N > gm.npts:  # longer than the whole record: can never work
                raise InputError(f"{where}: {what}")
            log.warning("%s", what)  # a short run asked for explicitly
    _check_shared_links(cfg, channels)
    links = link_loads(cfg, channels, fs)
    sf = cfg["safety"]
    forced = [ch for ch in channels if ch.control != "displacement"]
    multi = len(channels) > 1  # a record of one channel names its columns plainly
    if any(ch.control == "force" for ch in forced):  # the trial displacements beside
        structure = TrialColumns(
            structure,
            [
                (ch.name, columns.column_name("trial", ch.name if multi else None))
                for ch in forced
                if ch.control == "force"
            ],
        )
    cols = record_columns([ch.name for ch in channels], n_dof, structure)
    for ch in forced:  # the target and the command of a force channel are forces
        what = "the structure (force)" if ch.control == "force" else "control.load (load)"
        chan = ch.name if multi else None
        for i, (name, dtype, _, _) in enumerate(cols):
            if name == columns.column_name("target", chan):
                cols[i] = (name, dtype, "N", f"target force from {what}")
            elif name == columns.column_name("command", chan):
                cols[i] = (name, dtype, "N", "force set-point sent (after compensation)")
    row_bytes = sum(np.dtype(col[1]).itemsize for col in cols)
    check_disk(n * row_bytes, run_dir, f"the record of {dur or n / fs:g} s at {fs:g} Hz")
    return TestPlan(
        cfg=cfg,
        mode=mode,
        fs=fs,
        dt=dt,
        n_steps=n,
        ag=ag,
        ground_motion=gm,
        run_dir=run_dir,
        structure=structure,
        fn1=fn1,
        channels=channels,
        columns=cols,
        # paced: at most 0.8 period; lockstep waits for every reply, up to the wall-clock bound
        # that trips the watchdog
        timeout=(lp["feedback_timeout"] or 0.8 * dt) if mode == "paced" else lp["lockstep_timeout"],
        # never spin through a whole period: a SCHED_FIFO thread that never sleeps is stopped by
        # Linux's RT throttling (95 % of a CPU) for 50 ms every second
        spin=min(lp["spin"], 0.4 * dt),
        overrun_threshold=lp["overrun_threshold"] * dt,
        max_overruns=sf["max_overruns"],
        max_stall=sf["max_stall"],
        after_stall=lp["after_stall"],
        heartbeat_steps=round(lp["heartbeat"] * fs) if lp["heartbeat"] > 0 else 0,
        console_interval=lp["console"],
        priority=lp["priority"],
        links=links,
        cpu=_loop_cpu(lp["cpu"]),
    )


def _loop_cpu(cpu: int) -> int:
    """``loop.cpu``, checked against the CPUs this process may run on."""
    if cpu < 0:
        return -1
    allowed = sorted(os.sched_getaffinity(0))
    if cpu not in allowed:
        raise InputError(
            f"loop.cpu = {cpu}: this process may run on CPUs {', '.join(map(str, allowed))}"
        )
    return cpu


def link_loads(cfg: Config, channels: list[ChannelPlan], fs: float) -> list:
    """Each link's load (:mod:`rths_hil.linkbudget`); refuse a link above 80 % (one line).

    Channels with a twin and no explicit bus (CAN channel, Modbus port, serial port) each get a
    link of their own (a fresh virtual bus, port or pseudo-terminal).
    """
    from rths_hil.drivers.registry import protocol

    from ..linkbudget import check_links, link_key, link_load

    groups: dict[str, list[ChannelPlan]] = {}
    for i, ch in enumerate(channels):
        conn = ch.connection
        own = ch.twin_enabled and protocol(ch.driver_name).own_link(conn)
        key = f"{link_key(ch.driver_name, conn)}#{i}" if own else link_key(ch.driver_name, conn)
        groups.setdefault(key, []).append(ch)
    hb = cfg["loop"]["heartbeat"]
    try:
        loads = [
            link_load(
                chs[0].driver_name,
                chs[0].connection,
                len(chs),
                fs,
                heartbeat_hz=1.0 / hb if hb > 0 else 0.0,
            )
            for chs in groups.values()
        ]
        check_links(loads)
    except InputError as exc:
        raise InputError(f"{cfg.source}: {exc}") from None
    return loads


def _check_shared_links(cfg: Config, channels: list[ChannelPlan]) -> None:
    """Channels sharing a link must be told apart (CAN node ids, Modbus unit ids; one channel
    per serial line): each protocol checks its own channels (``Protocol.check_sharing``)."""
    from rths_hil.drivers.registry import protocol

    by_driver: dict[str, list[tuple[int, str, dict[str, Any], bool]]] = {}
    for i, ch in enumerate(channels):
        by_driver.setdefault(ch.driver_name, []).append(
            (i, ch.name, ch.connection, ch.twin_enabled)
        )
    for name, chs in by_driver.items():
        try:
            protocol(name).check_sharing(chs)
        except InputError as exc:
            raise InputError(f"{cfg.source}: {exc}") from None

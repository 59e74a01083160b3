"""Every rule that ties configuration keys together, checked once the configuration is read.

A single key's type, unit and range are checked as it is read (:mod:`.coerce`); the rules
here relate keys to each other (a shear building's masses and stiffnesses, a channel's DOF
and the structure, the FEI window and the loop rate, …).
"""

from __future__ import annotations

from ..errors import InputError
from .model import Config, resolve_channel
from .schema import CHANNEL_SECTIONS

__all__ = [
    "check_control_keys",
    "check_motion_keys",
    "check_window_samples",
    "cross_check",
    "cross_check_channel",
    "structure_dofs",
]


def cross_check(cfg: Config, note: str = "") -> None:
    """Check the rules that relate keys of a read configuration, and each channel's.

    Parameters
    ----------
    cfg : Config
        The configuration, every key already coerced (:func:`rths_hil.config.coerce`).
    note : str
        Appended to ``cfg.source`` in messages (`` (with --set overrides)``).

    Raises
    ------
    InputError
        The first rule broken, naming the source and the key path.
    """
    where = cfg.source + note
    cross_check_channel(cfg, where)
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
        load = e.get("control", {}).get("mode", cfg["control"]["mode"]) == "load"  # no DOF
        if (
            n_dof is not None
            and n_dof > 1
            and "dof" not in e
            and "transform" not in e
            and not (site or load)
        ):
            raise InputError(
                f"{path}: say where the actuator acts: dof = 1..{n_dof} or transform = [...]"
            )
        if any(section in e for section in CHANNEL_SECTIONS):
            cross_check_channel(resolve_channel(cfg, e).config, f"{path}")


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


def check_window_samples(window: float | str, window_s: float, fs: float, where: str) -> None:
    """Raise unless the FEI window ``window`` (``window_s`` seconds) holds at least 8 samples
    at ``fs``: fewer leave no bin between DC and Nyquist to estimate from."""
    if not window_s * fs >= 8:
        raise InputError(f"{where}: fei.window: {window!r} is fewer than 8 samples at {fs:g} Hz")


def cross_check_channel(cfg: Config, where: str) -> None:
    """The rules of one channel's sections (and the structure and loop they run with)."""
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
    check_window_samples(w, ws, lp["fs"], where)
    if c["adaptive"] and not cfg["fei"]["enabled"]:
        raise InputError(f"{where}: compensation.adaptive needs fei.enabled = true")
    check_motion_keys(cfg, where)
    check_control_keys(cfg, where)


def check_control_keys(cfg: Config, where: str) -> None:
    """A channel's control mode and its load: a load channel holds one load (a constant or a
    schedule) inside the force limit; only a load channel has one; a force channel needs the
    specimen stiffness its force targets are computed with (``docs/channels.md``)."""
    c = cfg["control"]
    mode, load, sched = c["mode"], c["load"], c["load_schedule"]
    if mode != "load":
        if load or sched:
            key = "load" if load else "load_schedule"
            raise InputError(
                f"{where}: control.{key}: only a control.mode = 'load' channel holds a load "
                f"(this channel is {mode}-controlled)"
            )
    else:
        if load and sched:
            raise InputError(
                f"{where}: control.load_schedule: give control.load or control.load_schedule, "
                "not both"
            )
        if not load and not sched:
            raise InputError(
                f"{where}: control.load: a control.mode = 'load' channel needs the force it "
                "holds: control.load (N) or control.load_schedule ([[t, N], …])"
            )
        lim = cfg["safety"]["force_limit"]
        peak = abs(load) if load else max(abs(v) for _, v in sched)
        if lim and not peak < lim:
            key = "load" if load else "load_schedule"
            raise InputError(
                f"{where}: control.{key}: {peak:.6g} N is not inside the force limit "
                f"±{lim:.6g} N (safety.force_limit)"
            )
    if mode == "force" and not cfg["structure"]["k_specimen"] > 0:
        raise InputError(
            f"{where}: structure.k_specimen: a control.mode = 'force' channel computes its force "
            "targets with the specimen's stiffness: give it (> 0 N/m)"
        )


def check_motion_keys(cfg: Config, where: str) -> None:
    """The keys of a run that name a position or a distance the actuator is driven to, against
    the channel's displacement limit, before anything moves.

    A rest position on or past the displacement limit would drive the actuator into its own
    trip at the end of a test (and leave it e-stopped, not handed back). The start position
    is where the actuator is, refused outside the limit when the run starts
    (:mod:`rths_hil.hybrid.phases`); the start and end
    ramps' speed (``start.velocity``) is capped at half the velocity limit by the loop itself
    (documented with the key), and ``rths-hil commission`` holds its own motion against the
    limits where the actuator is, so neither is refused here.
    """
    lim = cfg["safety"]["displacement_limit"]
    if not lim:
        return
    checks = []
    if cfg["end"]["rest"] == "position":
        checks.append(("end.rest_position", cfg["end"]["rest_position"]))
    for key, value in checks:
        if not abs(value) < lim:
            raise InputError(
                f"{where}: {key}: {value * 1e3:+.6g} mm is not inside the displacement limit "
                f"±{lim * 1e3:.6g} mm (safety.displacement_limit); the actuator would be driven "
                "into a trip"
            )

"""The DBC profile format (``protocol = "can"``, :mod:`rths_hil.drivers.profile`): each role a
signal of the lab's DBC, read through cantools. :func:`load_can` reads the ``dbc``, ``roles``,
``status``, ``actions`` and ``heartbeat`` keys; :func:`rths_hil.drivers.profile.load_profile` is
the entry, which finds this module by its package's name (the format is ``can``) and calls its
:func:`load`."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rths_hil.errors import InputError
from rths_hil.keys import REQUIRED, Key

from ..profile import (
    UNITS,
    UNITS_KEY,
    ProfileFormat,
    _check_mode_actions,
    _masks,
    _units,
    check_keys,
    check_mask_bits,
    read_actions,
    read_roles,
    top_keys,
)

__all__ = ["FILE_KEYS", "FORMAT", "SIGNAL_KEYS", "CANProfile", "CANSignal", "load", "load_can"]

#: The ``protocol`` of a profile of this format: how
#: :func:`rths_hil.drivers.registry.profile_formats` finds it (read without importing this
#: module, so a string literal), and :func:`load` reads it.
FORMAT = "can"

#: The top-level keys of a DBC profile.
FILE_KEYS = top_keys({"dbc": Key("str", REQUIRED, doc="the DBC file, relative to the profile")})
#: A role (or the heartbeat) on a DBC signal.
SIGNAL_KEYS = {
    "message": Key("str", REQUIRED, doc="the DBC message"),
    "signal": Key("str", REQUIRED, doc="the signal of the message"),
    "units": UNITS_KEY,
}
#: An action: the signal and the value written.
ACTION_SIGNAL_KEYS = {**SIGNAL_KEYS, "value": Key("float", 1.0, doc="the value written")}


# ------------------------------------------------------------------------------------------
# CAN with the lab's DBC
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CANSignal:
    """A role on a DBC signal: ``message``, ``signal`` and the SI factor of its unit."""

    role: str
    message: str
    signal: str
    factor: float
    value: float | None = None  # actions: the value written


@dataclass(frozen=True)
class CANProfile(ProfileFormat):
    """A validated CAN profile (see the module docstring)."""

    source: str
    dbc: str
    database: Any
    roles: dict[str, CANSignal]
    actions: dict[str, CANSignal]
    masks: dict[int, int]
    heartbeat: CANSignal | None
    protocol: str = FORMAT

    def _setpoint_span(self) -> tuple[float, float, str]:
        """The set-point signal's raw range (its bits and sign) through its scale and offset,
        within the DBC's minimum and maximum."""
        sp = self.roles["setpoint"]
        sig = self.command.get_signal_by_name(sp.signal)
        ends = [(r * sig.scale + sig.offset) * sp.factor for r in _raw_range(sig)]
        if sig.minimum is not None:
            ends[0] = max(min(ends), float(sig.minimum) * sp.factor)
        if sig.maximum is not None:
            ends[1] = min(max(ends), float(sig.maximum) * sp.factor)
        return min(ends), max(ends), f"the DBC signal {sp.message}.{sp.signal}"

    def _force_hint(self) -> str:
        """``roles.force_setpoint`` is a signal of the command message; as the set-point of
        every command frame, the displacement set-point signal keeps its DBC initial value."""
        return f"a signal of the command message {self.roles['setpoint'].message}"

    def _with_setpoint(self, fsp: CANSignal) -> CANProfile:
        return replace(self, roles={**self.roles, "setpoint": fsp})

    @property
    def command(self) -> Any:
        """The cantools message carrying the set-point."""
        return self.database.get_message_by_name(self.roles["setpoint"].message)

    @property
    def feedback(self) -> Any:
        """The cantools message carrying the measured values."""
        return self.database.get_message_by_name(self.roles["position"].message)


def _can_signal(
    src: str, table: Any, path: str, db: Any, dbc: str, action: bool = False
) -> CANSignal:
    """The role, heartbeat or action at ``path`` on its DBC signal (the SI factor of its
    unit: the profile's ``units``, else the DBC's)."""
    t = check_keys(src, table, ACTION_SIGNAL_KEYS if action else SIGNAL_KEYS, path)
    msg_name, sig_name = t["message"], t["signal"]

    def fail(key: str, why: str) -> InputError:
        return InputError(f"profile {src}: {path}.{key}: {why}")

    try:
        msg = db.get_message_by_name(msg_name)
    except KeyError:
        raise fail("message", f"the DBC {dbc} has no message {msg_name!r}") from None
    try:
        sig = msg.get_signal_by_name(sig_name)
    except KeyError:
        raise fail(
            "signal", f"the DBC {dbc} message {msg_name} has no signal {sig_name!r}"
        ) from None
    if sig.scale == 0:
        raise fail("signal", f"DBC signal {msg_name}.{sig_name} has scale 0")
    unit = str(sig.unit or "").strip()
    if t["units"] is None and unit not in UNITS:
        # the DBC names a unit the bridge cannot convert: taken as SI it could be off by any
        # factor (a "cm" signal read as metres is 100 times off)
        raise fail(
            "signal",
            f"the DBC {dbc} gives {msg_name}.{sig_name} the unit {unit!r}, which the bridge "
            f"does not convert (known: {', '.join(k for k in UNITS if k)}); give its units "
            "in the profile",
        )
    role = path.rpartition(".")[2]
    factor = _units(src, path, t["units"], unit, role=role)
    return CANSignal(role, msg_name, sig_name, factor, t.get("value"))


def load(source: str, data: dict[str, Any], base: Path) -> CANProfile:
    """The profile of this format at ``source`` (its TOML ``data``; ``base`` the folder the
    ``dbc`` is relative to): :func:`load_can`, as
    :func:`rths_hil.drivers.profile.load_profile` calls every format's ``load``."""
    return load_can(source, data, base)


def load_can(src: str, data: dict[str, Any], base: Path) -> CANProfile:
    """The DBC profile ``src`` (its TOML ``data``; ``dbc`` relative to ``base``)."""
    from .codec import load_dbc

    top = check_keys(src, data, FILE_KEYS, "")
    dbc_rel = top["dbc"]
    dbc = base / dbc_rel
    try:
        db = load_dbc(dbc)
    except InputError as exc:
        raise InputError(f"profile {src}: dbc: {exc}") from None
    roles = read_roles(src, top["roles"], lambda t, path: _can_signal(src, t, path, db, dbc_rel))
    fsp = roles.get("force_setpoint")
    if fsp is not None and fsp.message != roles["setpoint"].message:
        raise InputError(
            f"profile {src}: roles.force_setpoint: must be a signal of the command message "
            f"{roles['setpoint'].message} (roles.setpoint), got {fsp.message}"
        )
    if fsp is not None and fsp.signal == roles["setpoint"].signal:
        raise InputError(
            f"profile {src}: roles.force_setpoint: {fsp.message}.{fsp.signal} is the "
            "displacement set-point's signal (roles.setpoint)"
        )
    fb = roles["position"].message
    for x in ("force", "status"):
        if roles[x].message != fb:
            raise InputError(
                f"profile {src}: roles.{x}: must be in the feedback message {fb} "
                f"(roles.position), got {roles[x].message}"
            )
    if roles["setpoint"].message == fb:
        raise InputError(f"profile {src}: roles.setpoint: the command and feedback share {fb}")
    actions = read_actions(
        src, top["actions"], lambda t, path: _can_signal(src, t, path, db, dbc_rel, action=True)
    )
    for a, s in actions.items():
        if a != "estop" and s.message != roles["setpoint"].message:
            raise InputError(
                f"profile {src}: actions.{a}: must be a signal of the command message "
                f"{roles['setpoint'].message}"
            )
    if actions["estop"].message in (roles["setpoint"].message, fb):
        raise InputError(f"profile {src}: actions.estop: needs a message of its own")
    _check_mode_actions(src, actions, roles, lambda a: (a.message, a.signal, a.value))
    hb = None
    if top["heartbeat"] is not None:
        hb = _can_signal(src, top["heartbeat"], "heartbeat", db, dbc_rel)
        if hb.message in (actions["estop"].message, fb):
            what = "the e-stop's" if hb.message == actions["estop"].message else "the feedback"
            raise InputError(
                f"profile {src}: heartbeat.message: {hb.message} is {what} message: every "
                "heartbeat would be sent as one; give the heartbeat a message of its own"
            )
    masks = _masks(src, top["status"])
    _check_can_fields(src, db, roles, actions, masks, hb)
    return CANProfile(src, str(dbc), db, roles, actions, masks, hb)


def _raw_range(sig: Any) -> tuple[int, int]:
    """The raw integers a DBC signal carries (its bit length and sign)."""
    n = int(sig.length)
    return (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if sig.is_signed else (0, 2**n - 1)


def _check_can_fields(
    src: str,
    db: Any,
    roles: dict[str, CANSignal],
    actions: dict[str, CANSignal],
    masks: dict[int, int],
    hb: CANSignal | None,
) -> None:
    """Values that must fit their DBC signals: the status masks in the status signal, each
    action's value in its signal, a heartbeat counter of more than one bit."""

    def signal(s: CANSignal) -> Any:
        return db.get_message_by_name(s.message).get_signal_by_name(s.signal)

    st = roles["status"]
    what = f"the DBC signal {st.message}.{st.signal} ({signal(st).length} bits)"
    check_mask_bits(src, masks, max(_raw_range(signal(st))[1], 0), what)
    for name, a in actions.items():
        sig = signal(a)
        lo, hi = _raw_range(sig)
        raw = ((a.value or 0.0) - sig.offset) / sig.scale
        if not lo <= raw <= hi:
            raise InputError(
                f"profile {src}: actions.{name}.value: {a.value:g} does not fit the DBC signal "
                f"{a.message}.{a.signal} ({sig.length} bits, "
                f"{lo * sig.scale + sig.offset:g}…{hi * sig.scale + sig.offset:g})"
            )
    if hb is not None and int(signal(hb).length) < 2:
        raise InputError(
            f"profile {src}: heartbeat: the DBC signal {hb.message}.{hb.signal} has 1 bit; a "
            "counter the controller sees change needs more"
        )

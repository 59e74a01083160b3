"""The DBC profile format (``protocol = "can"``, :mod:`rths_hil.drivers.profile`): each role a
signal of the lab's DBC, read through cantools. :func:`load_can` reads the ``dbc``, ``roles``,
``status``, ``actions`` and ``heartbeat`` keys; :func:`rths_hil.drivers.profile.load_profile` is
the entry."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rths_hil.errors import InputError

from ..profile import (
    ACTIONS,
    CONTROL_MODES,
    OPTIONAL_ROLES,
    ROLES,
    STATUS_BITS,
    UNITS,
    _check_force_loop,
    _check_mode_actions,
    _masks,
    _no_force_role,
    _range_refusal,
    _Reader,
    _units,
)

__all__ = ["CANProfile", "CANSignal", "load_can"]


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
class CANProfile:
    """A validated CAN profile (see the module docstring)."""

    source: str
    dbc: str
    database: Any
    roles: dict[str, CANSignal]
    actions: dict[str, CANSignal]
    masks: dict[int, int]
    heartbeat: CANSignal | None
    protocol: str = "can"

    def check_setpoint_range(self, limit: float) -> None:
        """Refuse a set-point signal that cannot carry every command within ±``limit`` m
        (``safety.displacement_limit``; 0 = off): one line, before anything moves.

        On the profile of a force-controlled channel (:meth:`for_control`) the set-point is
        the force set-point signal and ``limit`` the force limit in N (``safety.force_limit``).
        """
        sp = self.roles["setpoint"]
        if limit <= 0:
            return
        sig = self.command.get_signal_by_name(sp.signal)
        n = int(sig.length)
        raw = (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if sig.is_signed else (0, 2**n - 1)
        ends = [(r * sig.scale + sig.offset) * sp.factor for r in raw]
        if sig.minimum is not None:
            ends[0] = max(min(ends), float(sig.minimum) * sp.factor)
        if sig.maximum is not None:
            ends[1] = min(max(ends), float(sig.maximum) * sp.factor)
        lo, hi = min(ends), max(ends)
        if lo > -limit or hi < limit:
            what = f"the DBC signal {sp.message}.{sp.signal}"
            raise InputError(_range_refusal(self.source, sp.role, what, lo, hi, limit))

    @property
    def control_modes(self) -> tuple[str, ...]:
        """The wire control modes the profile can run: ``displacement``, and ``force`` when
        it maps ``roles.force_setpoint``."""
        return CONTROL_MODES if "force_setpoint" in self.roles else CONTROL_MODES[:1]

    def for_control(self, mode: str) -> CANProfile:
        """The profile as a channel in wire mode ``mode`` uses it.

        ``"displacement"``: this profile. ``"force"``: ``roles.force_setpoint`` (a signal of
        the command message, its value in N) as the set-point of every command frame; the
        displacement set-point signal keeps its DBC initial value.

        Raises
        ------
        InputError
            ``"force"`` and the profile has no ``roles.force_setpoint`` (one line).
        """
        if mode != "force":
            return self
        fsp = self.roles.get("force_setpoint")
        if fsp is None:
            raise _no_force_role(
                self.source, f"a signal of the command message {self.roles['setpoint'].message}"
            )
        _check_force_loop(self.source, self.actions)
        return replace(self, roles={**self.roles, "setpoint": fsp})

    @property
    def command(self) -> Any:
        """The cantools message carrying the set-point."""
        return self.database.get_message_by_name(self.roles["setpoint"].message)

    @property
    def feedback(self) -> Any:
        """The cantools message carrying the measured values."""
        return self.database.get_message_by_name(self.roles["position"].message)


def _can_signal(r: _Reader, name: str, db: Any, dbc: str, action: bool = False) -> CANSignal:
    t = r.table(name, required=True)
    assert t is not None
    t.unknown(("message", "signal", "units", "value") if action else ("message", "signal", "units"))
    msg_name = t.str("message")
    sig_name = t.str("signal")
    try:
        msg = db.get_message_by_name(msg_name)
    except KeyError:
        raise t.fail("message", f"the DBC {dbc} has no message {msg_name!r}") from None
    try:
        sig = msg.get_signal_by_name(sig_name)
    except KeyError:
        raise t.fail(
            "signal", f"the DBC {dbc} message {msg_name} has no signal {sig_name!r}"
        ) from None
    if sig.scale == 0:
        raise t.fail("signal", f"DBC signal {msg_name}.{sig_name} has scale 0")
    unit = str(sig.unit or "").strip()
    if "units" not in t.data and unit not in UNITS:
        # the DBC names a unit the bridge cannot convert: taken as SI it could be off by any
        # factor (a "cm" signal read as metres is 100 times off)
        raise t.fail(
            "signal",
            f"the DBC {dbc} gives {msg_name}.{sig_name} the unit {unit!r}, which the bridge "
            f"does not convert (known: {', '.join(k for k in UNITS if k)}); give its units "
            "in the profile",
        )
    factor = _units(t, unit, role=name)
    value = t.float("value", 1.0) if action else None
    return CANSignal(name, msg_name, sig_name, factor, value)


def load_can(r: _Reader, base: Path) -> CANProfile:
    from .codec import load_dbc

    src = r.source
    dbc_rel = r.str("dbc")
    dbc = base / dbc_rel
    try:
        db = load_dbc(dbc)
    except InputError as exc:
        raise InputError(f"profile {src}: dbc: {exc}") from None
    roles_t = r.table("roles", required=True)
    assert roles_t is not None
    roles_t.unknown(ROLES + OPTIONAL_ROLES)
    missing = [x for x in ROLES if x not in roles_t.data]
    if missing:
        raise InputError(
            f"profile {src}: roles.{missing[0]} is missing (the bridge needs {', '.join(ROLES)})"
        )
    roles = {
        x: _can_signal(roles_t, x, db, dbc_rel) for x in ROLES + OPTIONAL_ROLES if x in roles_t.data
    }
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
    acts = r.table("actions", required=True)
    assert acts is not None
    acts.unknown(ACTIONS)
    if "estop" not in acts.data:
        raise InputError(f"profile {src}: actions.estop is missing (every driver can e-stop)")
    actions = {a: _can_signal(acts, a, db, dbc_rel, action=True) for a in ACTIONS if a in acts.data}
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
    if r.table("heartbeat") is not None:
        hb = _can_signal(r, "heartbeat", db, dbc_rel)
        if hb.message in (actions["estop"].message, fb):
            what = "the e-stop's" if hb.message == actions["estop"].message else "the feedback"
            raise InputError(
                f"profile {src}: heartbeat.message: {hb.message} is {what} message: every "
                "heartbeat would be sent as one; give the heartbeat a message of its own"
            )
    masks = _masks(r)
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
    lo, hi = _raw_range(signal(st))
    names = {flag: name for name, flag in STATUS_BITS.items()}
    for flag, mask in masks.items():
        if mask > max(hi, 0):
            raise InputError(
                f"profile {src}: status.{names[flag]}: 0x{mask:X} is not a bit of the DBC "
                f"signal {st.message}.{st.signal} ({signal(st).length} bits)"
            )
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

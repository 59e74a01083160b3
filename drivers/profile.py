"""Controller profiles: a lab's own register map or DBC, declared in a TOML file, not in code.

A profile maps the bridge's **roles** onto the controller's protocol:

========================  ===============================================================
role                      meaning
========================  ===============================================================
``roles.setpoint``        commanded actuator displacement (written every step)
``roles.force_setpoint``  commanded force (optional): written every step instead of the
                          set-point on a force-controlled channel (``control = "force"``
                          or ``"load"``); a profile without it refuses such a channel
``roles.position``        measured actuator displacement (read every step)
``roles.force``           measured specimen force (read every step)
``roles.status``          the controller's status word; ``[status]`` gives the bit masks
                          ``enabled``, ``estop``, ``fault``, ``watchdog`` and
                          ``sensor_invalid`` (the sample's measurement is not valid: the
                          driver delivers its displacement as NaN)
``actions.estop``         what latches the controller's e-stop (required)
``actions.enable``,       what enables / disables (holds) the controller; written when the
``actions.disable``       bridge's enable flag changes
``actions.acknowledge``   what acknowledges a latched e-stop (written with ``disable``)
``heartbeat``             a counter the bridge writes at ``loop.heartbeat``
========================  ===============================================================

Optional ``actions.force_mode`` and ``actions.displacement_mode`` select the controller's loop
for a controller that closes its force or displacement loop on command (not by which set-point
is written): Modbus writes the one of the channel's wire mode while disabled at arming, CAN
carries it in every command frame; ``force_mode`` needs ``roles.force_setpoint``.

``protocol = "modbus"`` (Modbus TCP): each role is a *point* — ``table`` (``holding``,
``input``, ``coil``, ``discrete``), ``address`` (0-based PDU address), ``type`` (``int16``,
``uint16``, ``int32``, ``uint32``, ``float32``, ``float64``; ``bool`` for coils and discrete
inputs), ``word_order`` and ``byte_order`` (``big`` or ``little``, defaults from
``[modbus]``), ``scale`` and ``offset`` (value in ``units`` = raw · scale + offset) and
``units`` (``m``, ``mm``, ``um``, ``in``, ``N``, ``kN``, ``lbf``; SI when omitted). Registers
are converted by pymodbus (``convert_to_registers`` / ``convert_from_registers``); a
``byte_order = "little"`` swaps the two bytes of each register. The Modbus profile driver and
twin precompile these conversions into ``struct`` layouts checked against pymodbus when they
open (:mod:`.modbus.layout`). Actions are a ``table``
(``coil`` or ``holding``), an ``address`` and the ``value`` written. ``[modbus] unit`` is the
unit id; ``[modbus] pipeline`` (default true) sends a step's Modbus TCP requests in one socket
write, their responses matched by transaction id (false: one request at a time; RTU is always
one at a time).

``protocol = "can"``: ``dbc`` (path, relative to the profile) and, for each role, the DBC
``message`` and ``signal``; byte order (Intel or Motorola), sign, scale and offset come from
the DBC through cantools; ``units`` as above, else the DBC signal's unit. Actions are a
``message``, a ``signal`` and a ``value`` (an action in the set-point message is a signal of
every command; one in another message is a frame of its own). The controller echoes no
sequence number: the first feedback frame received after a command answers it (its age is
recorded). Extended (29-bit) identifiers are taken from the DBC.

The profile is validated when loaded: one line naming the file and the key, exit 2
(:class:`~rths_hil.errors.InputError`): unknown type, table or unit, overlapping or
out-of-range registers, a missing role, scale 0, a DBC without the named message or signal.
``driver.profile = "rths-hil"`` (the default) is the built-in protocol of each driver.

This module holds what both formats share (the roles, units, status masks, the reader of the
file's tables) and :func:`load_profile`; each protocol's package holds its format:
:mod:`rths_hil.drivers.modbus.profile_format` (``ModbusProfile``, a register map) and
:mod:`rths_hil.drivers.can.profile_format` (``CANProfile``, a DBC profile).
"""

from __future__ import annotations

import builtins
import math
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rths_hil.errors import InputError
from rths_hil.formats import read_toml

from .base import Status

if TYPE_CHECKING:
    from collections.abc import Callable

    from .can.profile_format import CANProfile
    from .modbus.profile_format import ModbusProfile

__all__ = [
    "BUILTIN_PROFILE",
    "is_builtin",
    "load_profile",
    "status_from_word",
    "word_from_status",
]

#: The name of the built-in profile: each driver's own protocol.
BUILTIN_PROFILE = "rths-hil"

#: Unit name → SI factor (value in the unit × factor = SI).
UNITS: dict[str, float] = {
    "": 1.0,
    "-": 1.0,
    "m": 1.0,
    "cm": 1e-2,
    "mm": 1e-3,
    "um": 1e-6,
    "µm": 1e-6,
    "in": 0.0254,
    "N": 1.0,
    "kN": 1e3,
    "lbf": 4.4482216152605,
}
READ_ROLES = ("position", "force", "status")
ROLES = ("setpoint", *READ_ROLES)
#: Roles a profile may map: the force set-point of a force-controlled channel.
OPTIONAL_ROLES = ("force_setpoint",)
#: The wire control modes (:meth:`rths_hil.drivers.base.Driver.set_control`).
CONTROL_MODES = ("displacement", "force")
ACTIONS = ("enable", "disable", "estop", "acknowledge", "force_mode", "displacement_mode")
#: The actions that select the controller's loop, by wire mode.
MODE_ACTIONS = {"force": "force_mode", "displacement": "displacement_mode"}
STATUS_BITS: dict[str, int] = {
    "enabled": int(Status.ENABLED),
    "estop": int(Status.ESTOP_ACTIVE),
    "fault": int(Status.FAULT),
    "watchdog": int(Status.WATCHDOG),
    "sensor_invalid": int(Status.SENSOR_INVALID),
}


def is_builtin(profile: str | None) -> bool:
    """True for no profile or the built-in ``rths-hil`` one."""
    return profile is None or str(profile) in ("", BUILTIN_PROFILE)


class _Reader:
    """Typed access to one TOML table, with errors naming the file and the key."""

    def __init__(self, source: str, data: dict[str, Any], where: str = "") -> None:
        self.source, self.data, self.where = source, data, where

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def fail(self, name: str, why: str) -> InputError:
        return InputError(f"profile {self.source}: {self.key(name)}: {why}")

    def table(self, name: str, required: bool = False) -> _Reader | None:
        v = self.data.get(name)
        if v is None:
            if required:
                raise InputError(f"profile {self.source}: {self.key(name)} is missing")
            return None
        if not isinstance(v, dict):
            raise self.fail(name, "must be a table")
        return _Reader(self.source, v, self.key(name))

    def str(self, name: str, default: str | None = None, choices: Any = None) -> str:
        v = self.data.get(name, default)
        if v is None:
            raise InputError(f"profile {self.source}: {self.key(name)} is missing")
        if not isinstance(v, str):
            raise self.fail(name, f"must be a string, got {v!r}")
        if choices is not None and v not in choices:
            raise self.fail(name, f"unknown value {v!r} (known: {', '.join(choices)})")
        return v

    def int(
        self,
        name: builtins.str,
        default: builtins.int | None = None,
        lo: builtins.int = 0,
        hi: builtins.int = 65535,
    ) -> builtins.int:
        v = self.data.get(name, default)
        if v is None:
            raise InputError(f"profile {self.source}: {self.key(name)} is missing")
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(name, f"must be an integer, got {v!r}")
        if not lo <= v <= hi:
            raise self.fail(name, f"{v} is out of range {lo}..{hi}")
        return v

    def float(self, name: builtins.str, default: builtins.float) -> builtins.float:
        v = self.data.get(name, default)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self.fail(name, f"must be a finite number, got {v!r}")
        return float(v)

    def unknown(self, known: tuple[builtins.str, ...]) -> None:
        extra = sorted(set(self.data) - set(known))
        if extra:
            raise self.fail(extra[0], f"unknown key (known: {', '.join(known)})")


#: What each unit measures; a role takes only its own kind.
_UNIT_KIND = {"m": "length", "cm": "length", "mm": "length", "um": "length", "µm": "length"}
_UNIT_KIND["in"] = "length"
_UNIT_KIND.update({"N": "force", "kN": "force", "lbf": "force"})
_ROLE_KIND = {
    "setpoint": "length",
    "position": "length",
    "force": "force",
    "force_setpoint": "force",
}


def _units(r: _Reader, default: str = "", role: str = "") -> float:
    u = r.str("units", default)
    if u not in UNITS:
        raise r.fail("units", f"unknown unit {u!r} (known: {', '.join(k for k in UNITS if k)})")
    want, kind = _ROLE_KIND.get(role), _UNIT_KIND.get(u)
    if want is not None and kind is not None and kind != want:
        raise r.fail("units", f"{u!r} is a {kind} unit; the {role} is a {want}")
    return UNITS[u]


def _masks(r: _Reader) -> dict[int, int]:
    """``[status]``: flag → mask (a bit of the status word that sets the flag)."""
    st = r.table("status", required=True)
    assert st is not None
    st.unknown(tuple(STATUS_BITS))
    out: dict[int, int] = {}
    for name, flag in STATUS_BITS.items():
        if name in st.data:
            mask = st.int(name, lo=1, hi=2**32 - 1)
            out[flag] = mask
    for need in ("enabled", "estop"):
        if need not in st.data:
            raise InputError(f"profile {r.source}: status.{need} (bit mask) is missing")
    enabled = out[int(Status.ENABLED)]
    for name, flag in STATUS_BITS.items():
        if name != "enabled" and flag in out and out[flag] & enabled:
            raise st.fail(
                name,
                f"0x{out[flag]:X} shares bits with status.enabled (0x{enabled:X}): the "
                "controller could never be enabled without reporting it",
            )
    return out


def _range_refusal(source: str, role: str, what: str, lo: float, hi: float, limit: float) -> str:
    """The one line refusing a set-point field that cannot carry ±``limit`` (SI)."""
    if role == "force_setpoint":
        return (
            f"profile {source}: roles.force_setpoint: {what} carries {lo * 1e-3:g}…"
            f"{hi * 1e-3:g} kN, not the force limit ±{limit * 1e-3:g} kN (safety.force_limit)"
        )
    return (
        f"profile {source}: roles.setpoint: {what} carries {lo * 1e3:g}…{hi * 1e3:g} mm, not "
        f"the displacement limit ±{limit * 1e3:g} mm (safety.displacement_limit)"
    )


def _no_force_role(source: str, how: str) -> InputError:
    return InputError(
        f"profile {source}: roles.force_setpoint is missing: a force-controlled channel "
        f'(control = "force" or "load") writes its force set-point there ({how})'
    )


def status_from_word(word: int, masks: dict[int, int]) -> int:
    """The bridge's :class:`Status` flags from a controller status word."""
    s = 0
    for flag, mask in masks.items():
        if word & mask:
            s |= flag
    return s


def word_from_status(status: int, masks: dict[int, int]) -> int:
    """The controller status word for the bridge's :class:`Status` flags (twins)."""
    w = 0
    for flag, mask in masks.items():
        if status & flag:
            w |= mask
    return w


def _check_force_loop(source: str, actions: dict[str, Any]) -> None:
    """A controller that selects its loop on command (``actions.displacement_mode``) runs a
    force channel only with the action that selects its force loop."""
    if "displacement_mode" in actions and "force_mode" not in actions:
        raise InputError(
            f"profile {source}: actions.force_mode is missing: the controller selects its loop "
            "on command (actions.displacement_mode) and a force-controlled channel needs its "
            "force loop selected"
        )


def _check_mode_actions(
    src: str,
    actions: dict[str, Any],
    roles: dict[str, Any],
    write: Callable[[Any], tuple[Any, ...]],
) -> None:
    """``actions.force_mode`` only with a force set-point to follow, and not the same write as
    ``actions.displacement_mode`` (the controller could not tell the loops apart); ``write``
    gives what an action of the format writes, where and which value."""
    if "force_mode" in actions and "force_setpoint" not in roles:
        raise InputError(
            f"profile {src}: actions.force_mode: selects a force loop, but the profile maps no "
            "roles.force_setpoint to command it"
        )
    f, d = actions.get("force_mode"), actions.get("displacement_mode")
    if f is not None and d is not None:
        if write(f) == write(d):
            raise InputError(
                f"profile {src}: actions.displacement_mode: the same write as "
                "actions.force_mode: the controller could not tell the loops apart"
            )


@cache
def _load_cached(path: str) -> ModbusProfile | CANProfile:
    p = Path(path)
    data = read_toml(p, "profile", f"profile {p}")
    r = _Reader(str(p), data)
    protocol = r.str("protocol", choices=("modbus", "can"))
    if protocol == "modbus":
        from .modbus.profile_format import load_modbus

        r.unknown(("protocol", "name", "modbus", "roles", "status", "actions", "heartbeat"))
        return load_modbus(r)
    from .can.profile_format import load_can

    r.unknown(("protocol", "name", "dbc", "roles", "status", "actions", "heartbeat"))
    return load_can(r, p.parent)


def load_profile(path: str | Path) -> ModbusProfile | CANProfile:
    """Load and validate the profile file ``path`` (cached by absolute path).

    Raises
    ------
    InputError
        One line naming the file and the key (module docstring).
    """
    try:
        absolute = Path(path).expanduser().resolve()
    except (RuntimeError, OSError) as exc:  # a symlink loop (RuntimeError before Python 3.13)
        raise InputError(f"profile {path}: cannot be resolved: {exc}") from None
    return _load_cached(str(absolute))

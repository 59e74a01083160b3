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

Every table's keys are declared as :class:`~rths_hil.config.Key` tables next to the format that
reads them and checked by :func:`rths_hil.config.check_table`, the validator of the run
configuration. This module holds what both formats share (the roles, units, status masks, the
keys of the role, action and status tables) and :func:`load_profile`; each protocol's package
holds its format, in its ``profile_format`` module:
:mod:`rths_hil.drivers.modbus.profile_format` (``ModbusProfile``, a register map) and
:mod:`rths_hil.drivers.can.profile_format` (``CANProfile``, a DBC profile). This module names
no format: such a module reads the profiles whose ``protocol`` is its package's name (the
``can`` package's, ``protocol = "can"``) with its ``load(source, data, base)``, and
:func:`rths_hil.drivers.registry.profile_formats` finds them
(a protocol package added with a ``profile_format`` module adds its format to the
``protocol`` choices; nothing is listed here).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any, ClassVar, Self, TypeVar

from rths_hil.config.coerce import check_table
from rths_hil.errors import InputError
from rths_hil.formats import read_toml
from rths_hil.keys import REQUIRED, Key

from .base import Status

__all__ = [
    "BUILTIN_PROFILE",
    "ProfileFormat",
    "is_builtin",
    "load_profile",
    "protocol_key",
    "status_from_word",
    "word_from_status",
]

T = TypeVar("T")

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


def where(source: str) -> str:
    """The start of every message about the profile file ``source``."""
    return f"profile {source}"


def check_keys(
    source: str, table: Any, keys: Mapping[str, Key], path: str, missing: str = "missing"
) -> dict[str, Any]:
    """A table of the profile ``source`` at ``path`` checked against its declared ``keys``
    (:func:`rths_hil.config.check_table`): the values, defaults filled."""
    return check_table(table, keys, where(source), path, missing=missing)


def top_keys(own: Mapping[str, Key]) -> dict[str, Key]:
    """The top-level keys of a profile format: ``protocol``, ``name``, the format's ``own``,
    the role, status, action and heartbeat tables."""
    return {
        "protocol": protocol_key(),
        "name": Key("str", "", doc="the controller's name (free text)"),
        **own,
        "roles": Key("table", REQUIRED, doc="role → where its value is on the wire"),
        "status": Key("table", REQUIRED, doc="status flag → bit mask of the status word"),
        "actions": Key("table", REQUIRED, doc="action → the write that performs it"),
        "heartbeat": Key("table", None, doc="a counter the bridge writes at loop.heartbeat"),
    }


def protocol_key() -> Key:
    """``protocol``: which format the file is, one of the formats the protocol packages declare
    (:func:`rths_hil.drivers.registry.profile_formats`)."""
    from .registry import profile_formats

    return Key("choice", REQUIRED, choices=tuple(profile_formats()), doc="the profile's format")


#: ``units`` of a role: the unit of its value on the wire (a key of :data:`UNITS`).
UNITS_KEY = Key("str", None, doc="unit of the value on the wire (SI when omitted)")
#: ``[roles]``: the required roles and the optional force set-point, each a table.
ROLE_KEYS = {
    **{r: Key("table", REQUIRED) for r in ROLES},
    **{r: Key("table", None) for r in OPTIONAL_ROLES},
}
#: The roles a message names when one is missing.
ROLES_MISSING = f"missing (the bridge needs {', '.join(ROLES)})"
#: ``[actions]``: the e-stop is required (every driver can e-stop).
ACTION_KEYS = {a: Key("table", REQUIRED if a == "estop" else None) for a in ACTIONS}
#: ``[status]``: flag → bit mask; ``enabled`` and ``estop`` required.
STATUS_KEYS = {
    name: Key("int", REQUIRED if name in ("enabled", "estop") else None, lo=1, hi=2**32 - 1)
    for name in STATUS_BITS
}


def read_roles(source: str, table: Any, read: Callable[[Any, str], T]) -> dict[str, T]:
    """``[roles]``: each role mapped, in :data:`ROLE_KEYS` order, read by ``read(its table,
    its key path)``; every role the bridge needs must be there."""
    given = check_keys(source, table, ROLE_KEYS, "roles", ROLES_MISSING)
    return {r: read(given[r], f"roles.{r}") for r in ROLE_KEYS if given[r] is not None}


def read_actions(source: str, table: Any, read: Callable[[Any, str], T]) -> dict[str, T]:
    """``[actions]``: each action given, in :data:`ACTIONS` order, read by ``read(its table,
    its key path)``; the e-stop must be there."""
    given = check_keys(source, table, ACTION_KEYS, "actions", "missing (every driver can e-stop)")
    return {a: read(given[a], f"actions.{a}") for a in ACTION_KEYS if given[a] is not None}


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


def _units(source: str, path: str, given: str | None, default: str = "", role: str = "") -> float:
    """The SI factor of the ``units`` at ``path`` (``given``, else ``default``); a role takes
    only a unit of its own kind."""
    u = default if given is None else given
    if u not in UNITS:
        raise InputError(
            f"{where(source)}: {path}.units: unknown unit {u!r} "
            f"(known: {', '.join(k for k in UNITS if k)})"
        )
    want, kind = _ROLE_KIND.get(role), _UNIT_KIND.get(u)
    if want is not None and kind is not None and kind != want:
        raise InputError(
            f"{where(source)}: {path}.units: {u!r} is a {kind} unit; the {role} is a {want}"
        )
    return UNITS[u]


def _masks(source: str, status: Any) -> dict[int, int]:
    """``[status]``: flag → mask (a bit of the status word that sets the flag)."""
    given = check_keys(source, status, STATUS_KEYS, "status", "missing (a bit mask)")
    out = {STATUS_BITS[n]: m for n, m in given.items() if m is not None}
    enabled = out[int(Status.ENABLED)]
    for name, flag in STATUS_BITS.items():
        if name != "enabled" and flag in out and out[flag] & enabled:
            raise InputError(
                f"{where(source)}: status.{name}: 0x{out[flag]:X} shares bits with "
                f"status.enabled (0x{enabled:X}): the controller could never be enabled "
                "without reporting it"
            )
    return out


def check_mask_bits(source: str, masks: dict[int, int], top: int, what: str) -> None:
    """Every status mask a bit of the status field: none above ``top`` (``what`` names the
    field)."""
    for name, flag in STATUS_BITS.items():
        mask = masks.get(flag, 0)
        if mask > top:
            raise InputError(f"{where(source)}: status.{name}: 0x{mask:X} is not a bit of {what}")


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


class ProfileFormat:
    """What the two profile formats share: the wire control modes a profile can run and the
    profile a force-controlled channel uses.

    A format is a frozen dataclass with ``source``, ``actions`` and its role map, the field
    :attr:`ROLE_FIELD` (role → where its value is on the wire); it says what its force
    set-point would be (:meth:`_force_hint`) and how it writes one (:meth:`_with_setpoint`).
    """

    #: The field holding the role map.
    ROLE_FIELD: ClassVar[str] = "roles"
    #: The format's name, the profile's ``protocol`` (its module's ``FORMAT``).
    protocol: str
    source: str
    actions: dict[str, Any]

    def _roles(self) -> dict[str, Any]:
        roles: dict[str, Any] = getattr(self, self.ROLE_FIELD)
        return roles

    def _force_hint(self) -> str:
        raise NotImplementedError

    def _with_setpoint(self, fsp: Any) -> Self:
        raise NotImplementedError

    def _setpoint_span(self) -> tuple[float, float, str] | None:
        """The lowest and highest SI value the set-point field carries and what the field is
        (a message names it); ``None`` when it carries any."""
        raise NotImplementedError

    def check_setpoint_range(self, limit: float) -> None:
        """Refuse a set-point field that cannot carry every command within ±``limit`` m
        (``safety.displacement_limit``; 0 = off): one line, before anything moves.

        On the profile of a force-controlled channel (:meth:`for_control`) the set-point is
        the force set-point and ``limit`` the force limit in N (``safety.force_limit``).

        Raises
        ------
        InputError
            The field's range does not reach ±``limit``.
        """
        span = self._setpoint_span() if limit > 0 else None
        if span is not None and (span[0] > -limit or span[1] < limit):
            role = self._roles()["setpoint"].role
            raise InputError(_range_refusal(self.source, role, span[2], *span[:2], limit))

    @property
    def control_modes(self) -> tuple[str, ...]:
        """The wire control modes the profile can run: ``displacement``, and ``force`` when
        it maps ``roles.force_setpoint``."""
        return CONTROL_MODES if "force_setpoint" in self._roles() else CONTROL_MODES[:1]

    def for_control(self, mode: str) -> Self:
        """The profile as a channel in wire mode ``mode`` uses it.

        ``"displacement"``: this profile. ``"force"``: the profile with
        ``roles.force_setpoint`` as the set-point written every step (its value in N).

        Raises
        ------
        InputError
            ``"force"`` and the profile has no ``roles.force_setpoint``, or its controller
            selects its loop on command without an action for the force loop (one line).
        """
        if mode != "force":
            return self
        fsp = self._roles().get("force_setpoint")
        if fsp is None:
            raise _no_force_role(self.source, self._force_hint())
        _check_force_loop(self.source, self.actions)
        return self._with_setpoint(fsp)


def _move_bits(bits: int, pairs: Iterable[tuple[int, int]]) -> int:
    """The bits ``to`` of each pair ``(from, to)`` whose ``from`` bits ``bits`` has."""
    out = 0
    for have, give in pairs:
        if bits & have:
            out |= give
    return out


def status_from_word(word: int, masks: dict[int, int]) -> int:
    """The bridge's :class:`Status` flags from a controller status word."""
    return _move_bits(word, ((mask, flag) for flag, mask in masks.items()))


def word_from_status(status: int, masks: dict[int, int]) -> int:
    """The controller status word for the bridge's :class:`Status` flags (twins)."""
    return _move_bits(status, masks.items())


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
def _load_cached(path: str) -> ProfileFormat:
    from rths_hil.plugins import load_target

    from .registry import profile_formats

    p = Path(path)
    data = read_toml(p, "profile", f"profile {p}")
    protocol = data.get("protocol")
    formats = profile_formats()
    target = formats.get(protocol) if isinstance(protocol, str) else None
    if target is None:
        given = {"protocol": protocol} if "protocol" in data else {}
        # says what is wrong with it, in one line naming the formats
        missing = f"missing, one of {', '.join(formats)}"
        check_keys(str(p), given, {"protocol": protocol_key()}, "", missing)
        raise AssertionError(protocol)  # pragma: no cover
    load = load_target(target, None, f"profile format {protocol!r}")
    prof: ProfileFormat = load(str(p), data, p.parent)
    return prof


def load_profile(path: str | Path) -> ProfileFormat:
    """Load and validate the profile file ``path`` (cached by absolute path).

    The file's ``protocol`` picks the format (:func:`rths_hil.drivers.registry.profile_formats`)
    whose ``load`` reads it.

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

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
open (:mod:`.modbus_layout`). Actions are a ``table``
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
"""

from __future__ import annotations

import builtins
import math
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import Any

from pymodbus.client.mixin import ModbusClientMixin

from rths_hil.errors import InputError
from rths_hil.formats import read_toml

from .base import Status

__all__ = [
    "BUILTIN_PROFILE",
    "CANProfile",
    "CANSignal",
    "ModbusAction",
    "ModbusPoint",
    "ModbusProfile",
    "is_builtin",
    "load_profile",
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
#: Modbus register types → registers per value.
REG_TYPES: dict[str, int] = {
    "int16": 1,
    "uint16": 1,
    "int32": 2,
    "uint32": 2,
    "float32": 2,
    "float64": 4,
}
#: Modbus tables: name → (readable by FC, writable).
TABLES: dict[str, tuple[int, bool]] = {
    "holding": (3, True),
    "input": (4, False),
    "coil": (1, True),
    "discrete": (2, False),
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
_DT: type[ModbusClientMixin.DATATYPE] = ModbusClientMixin.DATATYPE  # a variable, not an alias
_INT_RANGE = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
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


def _check_masks(source: str, masks: dict[int, int], point: ModbusPoint) -> None:
    """Every status mask must be a bit the status point can carry."""
    if point.type in ("float32", "float64"):
        raise InputError(
            f"profile {source}: roles.status: a {point.type} carries no status bits (use an "
            "integer type, or a coil or discrete input)"
        )
    top = {"bool": 0x1, "int16": 0x7FFF, "uint16": 0xFFFF, "int32": 0x7FFFFFFF}
    hi = top.get(point.type, 0xFFFFFFFF)
    names = {flag: name for name, flag in STATUS_BITS.items()}
    for flag, mask in masks.items():
        if mask > hi:
            raise InputError(
                f"profile {source}: status.{names[flag]}: 0x{mask:X} is not a bit of the "
                f"{point.table} {point.type} status point (bits up to 0x{hi:X})"
            )


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


# ------------------------------------------------------------------------------------------
# Modbus
# ------------------------------------------------------------------------------------------
#: The function code that reads each table.
_READ_FC = {"holding": 3, "input": 4, "coil": 1, "discrete": 2}


@dataclass(frozen=True)
class ModbusPoint:
    """One role on a Modbus table (see the module docstring)."""

    role: str
    table: str
    address: int
    type: str
    count: int
    word_order: str
    byte_order: str
    scale: float
    offset: float
    factor: float

    @property
    def end(self) -> int:
        """One past the last address."""
        return self.address + self.count

    @property
    def dtype(self) -> Any:
        """pymodbus's ``DATATYPE`` of the point (cached)."""
        dt = self.__dict__.get("_dtype")
        if dt is None:
            dt = _DT[self.type.upper()]
            object.__setattr__(self, "_dtype", dt)
        return dt

    def _swap(self, regs: list[int]) -> list[int]:
        if self.byte_order == "little":
            return [((r & 0xFF) << 8) | (r >> 8) for r in regs]
        return regs

    def raw_value(self, si: float) -> float | int:
        """The raw value of the SI value ``si``: ``raw = (si / factor − offset) / scale``,
        rounded to the nearest integer for an integer type (the inverse of :meth:`si`).

        Raises
        ------
        InputError
            The value does not fit the point's integer type.
        """
        value = (si / self.factor - self.offset) / self.scale
        if self.type in _INT_RANGE:
            raw = round(value)
            lo, hi = _INT_RANGE[self.type]
            if not lo <= raw <= hi:
                raise InputError(
                    f"{self.role}: {si} is out of the {self.type} range of the profile's map"
                )
            return raw
        return value

    def to_registers(self, si: float) -> list[int]:
        """Registers (or one coil value) for the SI value ``si``.

        Raises
        ------
        InputError
            The value does not fit the point's integer type.
        """
        if self.type == "bool":
            return [1 if (si / self.factor - self.offset) / self.scale else 0]
        value = self.raw_value(si)
        regs = ModbusClientMixin.convert_to_registers(
            value,
            self.dtype,
            word_order=self.word_order,  # type: ignore[arg-type]
        )
        return self._swap(regs)

    def si(self, raw: float) -> float:
        """The SI value of the point's raw value (value in ``units`` = raw · scale + offset)."""
        return (raw * self.scale + self.offset) * self.factor

    def from_registers(self, regs: list[int]) -> float:
        """The SI value of the point's registers (or coil value)."""
        if self.type == "bool":
            raw: float = 1.0 if regs[0] else 0.0
        else:
            raw = ModbusClientMixin.convert_from_registers(
                self._swap(regs),
                self.dtype,
                word_order=self.word_order,  # type: ignore[arg-type]
            )  # type: ignore[assignment]
        return (raw * self.scale + self.offset) * self.factor

    def raw_from_registers(self, regs: list[int]) -> int:
        """The integer of a status word (no scale)."""
        if self.type == "bool":
            return 1 if regs[0] else 0
        if self.type == "uint16" and self.byte_order == "big":
            return int(regs[0])  # the register pymodbus decoded is the unsigned 16-bit value
        return int(
            ModbusClientMixin.convert_from_registers(
                self._swap(regs),
                self.dtype,
                word_order=self.word_order,  # type: ignore[arg-type]
            )
        )


@dataclass(frozen=True)
class ModbusAction:
    """A write that performs an action: ``value`` to ``table[address]`` (coil or holding)."""

    name: str
    table: str
    address: int
    value: int


@dataclass(frozen=True)
class ReadBlock:
    """One read request per step: ``count`` items of ``table`` from ``address``."""

    table: str
    address: int
    count: int
    points: tuple[ModbusPoint, ...]


@dataclass(frozen=True)
class ModbusProfile:
    """A validated Modbus profile (see the module docstring).

    Attributes
    ----------
    fc23 : bool
        One Read/Write Multiple Registers (FC 23) per step: the set-point is in holding
        registers and every read role is in one block of holding registers (≤ 125).
    reads : tuple of ReadBlock
        The read requests per step otherwise (one per table, contiguous span ≤ 125 / 2000).
    pipeline : bool
        Modbus TCP: the step's requests go out in one socket write, their responses matched by
        transaction id (``[modbus] pipeline``, default true). False: one request at a time,
        the next written when the previous one is answered. RTU is always one at a time.
    """

    source: str
    unit: int
    points: dict[str, ModbusPoint]
    actions: dict[str, ModbusAction]
    masks: dict[int, int]
    heartbeat: ModbusPoint | None
    reads: tuple[ReadBlock, ...]
    fc23: bool
    pipeline: bool = True
    protocol: str = "modbus"
    units_doc: dict[str, str] = field(default_factory=dict)

    def check_setpoint_range(self, limit: float) -> None:
        """Refuse a set-point point that cannot carry every command within ±``limit`` m
        (``safety.displacement_limit``; 0 = off): one line, before anything moves.

        On the profile of a force-controlled channel (:meth:`for_control`) the written point
        is the force set-point and ``limit`` the force limit in N (``safety.force_limit``).
        """
        sp = self.points["setpoint"]
        if limit <= 0 or sp.type not in _INT_RANGE:
            return
        lo, hi = sorted(sp.si(v) for v in _INT_RANGE[sp.type])
        if lo > -limit or hi < limit:
            what = f"{sp.type} with scale {sp.scale:g}"
            raise InputError(_range_refusal(self.source, sp.role, what, lo, hi, limit))

    @property
    def control_modes(self) -> tuple[str, ...]:
        """The wire control modes the map can run: ``displacement``, and ``force`` when it
        maps ``roles.force_setpoint``."""
        return CONTROL_MODES if "force_setpoint" in self.points else CONTROL_MODES[:1]

    def for_control(self, mode: str) -> ModbusProfile:
        """The profile as a channel in wire mode ``mode`` uses it.

        ``"displacement"``: this profile. ``"force"``: the same map with
        ``roles.force_setpoint`` as the point written every step (``points["setpoint"]``,
        its role ``force_setpoint``, its value in N), the requests per step worked out for it.

        Raises
        ------
        InputError
            ``"force"`` and the map has no ``roles.force_setpoint`` (one line).
        """
        if mode != "force":
            return self
        fsp = self.points.get("force_setpoint")
        if fsp is None:
            raise _no_force_role(self.source, "a holding register point in N, kN or lbf")
        _check_force_loop(self.source, self.actions)
        points = {**self.points, "setpoint": fsp}
        fc23 = fsp.table == "holding" and len(self.reads) == 1 and self.reads[0].table == "holding"
        return replace(self, points=points, fc23=fc23)

    def step_functions(self) -> list[int]:
        """The function code of each request of one step: 23, or 16 and one read per block
        (3 holding, 4 input, 1 coils, 2 discrete inputs), in the order they are sent."""
        if self.fc23:
            return [23]
        return [16] + [_READ_FC[b.table] for b in self.reads]

    def rtu_frames(self) -> list[tuple[int, int]]:
        """(request, response) bytes on an RTU line, CRC included, of each transaction of
        one step: FC 23 (``13 + 2w``, ``5 + 2r``), or FC 16 (``9 + 2w``, 8) and one read per
        block (8, ``5 + 2n`` registers or ``5 + ⌈n/8⌉`` bits), Modbus application protocol
        V1.1b3 §6.1–6.17, RTU framing (address + CRC) of the serial line guide V1.02 §2.5.1.1
        (docs/references.md)."""
        w = self.points["setpoint"].count
        if self.fc23:
            return [(13 + 2 * w, 5 + 2 * self.reads[0].count)]
        out = [(9 + 2 * w, 8)]
        for b in self.reads:
            n = b.count
            out.append((8, 5 + (2 * n if b.table in ("holding", "input") else -(-n // 8))))
        return out


def _modbus_point(r: _Reader, role: str, defaults: dict[str, str]) -> ModbusPoint:
    p = r.table(role, required=True)
    assert p is not None
    p.unknown(("table", "address", "type", "word_order", "byte_order", "scale", "offset", "units"))
    table = p.str("table", choices=tuple(TABLES))
    bit = table in ("coil", "discrete")
    typ = p.str("type", "bool" if bit else None)
    if bit and typ != "bool":
        raise p.fail("type", f"a {table} holds a bool, got {typ!r}")
    if not bit and typ not in REG_TYPES:
        raise p.fail("type", f"unknown type {typ!r} (known: {', '.join(REG_TYPES)})")
    count = 1 if bit else REG_TYPES[typ]
    address = p.int("address", lo=0, hi=65535)
    if address + count > 65536:
        raise p.fail("address", f"{address}+{count} registers run past 65535")
    scale = p.float("scale", 1.0)
    if scale == 0.0:
        raise p.fail("scale", "must not be 0")
    return ModbusPoint(
        role=role,
        table=table,
        address=address,
        type=typ,
        count=count,
        word_order=p.str("word_order", defaults["word_order"], ("big", "little")),
        byte_order=p.str("byte_order", defaults["byte_order"], ("big", "little")),
        scale=scale,
        offset=p.float("offset", 0.0),
        factor=_units(p, role=role),
    )


def _modbus_roles(roles: _Reader, defaults: dict[str, str]) -> dict[str, ModbusPoint]:
    """The role points of ``[roles]``: the required ones and the force set-point if mapped;
    the set-points must be writable registers."""
    src = roles.source
    points = {role: _modbus_point(roles, role, defaults) for role in ROLES}
    for role in OPTIONAL_ROLES:
        if role in roles.data:
            points[role] = _modbus_point(roles, role, defaults)
    for role, what in (("setpoint", "a displacement"), ("force_setpoint", "a force")):
        sp = points.get(role)
        if sp is None:
            continue
        if not TABLES[sp.table][1]:
            raise InputError(f"profile {src}: roles.{role}: the {sp.table} table is read-only")
        if sp.type == "bool":
            raise InputError(f"profile {src}: roles.{role}: {what} needs a register type")
    return points


def _check_force_loop(source: str, actions: dict[str, Any]) -> None:
    """A controller that selects its loop on command (``actions.displacement_mode``) runs a
    force channel only with the action that selects its force loop."""
    if "displacement_mode" in actions and "force_mode" not in actions:
        raise InputError(
            f"profile {source}: actions.force_mode is missing: the controller selects its loop "
            "on command (actions.displacement_mode) and a force-controlled channel needs its "
            "force loop selected"
        )


def _check_mode_actions(src: str, actions: dict[str, Any], roles: dict[str, Any]) -> None:
    """``actions.force_mode`` only with a force set-point to follow, and not the same write as
    ``actions.displacement_mode`` (the controller could not tell the loops apart)."""
    if "force_mode" in actions and "force_setpoint" not in roles:
        raise InputError(
            f"profile {src}: actions.force_mode: selects a force loop, but the profile maps no "
            "roles.force_setpoint to command it"
        )
    f, d = actions.get("force_mode"), actions.get("displacement_mode")
    if f is not None and d is not None:
        same = (
            (f.message, f.signal, f.value) == (d.message, d.signal, d.value)
            if isinstance(f, CANSignal)
            else (f.table, f.address, f.value) == (d.table, d.address, d.value)
        )
        if same:
            raise InputError(
                f"profile {src}: actions.displacement_mode: the same write as "
                "actions.force_mode: the controller could not tell the loops apart"
            )


def _check_overlaps(source: str, points: list[ModbusPoint], actions: list[ModbusAction]) -> None:
    spans = [(p.table, p.address, p.end, f"roles.{p.role}") for p in points]
    spans += [(a.table, a.address, a.address + 1, f"actions.{a.name}") for a in actions]
    for i, (t1, a1, e1, n1) in enumerate(spans):
        for t2, a2, e2, n2 in spans[i + 1 :]:
            if t1 == t2 and a1 < e2 and a2 < e1:
                if n1.startswith("actions.") and n2.startswith("actions."):
                    continue  # enable/disable/acknowledge may write one control word
                raise InputError(
                    f"profile {source}: {n2}: {t2} {a2}–{e2 - 1} overlaps {n1} ({a1}–{e1 - 1})"
                )


def _read_blocks(points: list[ModbusPoint]) -> tuple[ReadBlock, ...]:
    by_table: dict[str, list[ModbusPoint]] = {}
    for p in points:
        by_table.setdefault(p.table, []).append(p)
    out = []
    for table, pts in by_table.items():
        a = min(p.address for p in pts)
        e = max(p.end for p in pts)
        out.append(ReadBlock(table, a, e - a, tuple(pts)))
    return tuple(out)


def _load_modbus(r: _Reader) -> ModbusProfile:
    src = r.source
    mb = r.table("modbus")
    defaults = {"word_order": "big", "byte_order": "big"}
    unit = 1
    pipeline = True
    if mb is not None:
        mb.unknown(("unit", "word_order", "byte_order", "pipeline"))
        unit = mb.int("unit", 1, lo=0, hi=255)
        pipeline = mb.data.get("pipeline", True)
        if not isinstance(pipeline, bool):
            raise mb.fail("pipeline", f"must be true or false, got {pipeline!r}")
        defaults = {
            "word_order": mb.str("word_order", "big", ("big", "little")),
            "byte_order": mb.str("byte_order", "big", ("big", "little")),
        }
    roles = r.table("roles", required=True)
    assert roles is not None
    roles.unknown(ROLES + OPTIONAL_ROLES)
    missing = [x for x in ROLES if x not in roles.data]
    if missing:
        raise InputError(
            f"profile {src}: roles.{missing[0]} is missing (the bridge needs {', '.join(ROLES)})"
        )
    points = _modbus_roles(roles, defaults)
    sp = points["setpoint"]
    acts = r.table("actions", required=True)
    assert acts is not None
    acts.unknown(ACTIONS)
    if "estop" not in acts.data:
        raise InputError(f"profile {src}: actions.estop is missing (every driver can e-stop)")
    actions = {}
    for name in ACTIONS:
        a = acts.table(name)
        if a is None:
            continue
        a.unknown(("table", "address", "value"))
        table = a.str("table", choices=("coil", "holding"))
        hi = 1 if table == "coil" else 65535  # a coil is 0 or 1 (FC 5 writes ON or OFF)
        actions[name] = ModbusAction(
            name, table, a.int("address", lo=0, hi=65535), a.int("value", 1, lo=0, hi=hi)
        )
    _check_mode_actions(src, actions, points)
    heartbeat = None
    if r.table("heartbeat") is not None:
        heartbeat = _modbus_point(r, "heartbeat", defaults)
        if heartbeat.table not in ("holding",) or heartbeat.type not in ("uint16", "int16"):
            raise InputError(f"profile {src}: heartbeat: must be a 16-bit holding register")
    allpoints = list(points.values()) + ([heartbeat] if heartbeat else [])
    _check_overlaps(src, allpoints, list(actions.values()))
    reads = _read_blocks([points[x] for x in READ_ROLES])
    for b in reads:
        limit = 2000 if b.table in ("coil", "discrete") else 125
        if b.count > limit:
            raise InputError(
                f"profile {src}: roles: the {b.table} points span {b.count} addresses from "
                f"{b.address}; one read carries at most {limit}"
            )
    fc23 = sp.table == "holding" and len(reads) == 1 and reads[0].table == "holding"
    masks = _masks(r)
    _check_masks(src, masks, points["status"])
    return ModbusProfile(
        source=src,
        unit=unit,
        points=points,
        actions=actions,
        masks=masks,
        heartbeat=heartbeat,
        reads=reads,
        fc23=fc23,
        pipeline=pipeline,
    )


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


def _load_can(r: _Reader, base: Path) -> CANProfile:
    from .can.codec import load_dbc

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
    _check_mode_actions(src, actions, roles)
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


@cache
def _load_cached(path: str) -> ModbusProfile | CANProfile:
    p = Path(path)
    data = read_toml(p, "profile", f"profile {p}")
    r = _Reader(str(p), data)
    protocol = r.str("protocol", choices=("modbus", "can"))
    if protocol == "modbus":
        r.unknown(("protocol", "name", "modbus", "roles", "status", "actions", "heartbeat"))
        return _load_modbus(r)
    r.unknown(("protocol", "name", "dbc", "roles", "status", "actions", "heartbeat"))
    return _load_can(r, p.parent)


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

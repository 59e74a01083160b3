"""The Modbus register-map profile format (``protocol = "modbus"``,
:mod:`rths_hil.drivers.profile`): each role a *point* on a Modbus table, each action a write,
the read blocks of a step. :func:`load_modbus` reads the ``[modbus]``, ``roles``, ``status``,
``actions`` and ``heartbeat`` tables; :func:`rths_hil.drivers.profile.load_profile` is the
entry."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from pymodbus.client.mixin import ModbusClientMixin

from rths_hil.errors import InputError

from ..profile import (
    ACTIONS,
    CONTROL_MODES,
    OPTIONAL_ROLES,
    READ_ROLES,
    ROLES,
    STATUS_BITS,
    _check_force_loop,
    _check_mode_actions,
    _masks,
    _no_force_role,
    _range_refusal,
    _Reader,
    _units,
)

__all__ = [
    "REG_TYPES",
    "TABLES",
    "ModbusAction",
    "ModbusPoint",
    "ModbusProfile",
    "ReadBlock",
    "load_modbus",
]

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
_DT: type[ModbusClientMixin.DATATYPE] = ModbusClientMixin.DATATYPE  # a variable, not an alias
_INT_RANGE = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}


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


def load_modbus(r: _Reader) -> ModbusProfile:
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
    _check_mode_actions(src, actions, points, lambda a: (a.table, a.address, a.value))
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

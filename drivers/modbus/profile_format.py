"""The Modbus register-map profile format (``protocol = "modbus"``,
:mod:`rths_hil.drivers.profile`): each role a *point* on a Modbus table, each action a write,
the read blocks of a step. :func:`load_modbus` reads the ``[modbus]``, ``roles``, ``status``,
``actions`` and ``heartbeat`` tables; :func:`rths_hil.drivers.profile.load_profile` is the
entry, which finds this module by its package's name (the format is ``modbus``) and calls its
:func:`load`."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pymodbus.client.mixin import ModbusClientMixin

from rths_hil.errors import InputError
from rths_hil.keys import REQUIRED, Key

from ..profile import (
    READ_ROLES,
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

__all__ = [
    "FILE_KEYS",
    "FORMAT",
    "MODBUS_KEYS",
    "POINT_KEYS",
    "REG_TYPES",
    "TABLES",
    "ModbusAction",
    "ModbusPoint",
    "ModbusProfile",
    "ReadBlock",
    "load",
    "load_modbus",
]

#: The ``protocol`` of a profile of this format: how
#: :func:`rths_hil.drivers.registry.profile_formats` finds it (read without importing this
#: module, so a string literal), and :func:`load` reads it.
FORMAT = "modbus"

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
_ORDERS = ("big", "little")
#: The top-level keys of a register-map profile.
FILE_KEYS = top_keys({"modbus": Key("table", {}, doc="the unit id and the map's defaults")})
#: ``[modbus]``.
MODBUS_KEYS = {
    "unit": Key("int", 1, lo=0, hi=255, doc="the unit id"),
    "word_order": Key("choice", "big", choices=_ORDERS, doc="default word order of the points"),
    "byte_order": Key("choice", "big", choices=_ORDERS, doc="default byte order of the points"),
    "pipeline": Key("bool", True, doc="Modbus TCP: a step's requests in one socket write"),
}
#: A role (or the heartbeat) on a point of a Modbus table.
POINT_KEYS = {
    "table": Key("choice", REQUIRED, choices=tuple(TABLES), doc="the Modbus table"),
    "address": Key("int", REQUIRED, lo=0, hi=65535, doc="0-based PDU address"),
    "type": Key("str", None, doc="register type (REG_TYPES; bool on coils and discrete inputs)"),
    "word_order": Key("choice", None, choices=_ORDERS, doc="default: [modbus] word_order"),
    "byte_order": Key("choice", None, choices=_ORDERS, doc="default: [modbus] byte_order"),
    "scale": Key("float", 1.0, doc="value in units = raw · scale + offset"),
    "offset": Key("float", 0.0, doc="value in units = raw · scale + offset"),
    "units": UNITS_KEY,
}
#: An action: ``value`` written to ``table[address]`` (a coil is 0 or 1: FC 5 writes ON or OFF).
_ACTION = {
    table: {
        "table": Key("choice", REQUIRED, choices=("coil", "holding"), doc="coil or holding"),
        "address": Key("int", REQUIRED, lo=0, hi=65535, doc="0-based PDU address"),
        "value": Key("int", 1, lo=0, hi=hi, doc="the value written"),
    }
    for table, hi in (("coil", 1), ("holding", 65535))
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
    what = f"the {point.table} {point.type} status point (bits up to 0x{hi:X})"
    check_mask_bits(source, masks, hi, what)


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
class ModbusProfile(ProfileFormat):
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
    protocol: str = FORMAT
    units_doc: dict[str, str] = field(default_factory=dict)

    def _setpoint_span(self) -> tuple[float, float, str] | None:
        """An integer set-point point's range through its scale (a float one carries any)."""
        sp = self.points["setpoint"]
        if sp.type not in _INT_RANGE:
            return None
        lo, hi = sorted(sp.si(v) for v in _INT_RANGE[sp.type])
        return lo, hi, f"{sp.type} with scale {sp.scale:g}"

    ROLE_FIELD = "points"

    def _force_hint(self) -> str:
        return "a holding register point in N, kN or lbf"

    def _with_setpoint(self, fsp: ModbusPoint) -> ModbusProfile:
        """The map with ``fsp`` as the point written every step (``points["setpoint"]``, its
        role ``force_setpoint``), the requests per step worked out for it."""
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


def _modbus_point(src: str, table: Any, path: str, defaults: dict[str, Any]) -> ModbusPoint:
    """The role or heartbeat at ``path`` on its Modbus point (``defaults``: ``[modbus]``)."""
    p = check_keys(src, table, POINT_KEYS, path)

    def fail(key: str, why: str) -> InputError:
        return InputError(f"profile {src}: {path}.{key}: {why}")

    bit = p["table"] in ("coil", "discrete")
    typ = p["type"] or ("bool" if bit else None)
    if typ is None:
        raise fail("type", "missing")
    if bit and typ != "bool":
        raise fail("type", f"a {p['table']} holds a bool, got {typ!r}")
    if not bit and typ not in REG_TYPES:
        raise fail("type", f"unknown type {typ!r} (known: {', '.join(REG_TYPES)})")
    count = 1 if bit else REG_TYPES[typ]
    if p["address"] + count > 65536:
        raise fail("address", f"{p['address']}+{count} registers run past 65535")
    if p["scale"] == 0.0:
        raise fail("scale", "must not be 0")
    role = path.rpartition(".")[2]
    return ModbusPoint(
        role=role,
        table=p["table"],
        address=p["address"],
        type=typ,
        count=count,
        word_order=p["word_order"] or defaults["word_order"],
        byte_order=p["byte_order"] or defaults["byte_order"],
        scale=p["scale"],
        offset=p["offset"],
        factor=_units(src, path, p["units"], role=role),
    )


def _modbus_roles(src: str, roles: Any, defaults: dict[str, Any]) -> dict[str, ModbusPoint]:
    """The role points of ``[roles]``: the required ones and the force set-point if mapped;
    the set-points must be writable registers."""
    points = read_roles(src, roles, lambda t, path: _modbus_point(src, t, path, defaults))
    for role, what in (("setpoint", "a displacement"), ("force_setpoint", "a force")):
        sp = points.get(role)
        if sp is None:
            continue
        if not TABLES[sp.table][1]:
            raise InputError(f"profile {src}: roles.{role}: the {sp.table} table is read-only")
        if sp.type == "bool":
            raise InputError(f"profile {src}: roles.{role}: {what} needs a register type")
    return points


def _modbus_action(src: str, table: Any, path: str) -> ModbusAction:
    """The write of the action at ``path`` (a coil takes 0 or 1)."""
    coil = isinstance(table, dict) and table.get("table") == "coil"
    a = check_keys(src, table, _ACTION["coil" if coil else "holding"], path)
    return ModbusAction(path.rpartition(".")[2], a["table"], a["address"], a["value"])


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


def load(source: str, data: dict[str, Any], base: Path) -> ModbusProfile:
    """The profile of this format at ``source`` (its TOML ``data``; ``base``, the profile's
    folder, unused): :func:`load_modbus`, as :func:`rths_hil.drivers.profile.load_profile`
    calls every format's ``load``."""
    return load_modbus(source, data)


def load_modbus(src: str, data: dict[str, Any]) -> ModbusProfile:
    """The register-map profile ``src`` (its TOML ``data``)."""
    top = check_keys(src, data, FILE_KEYS, "")
    mb = check_keys(src, top["modbus"], MODBUS_KEYS, "modbus")
    points = _modbus_roles(src, top["roles"], mb)
    sp = points["setpoint"]
    actions = read_actions(src, top["actions"], lambda t, path: _modbus_action(src, t, path))
    _check_mode_actions(src, actions, points, lambda a: (a.table, a.address, a.value))
    heartbeat = None
    if top["heartbeat"] is not None:
        heartbeat = _modbus_point(src, top["heartbeat"], "heartbeat", mb)
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
    masks = _masks(src, top["status"])
    _check_masks(src, masks, points["status"])
    return ModbusProfile(
        source=src,
        unit=mb["unit"],
        points=points,
        actions=actions,
        masks=masks,
        heartbeat=heartbeat,
        reads=reads,
        fc23=fc23,
        pipeline=mb["pipeline"],
    )

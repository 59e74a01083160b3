"""The CANopen link model: the frames of one axis per step (SYNC, PDOs, heartbeats), the bus
load of a set of axes, how many fit, and the planning facts of the protocol (its link,
who may share it).
"""

from __future__ import annotations

import logging
import os
from typing import Any

import canopen
from canopen.objectdictionary import ODArray, ODRecord

from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad

from ..protocol import ChannelUse, LinkInputs, link_model
from .od import (
    BRIDGE_NODE_ID,
    TORQUE_ACTUAL,
    _check_bitrate,
    _quantity,
    _variable,
    parse_object,
)
from .profiles import PROFILES

log = logging.getLogger(__package__)


def inline_twin(connection: dict[str, Any]) -> bool:
    """The twin on python-can's in-process ``virtual`` bus serves the steps from the loop's
    thread (its own thread answers the SDO exchanges, see
    :meth:`rths_hil.sim_backends.endpoints.canopen.CANopenTwin.start`)."""
    return str((connection or {}).get("interface", "virtual")) == "virtual"


def link_key(connection: dict[str, Any]) -> str:
    """CANopen: the python-can interface and channel of the bus."""
    c = connection or {}
    return f"canopen {c.get('interface', 'virtual')}:{c.get('channel', 'rths-canopen')}"


def check_sharing(channels: list[ChannelUse]) -> None:
    """Several axes may share a bus (one SYNC per step for all, :class:`CANopenBus`), each
    with its own node id and the bus's settings (bit rate, the bridge's node id)."""
    seen: dict[str, dict[str, Any]] = {}
    for _, name, conn, twin in channels:
        c = conn or {}
        if twin and not c.get("channel"):
            continue  # each twin gets a bus of its own
        key = link_key(c)
        where = key.split(" ", 1)[1]
        first = seen.setdefault(key, {"name": name, "nodes": {}, "conn": c})
        node = c.get("node_id", 1)
        other = first["nodes"].get(node)
        if other is not None:
            raise InputError(
                f"actuators: channels {other!r} and {name!r} are both CANopen node {node} on "
                f"bus {where}: give each axis its own driver.connection.node_id"
            )
        first["nodes"][node] = name
        for k, default in (("bitrate", None), ("bridge_node_id", BRIDGE_NODE_ID)):
            if c.get(k, default) != first["conn"].get(k, default):
                raise InputError(
                    f"actuators: channels {first['name']!r} and {name!r} share CANopen bus "
                    f"{where} but differ in driver.connection.{k} "
                    f"({first['conn'].get(k, default)} vs {c.get(k, default)})"
                )


# ---------------------------------------------------------------------------------------------
# link budget
def step_frames(connection: dict[str, Any] | None = None) -> dict[str, int]:
    """Data bytes of the frames of one axis per step, and of the SYNC (shared by the bus).

    RPDO1 (control word + set-point), TPDO1 (status word + actual position), TPDO2 (force, absent
    when ``force_object = ""``) and the SYNC without a counter (0 bytes); heartbeats are 1 byte.
    With an EDS whose PDO mapping is fixed (its mapping objects read-only, the mapping in their
    defaults) the frames are those of that mapping: the RPDO with the control word, the TPDO
    with the status word ("tpdo1") and any other TPDO with the position or the force ("tpdo2").
    """
    c = dict(connection or {})
    fixed = _fixed_eds_frames(c)
    if fixed is not None:
        return {**fixed, "sync": 0, "heartbeat": 1}
    f = c.get("force_object", "0x2100")
    return {"rpdo": 6, "tpdo1": 6, "tpdo2": _force_bytes(c) if str(f).strip() else 0, "sync": 0,
            "heartbeat": 1}  # fmt: skip


def _force_bytes(c: dict[str, Any]) -> int:
    """Bytes of the force object in the EDS (4, an INTEGER32, when it cannot be told)."""
    eds, f = c.get("eds"), c.get("force_object")
    if f is None or not isinstance(eds, str) or not os.path.isfile(eds):
        return 4
    try:
        od = canopen.import_od(eds, int(c.get("node_id", 1)))
        return len(_variable(od, parse_object(f, "force_object"), eds, "force_object")) // 8
    except Exception:  # refused by the driver with its own message
        return 4


def _fixed_eds_frames(c: dict[str, Any]) -> dict[str, int] | None:
    """Data bytes of the PDOs of a fixed mapping read from the EDS (:func:`step_frames`), or
    None (no EDS, a mapping the driver may write, or one that does not carry the profile's
    objects: the driver's own mapping is counted)."""
    eds = c.get("eds")
    profile = PROFILES.get(str(c.get("device_profile", "cia402")))
    if not isinstance(eds, str) or profile is None or not os.path.isfile(eds):
        return None
    try:
        od = canopen.import_od(eds, int(c.get("node_id", 1)))
        maps: dict[str, list[list[tuple[int, int, int]]]] = {"R": [], "T": []}
        for kind, base in (("R", 0x1600), ("T", 0x1A00)):
            for no in range(512):
                rec = od.get(base + no)
                if rec is None:
                    continue
                if not isinstance(rec, ODRecord | ODArray) or any(
                    rec[i].writable for i in rec.subindices
                ):
                    return None
                n = int(rec[0].default or 0)
                entries = [int(rec[i].default or 0) for i in range(1, n + 1)]
                maps[kind].append([(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in entries])
    except Exception:  # an EDS the driver will refuse with its own message
        return None
    f = c.get("force_object")
    forces = [(0x2100, 0), TORQUE_ACTUAL] if f is None else []
    if f is not None and str(f).strip():
        try:
            forces = [parse_object(f, "force_object")]
        except InputError:
            return None

    def size(objs: list[tuple[int, int, int]]) -> int:
        return sum(bits for _, _, bits in objs) // 8

    def carrying(kind: str, obj: tuple[int, int]) -> list[tuple[int, int, int]] | None:
        return next((m for m in maps[kind] if any((i, s) == obj for i, s, _ in m)), None)

    rpdo, tpdo1 = carrying("R", profile.control), carrying("T", profile.status)
    if rpdo is None or tpdo1 is None:
        return None
    others = [carrying("T", profile.actual), *(carrying("T", o) for o in forces)]
    extra = {id(m): m for m in others if m is not None and m is not tpdo1}
    return {"rpdo": size(rpdo), "tpdo1": size(tpdo1),
            "tpdo2": sum(size(m) for m in extra.values())}  # fmt: skip


@link_model(link_key)
def link_load(i: LinkInputs) -> LinkLoad:
    """The CANopen link's load (:class:`rths_hil.linkbudget.LinkLoad`) of ``channels`` axes.

    Per step: one SYNC for the bus (shared by its axes, :class:`CANopenBus`) plus, per axis,
    RPDO1, TPDO1 and TPDO2; per second the bridge's heartbeat, one per bus (``heartbeat_hz``, at
    least ``1/heartbeat_period``), and each device's (``1/controller_heartbeat``). Frame bits
    with worst-case stuffing (:func:`rths_hil.drivers.can.linkbudget.can_frame_bits`).
    """
    from ..can.linkbudget import can_frame_bits

    c, name, channels, fs = i.connection, i.link, i.channels, i.fs
    for key in ("heartbeat_period", "controller_heartbeat"):  # as the driver takes them
        if key in c:
            v = _quantity(key, c[key], "s")
            if isinstance(v, bool) or not isinstance(v, int | float) or not v >= 0:
                raise InputError(f"canopen: {key} must be a number ≥ 0 (s), got {c[key]!r}")
            c[key] = v
    bitrate = c.get("bitrate")
    _check_bitrate(bitrate)
    n = step_frames(c)
    per_axis = sum(can_frame_bits(n[k]) for k in ("rpdo", "tpdo1", "tpdo2") if n[k] or k != "tpdo2")
    b_sync = can_frame_bits(0)
    period = c.get("heartbeat_period")
    hb_bridge = max(i.heartbeat_hz, 1.0 / period if period else 0.0)
    ctrl = c.get("controller_heartbeat", 0.1)
    hb_dev = 1.0 / ctrl if ctrl else 0.0
    b_hb = can_frame_bits(1)
    per_second_bits = b_hb * (hb_bridge + channels * hb_dev)  # the bridge's: one per bus
    detail = (
        f"SYNC {b_sync} + {channels} × (RPDO {can_frame_bits(n['rpdo'])} + TPDO "
        f"{can_frame_bits(n['tpdo1'])}"
        + (f" + TPDO {can_frame_bits(n['tpdo2'])}" if n["tpdo2"] else "")
        + f") bits at {fs:g} Hz + heartbeats of {b_hb} bits: the bridge's at {hb_bridge:g} Hz, "
        f"{channels} × the device's at {hb_dev:g} Hz"
    )
    interface = str(c.get("interface", "virtual"))
    bits_s = (b_sync + channels * per_axis) * fs + per_second_bits
    if bitrate is None:
        why = "virtual bus" if interface == "virtual" else "bit rate set by the interface"
        return LinkLoad(name, None, f"{why}; {detail} = {bits_s:.0f} bit/s", kind="can", **i.base)
    rate = float(bitrate)
    return LinkLoad(
        name,
        bits_s / rate,
        f"{detail}, worst-case stuffing, of {rate / 1e6:g} Mbit/s"
        + ("; virtual bus" if interface == "virtual" else ""),
        enforced=interface != "virtual",
        kind="can",
        rate=rate,
        per_channel=per_axis / rate,
        per_second=(b_sync * fs + per_second_bits) / rate,
        **i.base,
    )


def axes_that_fit(
    fs: float, bitrate: float = 1e6, limit: float = 0.8, connection: dict[str, Any] | None = None
) -> int:
    """How many axes one CANopen bus carries at ``fs`` below ``limit`` (SYNC, PDOs, heartbeats)."""
    bus = {**(connection or {}), "bitrate": bitrate, "interface": "socketcan"}
    n = 0
    while n < 128:
        load = link_load(bus, n + 1, fs).load
        if load is None or load > limit:
            break
        n += 1
    return n

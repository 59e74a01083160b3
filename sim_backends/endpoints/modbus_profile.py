"""Modbus twin (TCP or RTU) for a profile: a controller with the lab's own register map.

The twin loads the same profile as the driver (:mod:`rths_hil.drivers.profile`) and serves its
map on a Modbus TCP server bound to 127.0.0.1, or as an RTU slave on a serial line (``transport
= "rtu"``: a pseudo-terminal pair of its own, or ``device``): the set-point, position, force and
status points, the action coils or registers and the heartbeat register. Any other address is
answered with the Modbus exception ILLEGAL DATA ADDRESS (addresses between the points of one
read block read as 0), as a real controller does, so a driver started with a profile that does
not match is refused by its start-up check. Requests are decoded and responses built by pymodbus
(``FramerSocket`` / ``FramerRTU``, ``DecodePDU``, its PDU classes; an RTU request is cut by the
size its PDU class computes and checked by its CRC). Values are converted by the precompiled
``struct`` layouts of :mod:`rths_hil.drivers.modbus.layout` (made once, each checked against
pymodbus's ``convert_to_registers`` / ``convert_from_registers``), a status word's registers
and which mapped spans a request touches are worked out once and remembered, so that a step
costs the twin's thread little beside pymodbus's request decoding and response framing. The
server side (the line, the ``select`` loop, the requests cut out of its bytes and routed) is
:class:`~.modbus_server.ModbusServer`, shared with the built-in twin (:mod:`.modbus`).

Controller behaviour (the :class:`~.base.TwinController` of every twin): each write of the
set-point (``roles.force_setpoint`` when the plant is force-controlled: its value in N goes to
the plant unchanged; a profile without it is refused) is one command — one plant step while
enabled, a hold while disabled; the ``enable`` / ``disable`` actions set the enable state;
``acknowledge`` starts a new run (as the built-in twins' arming command: the latch cleared, the
plant at rest, the step count from 0); ``estop`` latches the e-stop; a heartbeat write or a
set-point write feeds the controller-side watchdog. After each command the position, force and
status points show the new values; the status word is refreshed on every read (a watchdog latch
is visible at once). The map carries no sequence number: the twin counts set-point writes from
the acknowledge (the disabled write that follows it is the arming command, the next one the
run's step 0), so a fault plan's step numbers are the bridge's.

Faults: the frame faults of step ``k`` (drop, corrupt, duplicate, delay) apply to the responses
to the reads of the feedback after the set-point write of step ``k`` — with FC 23 its one
response — as they would to a controller's answer: dropped, sent twice, held back (the twin
does nothing else meanwhile), or damaged where the driver must notice (TCP: the unit id of the
MBAP header, which TCP's own checksum would otherwise protect; RTU: a data bit under the CRC).
Measurement faults change the published values; a ``nan`` sets the status word's
``sensor_invalid`` bit (when the profile maps one) and, in an integer point that cannot carry
NaN, leaves the last value; ``disconnect_from`` closes the connection.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from typing import Any, ClassVar

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsResponse,
    ReadDiscreteInputsResponse,
    WriteSingleCoilResponse,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersResponse,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterResponse,
)
from rths_hil.drivers.base import Status
from rths_hil.drivers.modbus.layout import PointLayout
from rths_hil.drivers.modbus.profile import ModbusProfileDriver
from rths_hil.drivers.modbus.profile_format import ModbusPoint, ModbusProfile
from rths_hil.drivers.modbus.transport import CONNECTION_KEYS, MAX_UNIT
from rths_hil.drivers.profile import load_profile, word_from_status

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..faults import Faults
from .base import LISTEN_KEYS, TwinController, TwinEndpoint
from .modbus_server import Conn, ModbusServer, ServerRules

__all__ = ["ModbusProfileTwin"]

_READ_TABLE = {3: "holding", 4: "input", 1: "coil", 2: "discrete"}
_SAMPLE_FLAGS = int(Status.SENSOR_INVALID | Status.SEQ_GAP)
_FEEDBACK_FC = frozenset((1, 2, 3, 4, 23))  # the responses that carry a step's feedback

_READ_RESP = {
    3: ReadHoldingRegistersResponse,
    4: ReadInputRegistersResponse,
    1: ReadCoilsResponse,
    2: ReadDiscreteInputsResponse,
}


#: The settings of a Modbus twin (:class:`ModbusProfileTwin` and
#: :class:`~.modbus.ModbusTwin`): the transport, the TCP listener (:data:`~.base.LISTEN_KEYS`)
#: or the RTU line, and the unit it answers as.
SERVER_KEYS: dict[str, Key] = {
    "transport": CONNECTION_KEYS["transport"],
    **LISTEN_KEYS,
    "device": Key("str", None, doc="twin, RTU: serial device (none: a new pseudo-terminal)"),
    "device_id": Key("int", 1, lo=1, hi=MAX_UNIT, doc="twin: the Modbus unit id it answers as"),
    "baudrate": CONNECTION_KEYS["baudrate"],
}

#: How a profile twin's server answers (:class:`.ServerRules`): a lab's controller is one
#: device on a port of its own, so it ignores (counts malformed) a request for another unit id
#: and answers a broadcast as itself; the responses to one read go out in one write, because
#: its driver pipelines a step's set-point write and reads and takes their answers in one
#: TCP segment.
_RULES = ServerRules(shared=False, gateway=False, batch=True, reply_own_unit=True)


class ModbusProfileTwin(TwinEndpoint):
    """Modbus TCP server or RTU slave speaking ``profile`` (see the module docstring)."""

    name = "modbus"
    #: :data:`SERVER_KEYS`, the unit as the profile driver's (none: the profile's); the
    #: profile comes apart.
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        **SERVER_KEYS,
        "device_id": ModbusProfileDriver.CONNECTION["device_id"],
    }

    def __init__(
        self,
        controller: TwinController,
        profile: str,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 0,
        allow_remote: bool = False,
        device_id: int | None = None,
        device: str | None = None,
        baudrate: int = 115200,
    ) -> None:
        super().__init__(controller)
        prof = load_profile(profile)
        if not isinstance(prof, ModbusProfile):
            raise InputError(f"modbus twin: profile {profile} is not a Modbus profile")
        if transport not in ("tcp", "rtu"):
            raise InputError(f"modbus twin: transport must be 'tcp' or 'rtu', got {transport!r}")
        self.transport = transport
        self.device, self.baudrate = device, int(baudrate)
        self.server: ModbusServer | None = None
        self.profile_path = str(profile)
        self.profile = prof
        self.host, self.port, self.allow_remote = str(host), int(port), bool(allow_remote)
        self.device_id = prof.unit if device_id is None else int(device_id)
        try:  # the point the controller follows: roles.setpoint, or the force set-point
            self._sp = prof.for_control(self.control).points["setpoint"]
        except InputError as exc:
            raise InputError(f"modbus twin: {exc}") from None
        self.tables: dict[str, dict[int, int]] = {t: {} for t in _READ_TABLE.values()}
        for p in list(prof.points.values()) + ([prof.heartbeat] if prof.heartbeat else []):
            for a in range(p.address, p.end):
                self.tables[p.table][a] = 0
        for b in prof.reads:  # the gaps inside a read block read as 0
            for a in range(b.address, b.address + b.count):
                self.tables[b.table].setdefault(a, 0)
        for act in prof.actions.values():
            self.tables[act.table].setdefault(act.address, 0)
        # made once: each register point's layout (checked against pymodbus) and the struct of
        # its registers as they go on the wire, high byte first: ">HH" for two registers
        self._layouts: dict[str, tuple[PointLayout, struct.Struct]] = {
            p.role: (PointLayout(p, self.profile_path), struct.Struct(f">{p.count}H"))
            for p in prof.points.values()
            if p.type != "bool"
        }
        #: (table, address, value) → the actions it performs, in the profile's order
        self._actions: dict[tuple[str, int, int], list[str]] = {}
        for n, a in prof.actions.items():
            self._actions.setdefault((a.table, a.address, a.value), []).append(n)
        self._status_regs: dict[int, list[int]] = {}  # status word → its registers
        self._spans: dict[tuple[str, int, int], bool] = {}  # (table, address, count) → mapped
        self._enable = False
        #: a controller that selects its loop on command (actions.force_mode /
        #: displacement_mode): the loop selected, displacement at power-on; it follows the
        #: set-point only while the loop is its plant's
        self._modes = bool({"force_mode", "displacement_mode"} & set(prof.actions))
        self._loop = "displacement"
        self._k = 0
        # the frame faults of the current step (copies, corrupt), applied to its read responses
        # (the map's reads of one step: its blocks, or the one FC 23), not to later reads such
        # as a status poll after an e-stop
        self._plan: tuple[int, bool] | None = None
        self._step_reads = 1 if prof.fc23 else len(prof.reads)
        self._plan_left = 0  # read responses of the step the plan still applies to
        self._sample_flags = 0  # per-sample status flags of the last published feedback

    # -- lifecycle ------------------------------------------------------------------------------
    def _setup(self) -> None:
        srv = self.server = ModbusServer.join(self, _RULES)
        if srv.key is not None:  # TCP
            port = srv.key[1]
            self._ready(f"{self.host}:{port}", host=self.host, port=port)
        else:  # RTU: a pseudo-terminal pair of its own (the driver opens the slave) or device
            path = os.ttyname(srv.slave) if srv.slave is not None else str(self.device)
            self._ready(path, device=path)

    def _ready(self, place: str, **line: Any) -> None:
        """Serving at ``place`` on ``line`` (``host`` and ``port``, or ``device``): the driver's
        ``connection`` and ``where``, and the registers at rest."""
        self.connection = {
            "transport": self.transport,
            **line,
            "device_id": self.device_id,
            "profile": self.profile_path,
        }
        self.where = f"modbus {self.transport} {place} unit {self.device_id} ({self.profile_path})"
        self._publish(0.0, 0.0, self.controller.status())

    def _teardown(self) -> None:
        if self.server is not None:  # (kept after the stop: which server served this twin)
            self.server.leave(self)

    def _go_away(self) -> None:
        """Disconnect fault: the connection, the line and the serial port close."""
        super()._go_away()
        if self.server is not None:
            self.server.close()

    # -- serving --------------------------------------------------------------------------------
    def _serve_once(self, timeout: float) -> None:
        if self.server is None:
            self._stop.wait(timeout)
        else:
            self.server.serve(timeout, self._stop.wait)

    def handle(self, conn: Conn, pdu: ModbusPDU) -> None:
        """Answer one request of this unit (:meth:`.ModbusServer.serve` calls it)."""
        self._reply(conn, self._dispatch(pdu), pdu.transaction_id)

    def _reply(self, conn: Conn, pdu: Any, tid: int) -> None:
        """Send one response, with the frame faults of the step when it carries its feedback."""
        if pdu is None:
            return
        srv = self.server
        assert srv is not None
        pdu.dev_id, pdu.transaction_id = self.device_id, tid
        frame = srv.framer.buildFrame(pdu)
        plan = self._plan
        if plan is None or pdu.function_code not in _FEEDBACK_FC:
            srv.write_to(conn, frame)
            return
        copies, corrupt = plan  # a response carrying the step's feedback
        self._plan_left -= 1
        if self._plan_left <= 0:  # the step's reads are answered (or lost): later reads are not
            self._plan = None
        if corrupt:
            frame = self._corrupt(frame)
        for _ in range(copies):
            srv.write_to(conn, frame)
        self.controller.stats.replies += copies

    def _mapped(self, table: str, address: int, count: int) -> bool:
        key = (table, address, count)
        ok = self._spans.get(key)
        if ok is None:  # (the map does not change: worked out once per span)
            t = self.tables[table]
            ok = self._spans[key] = all(a in t for a in range(address, address + count))
        return ok

    def _to_registers(self, p: ModbusPoint, si: float) -> list[int]:
        """The point's registers for the SI value (:meth:`.ModbusPoint.to_registers`)."""
        codec = self._layouts.get(p.role)
        if codec is None:
            return p.to_registers(si)  # a bool point
        layout, regs = codec
        return list(regs.unpack(layout.pack(p.raw_value(si))))

    def _from_registers(self, p: ModbusPoint, values: list[int]) -> float:
        """The point's SI value from its registers (:meth:`.ModbusPoint.from_registers`)."""
        layout, regs = self._layouts[p.role]
        return p.si(layout.unpack_from(regs.pack(*values), 0))

    def _read(self, fc: int, address: int, count: int) -> Any:
        table = _READ_TABLE[fc]
        if not self._mapped(table, address, count):
            return ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS)
        self._refresh_status()
        values = [self.tables[table][a] for a in range(address, address + count)]
        if fc in (1, 2):
            return _READ_RESP[fc](bits=[bool(v) for v in values])
        return _READ_RESP[fc](registers=values)

    def _dispatch(self, pdu: Any) -> Any:
        fc = pdu.function_code
        if fc in _READ_TABLE:
            return self._read(fc, pdu.address, pdu.count)
        if fc == 5:  # write single coil
            if not self._mapped("coil", pdu.address, 1):
                return ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS)
            value = 1 if pdu.bits[0] else 0
            self.tables["coil"][pdu.address] = value
            self._act("coil", pdu.address, value)
            return WriteSingleCoilResponse(address=pdu.address, bits=[bool(value)])
        if fc in (6, 16, 23):
            if fc == 23:
                address, regs = pdu.write_address, list(pdu.write_registers)
            else:
                address, regs = pdu.address, list(pdu.registers)
            if not self._mapped("holding", address, len(regs)):
                return ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS)
            if fc == 23 and not self._mapped("holding", pdu.read_address, pdu.read_count):
                return ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS)
            self._write_holding(address, regs)
            if fc == 23:
                self._refresh_status()
                t = self.tables["holding"]
                a, n = pdu.read_address, pdu.read_count
                return ReadWriteMultipleRegistersResponse(registers=[t[x] for x in range(a, a + n)])
            if fc == 6:
                return WriteSingleRegisterResponse(address=address, registers=regs)
            return WriteMultipleRegistersResponse(address=address, count=len(regs))
        return ExceptionResponse(fc, ExcCodes.ILLEGAL_FUNCTION)

    def _write_holding(self, address: int, regs: list[int]) -> None:
        t = self.tables["holding"]
        for i, r in enumerate(regs):
            t[address + i] = r
        prof = self.profile
        for i, r in enumerate(regs):
            self._act("holding", address + i, r)
        hb = prof.heartbeat
        if hb is not None and address <= hb.address < address + len(regs):
            self.controller.heartbeat()
        sp = self._sp
        if address <= sp.address and sp.end <= address + len(regs):
            x = self._from_registers(sp, [t[a] for a in range(sp.address, sp.end)])
            enable = self._enable and (not self._modes or self._loop == self.control)
            reply = self.controller.command(self._k, x, enable)
            if self._enable or self._k:  # (the disabled write at 0 is the arming command)
                self._k += 1
            self.emit(reply)

    def _act(self, table: str, address: int, value: int) -> None:
        ctl = self.controller
        for name in self._actions.get((table, address, value), ()):
            if name == "estop":
                ctl.estop()
            elif name == "enable":
                self._enable = True
            elif name == "disable":
                self._enable = False
            elif name == "force_mode":
                self._loop = "force"
            elif name == "displacement_mode":
                self._loop = "displacement"
            elif name == "acknowledge":
                self._enable = False
                self._k = 0  # a new run (arming): the count restarts
                self._plan = None
                reply = ctl.command(0, ctl.displacement, False)
                if reply is not None:
                    self._publish(*reply[1:])

    # -- feedback -------------------------------------------------------------------------------
    def _publish(self, displacement: float, force: float, status: int) -> None:
        t = self.tables
        pts = self.profile.points
        for role, value in (("position", displacement), ("force", force)):
            p = pts[role]
            try:
                regs = self._to_registers(p, value)
            except (InputError, ValueError):
                continue  # not representable (NaN in an integer point): keep the old value
            for i, r in enumerate(regs):
                t[p.table][p.address + i] = r
        self._sample_flags = status & _SAMPLE_FLAGS
        self._set_status(status)

    def _set_status(self, status: int) -> None:
        p = self.profile.points["status"]
        word = word_from_status(status, self.profile.masks)
        regs = self._status_regs.get(word)
        if regs is None:  # (once per word)
            si = (word * p.scale + p.offset) * p.factor  # the point's raw value is the word
            regs = self._status_regs[word] = p.to_registers(si)
        for i, r in enumerate(regs):
            self.tables[p.table][p.address + i] = r

    def _refresh_status(self) -> None:
        # the controller's state now, with the flags of the last sample (sensor invalid)
        self._set_status(self.controller.status() | self._sample_flags)

    def emit(self, reply: tuple[int, float, float, int] | None) -> None:
        if reply is None:
            self._plan = (0, False)  # a lost command: its step's reads go unanswered
            self._plan_left = self._step_reads
            return
        super().emit(reply)

    def _send_feedback(
        self, reply: tuple[int, float, float, int], copies: int, pause: float, corrupt: bool
    ) -> None:
        """Publish the values of one command's feedback and plan the step's frame faults.

        A register map has no feedback frame of its own: the values are published to the
        tables, and the frame faults apply to the responses to the step's reads (:meth:`_reply`).
        """
        self._publish(*reply[1:])
        self._plan, self._plan_left = (copies, corrupt), self._step_reads
        if pause:  # a stalled controller: the step's reads are answered after the pause
            self._stop.wait(pause)

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        self._publish(displacement, force, status)  # (emit publishes; kept for the interface)
        return []

    def _corrupt(self, frame: bytes) -> bytes:
        # TCP: the unit id of the MBAP header (TCP's checksum guards the rest of a segment);
        # RTU: a bit of the first data byte, caught by the CRC
        return Faults.flip_bit(frame, 6 if self.transport == "tcp" else 3)

    def _write(self, frame: Any) -> None:  # pragma: no cover - responses go out in _reply
        pass

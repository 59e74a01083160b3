"""Modbus twin endpoint: a Modbus TCP server on 127.0.0.1 or an RTU slave on a pseudo-terminal.

The register map is the one of :mod:`rths_hil.drivers.modbus`. Requests are decoded and responses
encoded with pymodbus's own framers (``FramerSocket``, ``FramerRTU``) and PDU classes
(``DecodePDU(is_server=True)``, ``ReadWriteMultipleRegistersResponse`` …), so any Modbus client
can talk to it; the event loop is a plain ``select`` loop in one thread (the server side both
Modbus twins share, :mod:`.modbus_server`) rather than pymodbus's asyncio server, whose
per-request hops (``call_soon`` → ``run_coroutine_threadsafe`` → datastore coroutines) would
add hundreds of microseconds per step, and whose datastore API is being replaced
(SimData/SimDevice) in pymodbus 3.x/4.

Supported functions: FC 23 (write registers 0–3 and read any range within 0–31: one plant step
when the write covers exactly registers 0–3), FC 3 (read holding registers), FC 1 (read coils:
coil 0 = e-stop latched) and FC 5 (write coil 0 ON = e-stop). Anything else gets the Modbus
exception ILLEGAL_FUNCTION or ILLEGAL_ADDRESS.

``transport="tcp"`` listens on ``host:port`` (port 0 = a free port, reported in
``connection``). **Several units on one server:** a twin started on the ``host:port`` of a
running twin (same process) does not listen again: it joins that server as another Modbus unit
(``device_id``), with its own controller, register file, e-stop coil, faults and watchdog. The
server routes each request by its unit id (an unknown unit gets the exception GATEWAY TARGET
DEVICE FAILED TO RESPOND, as from a gateway) and is served by whichever unit's thread holds it.
A unit is a :class:`pymodbus.datastore.ModbusDeviceContext` in pymodbus' own server; that
context API is deprecated in pymodbus 3.x (replaced by SimData/SimDevice in 4) and sits behind
the asyncio server, so the routing here is the dictionary lookup it would do.

``transport="rtu"`` opens a pseudo-terminal pair with :func:`os.openpty` and
serves the master side (``connection["device"]`` = the slave path), or serves an existing
serial ``device``; no socat is needed. An RTU frame ends when the line is idle for one poll
period or when it is complete by length, whichever comes first.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import ReadCoilsResponse, WriteSingleCoilResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadWriteMultipleRegistersResponse,
)
from rths_hil.drivers.base import DISPLACEMENT_LSB, FORCE_LSB, INVALID_S32, Status
from rths_hil.drivers.modbus.driver import COIL_ESTOP, REG, WRITE_ADDRESS, WRITE_COUNT, feedback_crc
from rths_hil.drivers.modbus.transport import MAX_UNIT

from rths_hil.errors import InputError

from ..faults import Faults
from ..registry import TwinEntry
from .base import TwinController, TwinEndpoint
from .modbus_profile import SERVER_KEYS, ModbusProfileTwin
from .modbus_server import Conn, ModbusServer, ServerRules

if TYPE_CHECKING:
    from rths_hil.keys import Key

__all__ = ["ModbusServer", "ModbusTwin"]

N_REGISTERS = 32
_S32_MAX = 2**31 - 1
_FB = struct.Struct(">HHii")


def _s32(value: float, lsb: float) -> int:
    if value != value or value in (float("inf"), float("-inf")):
        return INVALID_S32
    return max(-_S32_MAX, min(_S32_MAX, round(value / lsb)))


#: How the built-in twin's server answers (:class:`.ServerRules`): several units behind one TCP
#: listener (``twin serve --device-id 1 --device-id 2``), so a request for a unit it does not
#: have is answered as a gateway answers it; each response written as it is made (its driver
#: sends one request and waits for its answer, nothing is pipelined); a broadcast answered with
#: the request's unit id.
_RULES = ServerRules(shared=True, gateway=True, batch=False, reply_own_unit=False)


class ModbusTwin(TwinEndpoint):
    """One Modbus unit (a :class:`TwinController`) of a TCP server or an RTU slave.

    Several ``ModbusTwin`` on one ``host:port`` are units of one :class:`ModbusServer`.
    """

    name = "modbus"
    poll = 0.02
    CONNECTION: ClassVar[Mapping[str, Key]] = SERVER_KEYS

    @classmethod
    def connection_from_args(cls, args: Any) -> dict[str, Any]:
        """``--transport`` (tcp, rtu), ``--host``/``--port``, ``--device`` (RTU) and the first
        ``--device-id``."""
        conn = super().connection_from_args(args)
        units = cls.serve_units(args)
        if args.device_id or not getattr(args, "profile", None):
            conn["device_id"] = units[0]  # with a profile: its [modbus] unit by default
        if conn.get("transport") == "rtu" and args.device:
            conn["device"] = args.device
        return conn

    @classmethod
    def profile_twin(cls) -> type[TwinEndpoint]:
        """A lab's own register map: :class:`~.modbus_profile.ModbusProfileTwin`."""
        return ModbusProfileTwin

    @classmethod
    def serve_units(cls, args: Any) -> list[Any]:
        """The ``--device-id`` units (default 1): several only over TCP, each once."""
        units = args.device_id or [1]
        if len(units) > 1 and (args.transport or "tcp") != "tcp":
            raise InputError("--device-id given several times: several units are served over TCP")
        if len(set(units)) != len(units):
            raise InputError(f"--device-id: unit ids repeat: {units}")
        return list(units)

    @classmethod
    def unit_connection(cls, first: dict[str, Any], unit: Any, args: Any) -> dict[str, Any]:
        """The next unit joins the first one's TCP server."""
        return dict(first, device_id=unit, allow_remote=args.allow_remote)

    def __init__(
        self,
        controller: TwinController,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 0,
        allow_remote: bool = False,
        device: str | None = None,
        device_id: int = 1,
        baudrate: int = 115200,
    ) -> None:
        super().__init__(controller)
        if transport not in ("tcp", "rtu"):
            raise InputError(f"modbus twin: transport must be 'tcp' or 'rtu', got {transport!r}")
        if (
            isinstance(device_id, bool)
            or not isinstance(device_id, int)
            or not (1 <= device_id <= MAX_UNIT)
        ):
            raise InputError(
                f"modbus twin: device_id must be a unit id 1..{MAX_UNIT}, got {device_id!r}"
            )
        self.transport = transport
        self.host, self.port = host, port
        self.allow_remote = bool(allow_remote)
        self.device, self.device_id, self.baudrate = device, int(device_id), int(baudrate)
        self.registers = [0] * N_REGISTERS
        self.server: ModbusServer | None = None
        self._current: tuple[Conn, ModbusPDU] | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def _setup(self) -> None:
        srv = self.server = ModbusServer.join(self, _RULES)
        if self.transport == "tcp":
            assert srv.key is not None
            host, port = srv.key
            self.connection = {
                "transport": "tcp",
                "host": host,
                "port": port,
                "device_id": self.device_id,
            }
            self.where = f"modbus tcp {host}:{port} unit {self.device_id}"
        else:
            path = os.ttyname(srv.slave) if srv.slave is not None else self.device
            self.connection = {"transport": "rtu", "device": path, "device_id": self.device_id}
            self.where = str(path)

    def _teardown(self) -> None:
        if self.server is not None:  # (kept after the stop: which server served this unit)
            self.server.leave(self)

    def _go_away(self) -> None:
        """Disconnect fault: this unit falls silent; a server with no other unit closes."""
        super()._go_away()
        srv = self.server
        if srv is not None and all(u._gone for u in srv.units.values()):
            srv.close(keep_serial=True)  # (a serial port stays open, silent, until the stop)

    # -- serving --------------------------------------------------------------------------------
    def _serve_once(self, timeout: float) -> None:
        if self.server is None:
            self._stop.wait(timeout)
        else:  # (or waits while another unit's thread serves the server)
            self.server.serve(timeout, self._stop.wait)

    def _send(self, conn: Conn, response: ModbusPDU, dev_id: int, tid: int) -> None:
        assert self.server is not None
        self.server.send(conn, response, dev_id, tid)

    def handle(self, conn: Conn, pdu: ModbusPDU) -> None:
        """Answer one request of this unit (:meth:`.ModbusServer.serve` calls it)."""
        fc = pdu.function_code
        regs = self.registers
        ctl = self.controller
        dev_id, tid = pdu.dev_id, pdu.transaction_id
        if fc == 23:
            ra, rc = pdu.read_address, pdu.read_count  # type: ignore[attr-defined]
            wa, values = pdu.write_address, list(pdu.write_registers)  # type: ignore[attr-defined]
            if wa != WRITE_ADDRESS or len(values) != WRITE_COUNT or ra + rc > N_REGISTERS:
                self._send(conn, ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS), dev_id, tid)
                return
            regs[0:4] = values
            raw = (values[2] << 16) | values[3]
            raw -= (raw >> 31) << 32
            cmd = raw * DISPLACEMENT_LSB
            reply = ctl.command(values[0], cmd, bool(values[1] & 1))
            if reply is None:
                return  # command lost / stale: no response, as a controller that missed it
            self._current = (conn, pdu)
            self.emit(reply)
            self._current = None
        elif fc == 3:
            a, n = pdu.address, pdu.count
            if a + n > N_REGISTERS:
                self._send(conn, ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS), dev_id, tid)
                return
            if a <= REG["STATUS"] < a + n:
                self._refresh_status()
            self._send(conn, ReadHoldingRegistersResponse(registers=regs[a : a + n]), dev_id, tid)
        elif fc == 1:
            if pdu.address != COIL_ESTOP or pdu.count != 1:
                self._send(conn, ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS), dev_id, tid)
                return
            self._send(conn, ReadCoilsResponse(bits=[ctl.estop_latched]), dev_id, tid)
        elif fc == 5:
            if pdu.address != COIL_ESTOP:
                self._send(conn, ExceptionResponse(fc, ExcCodes.ILLEGAL_ADDRESS), dev_id, tid)
                return
            if pdu.bits[0]:
                ctl.estop()
            self._send(
                conn,
                WriteSingleCoilResponse(address=COIL_ESTOP, bits=[bool(pdu.bits[0])]),
                dev_id,
                tid,
            )
        else:
            self._send(conn, ExceptionResponse(fc, ExcCodes.ILLEGAL_FUNCTION), dev_id, tid)

    # -- feedback (called through emit() with the faults applied) ------------------------------
    def _refresh_status(self) -> None:
        """STATUS (and FB_CRC) show the controller's state now: a watchdog latch that happened
        after the last command is visible to a plain register read (FC 3)."""
        regs = self.registers
        keep = ~int(Status.ENABLED | Status.ESTOP_ACTIVE | Status.WATCHDOG) & 0xFFFF
        status = (regs[REG["STATUS"]] & keep) | self.controller.status()
        if status != regs[REG["STATUS"]]:
            regs[REG["STATUS"]] = status
            block = struct.pack(">6H", *regs[REG["FB_SEQ"] : REG["FB_SEQ"] + 6])
            regs[REG["FB_CRC"]] = feedback_crc(block)

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        regs = self.registers
        block = _FB.pack(
            seq & 0xFFFF,
            status & 0xFFFF,
            _s32(displacement, DISPLACEMENT_LSB),
            _s32(force, FORCE_LSB),
        )
        words = struct.unpack(">6H", block)
        base = REG["FB_SEQ"]
        regs[base : base + 6] = words
        regs[REG["FB_CRC"]] = feedback_crc(block)
        assert self._current is not None and self.server is not None
        _conn, pdu = self._current
        ra, rc = pdu.read_address, pdu.read_count  # type: ignore[attr-defined]
        resp = ReadWriteMultipleRegistersResponse(registers=regs[ra : ra + rc])
        resp.dev_id, resp.transaction_id = pdu.dev_id, pdu.transaction_id
        return [self.server.framer.buildFrame(resp)]

    def _corrupt(self, frame: bytes) -> bytes:
        # A line error inside the register data: caught by FB_CRC (TCP) or the RTU CRC.
        index = 7 + 2 + 5 if self.transport == "tcp" else 1 + 2 + 5
        return Faults.flip_bit(frame, min(index, len(frame) - 3))

    def _write(self, frame: bytes) -> None:
        if self._current is not None and self.server is not None:
            self.server.write_to(self._current[0], frame)


#: This endpoint in the twins' registry (the twin of the driver of this module's name,
#: :func:`rths_hil.sim_backends.registry.builtin_entry`).
TWIN = TwinEntry("rths_hil.sim_backends.endpoints.modbus:ModbusTwin", transports=("tcp", "rtu"))

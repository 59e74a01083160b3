"""Modbus twin endpoint: a Modbus TCP server on 127.0.0.1 or an RTU slave on a pseudo-terminal.

The register map is the one of :mod:`rths_hil.drivers.modbus`. Requests are decoded and responses
encoded with pymodbus's own framers (``FramerSocket``, ``FramerRTU``) and PDU classes
(``DecodePDU(is_server=True)``, ``ReadWriteMultipleRegistersResponse`` …), so any Modbus client
can talk to it; the event loop is a plain ``select`` loop in one thread rather than pymodbus's
asyncio server, whose per-request hops (``call_soon`` → ``run_coroutine_threadsafe`` →
datastore coroutines) would add hundreds of microseconds per step, and whose datastore API is
being replaced (SimData/SimDevice) in pymodbus 3.x/4.

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
import select
import socket
import struct
import threading
import time
import tty
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import serial
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import ReadCoilsResponse, WriteSingleCoilResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadWriteMultipleRegistersResponse,
)
from rths_hil.drivers.base import DISPLACEMENT_LSB, FORCE_LSB, INVALID_S32, Status
from rths_hil.drivers.modbus.driver import COIL_ESTOP, REG, WRITE_ADDRESS, WRITE_COUNT, feedback_crc
from rths_hil.drivers.modbus.transport import MAX_UNIT, check_request, framer, next_request

from rths_hil.errors import InputError

from ..faults import Faults
from .base import TwinController, TwinEndpoint, listen
from .modbus_profile import SERVER_KEYS, ModbusProfileTwin

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


class _Conn:
    """One client connection (TCP) or the serial line (RTU)."""

    __slots__ = ("buf", "fd", "sock")

    def __init__(self, fd: int, sock: socket.socket | None = None) -> None:
        self.fd, self.sock, self.buf = fd, sock, b""


class ModbusServer:
    """One Modbus TCP listener (or RTU line) and the units (:class:`ModbusTwin`) it serves.

    TCP servers are registered by ``(host, port)`` so that a twin started on the address of a
    running one joins it (:meth:`join`). ``serving`` is held by the thread that reads the
    sockets; every unit's thread tries it, so the server is served while any unit runs.
    """

    _registry: ClassVar[dict[tuple[str, int], ModbusServer]] = {}
    _lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, transport: str) -> None:
        self.transport = transport
        self.framer = framer(transport == "rtu", server=True)
        self.units: dict[int, ModbusTwin] = {}
        self.listener: socket.socket | None = None
        self.conns: list[_Conn] = []
        self.slave: int | None = None
        self.serial: Any = None
        self.key: tuple[str, int] | None = None
        self.serving = threading.Lock()
        self.accepted = 0  # TCP connections accepted

    @classmethod
    def join(cls, twin: ModbusTwin) -> ModbusServer:
        """The server ``twin`` is served by: a running one on its ``host:port``, else a new one.

        Raises
        ------
        InputError
            The unit is already served there, or the transport cannot be opened.
        """
        srv: ModbusServer | None
        if twin.transport != "tcp":
            srv = cls(twin.transport)
            srv._open_rtu(twin.device, twin.baudrate)
            srv.units[twin.device_id] = twin
            return srv
        with cls._lock:
            srv = cls._registry.get((str(twin.host), int(twin.port))) if twin.port else None
            if srv is None:
                srv = cls("tcp")
                srv.listener = listen(twin.host, twin.port, twin.allow_remote, "modbus twin")
                srv.key = (str(twin.host), int(srv.listener.getsockname()[1]))
                cls._registry[srv.key] = srv
            elif twin.device_id in srv.units:
                raise InputError(
                    f"modbus twin: unit {twin.device_id} is already served on "
                    f"{twin.host}:{twin.port}"
                )
            srv.units[twin.device_id] = twin
            return srv

    def leave(self, twin: ModbusTwin) -> None:
        """Stop serving ``twin``'s unit; the last unit closes the server."""
        with self._lock:
            if self.units.get(twin.device_id) is twin:
                del self.units[twin.device_id]
            if self.units:
                return
            if self.key is not None and self._registry.get(self.key) is self:
                del self._registry[self.key]
        self.close()

    def _open_rtu(self, device: str | None, baudrate: int) -> None:
        if device is None:
            master, slave = os.openpty()
            tty.setraw(slave)
            self.slave = slave
            self.conns = [_Conn(master)]
            return
        try:
            self.serial = serial.serial_for_url(device, baudrate=baudrate, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise InputError(f"modbus twin: cannot open {device!r}: {exc}") from None
        self.conns = [_Conn(self.serial.fd)]

    def close_conn(self, conn: _Conn) -> None:
        if conn in self.conns:
            self.conns.remove(conn)
        try:
            if conn.sock is not None:
                conn.sock.close()
            elif self.serial is None:
                os.close(conn.fd)
        except OSError:  # pragma: no cover
            pass

    def close(self, keep_serial: bool = False) -> None:
        """Close every connection, the listener and the pseudo-terminal (and the serial port)."""
        for conn in list(self.conns):
            self.close_conn(conn)
        if self.listener is not None:
            self.listener.close()
            self.listener = None
        if self.slave is not None:
            os.close(self.slave)
            self.slave = None
        if self.serial is not None and not keep_serial:
            self.serial.close()
            self.serial = None

    def _malformed(self, dev_id: int | None = None) -> None:
        unit = self.units.get(dev_id) if dev_id is not None else None
        if unit is None and self.units:
            unit = next(iter(self.units.values()))
        if unit is not None:
            unit.controller.stats.malformed += 1

    # -- serving --------------------------------------------------------------------------------
    def serve_once(self, timeout: float) -> None:
        """Wait up to ``timeout`` for requests and answer them (holding :attr:`serving`)."""
        rlist: list[Any] = [c.fd for c in self.conns]
        if self.listener is not None:
            rlist.append(self.listener)
        if not rlist:
            time.sleep(timeout)
            return
        ready = select.select(rlist, (), (), timeout)[0]
        if not ready:
            if self.transport == "rtu":
                for idle in self.conns:
                    if idle.buf:  # line idle: an incomplete RTU frame is garbage
                        self._malformed()
                        idle.buf = b""
            return
        for item in ready:
            if item is self.listener:
                sock, _ = self.listener.accept()
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self.conns.append(_Conn(sock.fileno(), sock))
                self.accepted += 1
                continue
            conn = next((c for c in self.conns if c.fd == item), None)
            if conn is None:
                continue
            try:
                data = os.read(conn.fd, 4096)
            except OSError:
                data = b""
            if not data:
                if conn.sock is not None:
                    self.close_conn(conn)
                continue
            conn.buf += data
            self._process(conn)

    def _process(self, conn: _Conn) -> None:
        frm = self.framer
        while conn.buf and conn in self.conns:
            got = next_request(frm, conn.buf)
            if got is None:
                return
            used, dev_id, tid, pdu_bytes = got
            conn.buf = conn.buf[used:]
            if not pdu_bytes:
                self._malformed()  # garbage (an RTU CRC error, no such function code)
                continue
            unit = self.units.get(dev_id)
            if unit is None and self.transport == "rtu":
                if dev_id != 0 or len(self.units) != 1:
                    continue  # another slave's request
                unit = next(iter(self.units.values()))
            if unit is None:  # TCP: a unit this server does not have
                self._malformed()
                exc = ExceptionResponse(pdu_bytes[0] & 0x7F, ExcCodes.GATEWAY_NO_RESPONSE)
                self.send(conn, exc, dev_id, tid)
                continue
            if unit._gone:
                continue  # this unit fell silent (disconnect fault)
            pdu = check_request(frm.decoder, pdu_bytes)
            if isinstance(pdu, ExceptionResponse):
                unit.controller.stats.malformed += 1
                self.send(conn, pdu, dev_id, tid)
                continue
            pdu.dev_id, pdu.transaction_id = dev_id, tid
            unit._dispatch(conn, pdu)

    def send(self, conn: _Conn, response: ModbusPDU, dev_id: int, tid: int) -> None:
        response.dev_id, response.transaction_id = dev_id, tid
        self.write_to(conn, self.framer.buildFrame(response))

    def write_to(self, conn: _Conn, frame: bytes) -> None:
        try:
            os.write(conn.fd, frame)
        except OSError:  # pragma: no cover - client gone
            pass


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
        self._current: tuple[_Conn, ModbusPDU] | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def _setup(self) -> None:
        srv = self.server = ModbusServer.join(self)
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
        srv = self.server  # kept after the stop: which server served this unit
        if srv is not None and srv.units.get(self.device_id) is self:
            srv.leave(self)

    def _go_away(self) -> None:
        """Disconnect fault: this unit falls silent; a server with no other unit closes."""
        super()._go_away()
        srv = self.server
        if srv is not None and all(u._gone for u in srv.units.values()):
            srv.close(keep_serial=True)

    # -- serving --------------------------------------------------------------------------------
    def _serve_once(self, timeout: float) -> None:
        srv = self.server
        if srv is not None and srv.serving.acquire(blocking=False):
            try:
                srv.serve_once(timeout)
            finally:
                srv.serving.release()
        else:  # another unit's thread serves the server
            self._stop.wait(timeout)

    def _send(self, conn: _Conn, response: ModbusPDU, dev_id: int, tid: int) -> None:
        assert self.server is not None
        self.server.send(conn, response, dev_id, tid)

    def _dispatch(self, conn: _Conn, pdu: ModbusPDU) -> None:
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

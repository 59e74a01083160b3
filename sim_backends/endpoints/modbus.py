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
``connection``). ``transport="rtu"`` opens a pseudo-terminal pair with :func:`os.openpty` and
serves the master side (``connection["device"]`` = the slave path), or serves an existing
serial ``device``; no socat is needed. An RTU frame ends when the line is idle for one poll
period or when it is complete by length, whichever comes first.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import tty
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import ReadCoilsResponse, WriteSingleCoilResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadWriteMultipleRegistersResponse,
)
from rths_hil.drivers.base import DISPLACEMENT_LSB, FORCE_LSB, INVALID_S32, Status
from rths_hil.drivers.modbus import COIL_ESTOP, REG, WRITE_ADDRESS, WRITE_COUNT, feedback_crc

from rths_hil.errors import InputError

from ..faults import Faults
from .base import TwinController, TwinEndpoint, listen

__all__ = ["ModbusTwin"]

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


class ModbusTwin(TwinEndpoint):
    """Modbus TCP server or RTU slave around a :class:`TwinController`."""

    name = "modbus"
    poll = 0.02

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
        self.transport = transport
        self.host, self.port = host, port
        self.allow_remote = bool(allow_remote)
        self.device, self.device_id, self.baudrate = device, int(device_id), int(baudrate)
        self.registers = [0] * N_REGISTERS
        self.framer = (FramerSocket if transport == "tcp" else FramerRTU)(DecodePDU(True))
        self._listener: socket.socket | None = None
        self._conns: list[_Conn] = []
        self._slave: int | None = None
        self._serial: Any = None
        self._current: tuple[_Conn, ModbusPDU] | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def _setup(self) -> None:
        if self.transport == "tcp":
            lst = listen(self.host, self.port, self.allow_remote, "modbus twin")
            self._listener = lst
            host, port = lst.getsockname()[:2]
            self.connection = {
                "transport": "tcp",
                "host": host,
                "port": port,
                "device_id": self.device_id,
            }
            self.where = f"modbus tcp {host}:{port}"
        elif self.device is None:
            master, slave = os.openpty()
            tty.setraw(slave)
            self._slave = slave
            self._conns = [_Conn(master)]
            path = os.ttyname(slave)
            self.connection = {"transport": "rtu", "device": path, "device_id": self.device_id}
            self.where = path
        else:
            import serial

            try:
                self._serial = serial.serial_for_url(self.device, baudrate=self.baudrate, timeout=0)
            except (serial.SerialException, OSError, ValueError) as exc:
                raise InputError(f"modbus twin: cannot open {self.device!r}: {exc}") from None
            self._conns = [_Conn(self._serial.fd)]
            self.connection = {
                "transport": "rtu",
                "device": self.device,
                "device_id": self.device_id,
            }
            self.where = self.device

    def _close_conn(self, conn: _Conn) -> None:
        if conn in self._conns:
            self._conns.remove(conn)
        try:
            if conn.sock is not None:
                conn.sock.close()
            elif self._serial is None:
                os.close(conn.fd)
        except OSError:  # pragma: no cover
            pass

    def _teardown(self) -> None:
        for conn in list(self._conns):
            self._close_conn(conn)
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    def _go_away(self) -> None:
        super()._go_away()
        for conn in list(self._conns):
            self._close_conn(conn)
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None

    # -- serving --------------------------------------------------------------------------------
    def _serve_once(self, timeout: float) -> None:
        rlist: list[Any] = [c.fd for c in self._conns]
        if self._listener is not None:
            rlist.append(self._listener)
        if not rlist:
            self._stop.wait(timeout)
            return
        ready = select.select(rlist, (), (), timeout)[0]
        if not ready:
            if self.transport == "rtu":
                for conn in self._conns:
                    if conn.buf:  # line idle: an incomplete RTU frame is garbage
                        self.controller.stats.malformed += 1
                        conn.buf = b""
            return
        for item in ready:
            if item is self._listener:
                sock, _ = self._listener.accept()
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._conns.append(_Conn(sock.fileno(), sock))
                continue
            conn = next((c for c in self._conns if c.fd == item), None)
            if conn is None:
                continue
            try:
                data = os.read(conn.fd, 4096)
            except OSError:
                data = b""
            if not data:
                if conn.sock is not None:
                    self._close_conn(conn)
                continue
            conn.buf += data
            self._process(conn)

    def _process(self, conn: _Conn) -> None:
        framer = self.framer
        while conn.buf and conn in self._conns:
            data = conn.buf
            if self.transport == "rtu":
                # pymodbus's RTU framer consumes the whole buffer; cut one frame by its size so
                # that back-to-back requests (e-stop then command) are both served.
                if len(data) < framer.MIN_SIZE:
                    return
                pdu_class = framer.decoder.lookupPduClass(data)
                if pdu_class is None:
                    self.controller.stats.malformed += 1
                    conn.buf = data[1:]  # hunt for the next frame start
                    continue
                size = pdu_class.calculateRtuFrameSize(data)
                if not size or len(data) < size:
                    return
                data = data[:size]
            used, dev_id, tid, pdu_bytes = framer.decode(data)
            if not used:
                if len(conn.buf) > 2 * framer.MAX_SIZE:
                    self.controller.stats.malformed += 1
                    conn.buf = b""
                return
            conn.buf = conn.buf[used:]
            if not pdu_bytes:
                self.controller.stats.malformed += 1  # RTU CRC error: garbage
                continue
            if self.transport == "rtu" and dev_id not in (self.device_id, 0):
                continue  # another slave's request
            pdu = framer.decoder.decode(pdu_bytes)
            if pdu is None:
                self.controller.stats.malformed += 1
                self._send(
                    conn,
                    ExceptionResponse(pdu_bytes[0] & 0x7F, ExcCodes.ILLEGAL_FUNCTION),
                    dev_id,
                    tid,
                )
                continue
            pdu.dev_id, pdu.transaction_id = dev_id, tid
            self._dispatch(conn, pdu)

    def _send(self, conn: _Conn, response: ModbusPDU, dev_id: int, tid: int) -> None:
        response.dev_id, response.transaction_id = dev_id, tid
        self._write_to(conn, self.framer.buildFrame(response))

    def _write_to(self, conn: _Conn, frame: bytes) -> None:
        try:
            os.write(conn.fd, frame)
        except OSError:  # pragma: no cover - client gone
            pass

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
        assert self._current is not None
        _conn, pdu = self._current
        ra, rc = pdu.read_address, pdu.read_count  # type: ignore[attr-defined]
        resp = ReadWriteMultipleRegistersResponse(registers=regs[ra : ra + rc])
        resp.dev_id, resp.transaction_id = pdu.dev_id, pdu.transaction_id
        return [self.framer.buildFrame(resp)]

    def _corrupt(self, frame: bytes) -> bytes:
        # A line error inside the register data: caught by FB_CRC (TCP) or the RTU CRC.
        index = 7 + 2 + 5 if self.transport == "tcp" else 1 + 2 + 5
        return Faults.flip_bit(frame, min(index, len(frame) - 3))

    def _write(self, frame: bytes) -> None:
        if self._current is not None:
            self._write_to(self._current[0], frame)

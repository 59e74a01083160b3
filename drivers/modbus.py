"""Modbus driver (TCP and RTU): one Read/Write Multiple Registers (FC 23) transaction per step.

Register map (holding registers, 0-based PDU addresses; 32-bit values are two registers, high
word first; full table with examples in ``docs/protocols.md``):

======  ===========  ==========================================================  =========
addr    name         meaning                                                     scaling
======  ===========  ==========================================================  =========
0       SEQ          step sequence number modulo 65536                           1
1       CONTROL      bit 0 enable (1 follow, 0 hold / acknowledge an e-stop)     —
2–3     COMMAND      commanded displacement, signed 32 bit                       1e-7 m
16      FB_SEQ       SEQ of the command this feedback answers                    1
17      STATUS       status flags (drivers.base.Status)                          —
18–19   DISPLACEMENT measured displacement, signed 32 bit, 0x80000000 = invalid  1e-7 m
20–21   FORCE        measured force, signed 32 bit, 0x80000000 = invalid         0.01 N
22      FB_CRC       CRC-16/CCITT-FALSE of registers 16–21 (12 bytes, big-end.)  —
coil 0  ESTOP        write ON (FC 5) = e-stop; reads back the latched state      —
======  ===========  ==========================================================  =========

Per step the driver sends one FC 23 request that writes registers 0–3 and reads 16–22; the
controller performs the write first (as FC 23 specifies), steps once and answers with the new
feedback. E-stop is a Write Single Coil (FC 5) on coil 0, sent at once without waiting.

The hot path packs the request and unpacks the response with precompiled ``struct`` layouts (a
few µs) instead of pymodbus's client stack; the tests check byte for byte that these frames are
the ones pymodbus's own ``ReadWriteMultipleRegistersRequest`` / ``FramerSocket`` /
``FramerRTU`` build, and a plain pymodbus client drives the twin using only this map. RTU frame
CRCs come from pymodbus (``FramerRTU.compute_CRC``). The driver waits with ``select`` on the
socket or serial descriptor: unlike pymodbus's synchronous RTU client it never polls in 1 ms
sleeps.
"""

from __future__ import annotations

import binascii
import math
import os
import select
import socket
import struct
import time
from typing import Any, ClassVar

import serial
from pymodbus.framer import FramerRTU

from rths_hil.errors import InputError

from .base import DISPLACEMENT_LSB, FORCE_LSB, INVALID_S32, Driver, Feedback, check_command
from .base import extend_seq as _extend_seq

__all__ = [
    "COIL_ESTOP",
    "FORCE_LSB",
    "READ_ADDRESS",
    "READ_COUNT",
    "REG",
    "WRITE_ADDRESS",
    "WRITE_COUNT",
    "ModbusDriver",
    "feedback_crc",
]

#: Register addresses by name (see the module docstring).
REG = {
    "SEQ": 0,
    "CONTROL": 1,
    "COMMAND": 2,
    "FB_SEQ": 16,
    "STATUS": 17,
    "DISPLACEMENT": 18,
    "FORCE": 20,
    "FB_CRC": 22,
}
WRITE_ADDRESS, WRITE_COUNT = 0, 4
READ_ADDRESS, READ_COUNT = 16, 7
COIL_ESTOP = 0
FC_RW = 23
FC_WRITE_COIL = 5

# MBAP + PDU of the FC 23 request and response (big-endian, Modbus byte order).
_TCP_REQ = struct.Struct(">HHHBBHHHHBHHi")
_TCP_RESP = struct.Struct(">HHHBBBHHiiH")
_RTU_REQ = struct.Struct(">BBHHHHBHHi")
_RTU_RESP = struct.Struct(">BBBHHiiHH")  # with the RTU CRC
_FB_REGS = struct.Struct(">HHiiH")  # registers 16..22
_crc_hqx = binascii.crc_hqx
_rtu_crc = FramerRTU.compute_CRC


def feedback_crc(block12: bytes) -> int:
    """FB_CRC: CRC-16/CCITT-FALSE (``binascii.crc_hqx``, init 0xFFFF) of registers 16–21."""
    return _crc_hqx(block12, 0xFFFF)


class ModbusDriver(Driver):
    """Lockstep actuator driver over Modbus TCP or RTU (see the module docstring).

    Parameters
    ----------
    transport : {"tcp", "rtu"}
        Modbus TCP (``host``/``port``) or RTU over a serial line (``device``).
    host, port : str, int
        TCP server.
    device : str
        RTU: serial device or pyserial URL (``/dev/ttyUSB0``, ``/dev/pts/N``).
    device_id : int
        Modbus unit / slave id (1–247).
    baudrate, parity, stopbits : int, str, int
        RTU line settings (8 data bits).
    connect_timeout : float
        TCP connect timeout (s).
    estop_timeout : float
        RTU: how long :meth:`estop` waits for the coil write echo (s).
    """

    name: ClassVar[str] = "modbus"

    def __init__(
        self,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        device: str | None = None,
        device_id: int = 1,
        baudrate: int = 115200,
        parity: str = "E",
        stopbits: int = 1,
        connect_timeout: float = 1.0,
        estop_timeout: float = 0.1,
    ) -> None:
        super().__init__()
        if transport not in ("tcp", "rtu"):
            raise InputError(f"modbus driver: transport must be 'tcp' or 'rtu', got {transport!r}")
        if transport == "rtu" and not device:
            raise InputError("modbus driver: transport 'rtu' needs device= (serial port or URL)")
        if not 0 <= int(device_id) <= 255:
            raise InputError(f"modbus driver: device_id {device_id} is not within 0..255")
        self.transport = transport
        self.host, self.port = str(host), int(port)
        self.device = device
        self.device_id = int(device_id)
        self.baudrate, self.parity, self.stopbits = int(baudrate), str(parity), int(stopbits)
        self.connect_timeout = float(connect_timeout)
        self.estop_timeout = float(estop_timeout)
        self._coil_ack = False
        self._stash: Feedback | None = None
        self._sock: socket.socket | None = None
        self._ser: Any = None
        self._fd: int | None = None
        self._buf = b""
        self._rtu = transport == "rtu"
        # MBAP length, unit id, function code and byte count of a good FC 23 response
        self._resp_head = struct.pack(">HHBBB", 0, _TCP_RESP.size - 6, self.device_id, FC_RW, 14)

    # -- transport ------------------------------------------------------------------------------
    def open(self) -> None:
        if self._fd is not None:
            return
        if self._rtu:
            try:
                ser = serial.serial_for_url(
                    self.device,
                    baudrate=self.baudrate,
                    parity=self.parity,
                    stopbits=self.stopbits,
                    bytesize=8,
                    timeout=0,
                )
            except (serial.SerialException, OSError, ValueError) as exc:
                raise InputError(f"modbus driver: cannot open {self.device!r}: {exc}") from None
            if not hasattr(ser, "fd"):
                ser.close()
                raise InputError(f"modbus driver: RTU needs a serial device, got {self.device!r}")
            self._ser, self._fd = ser, ser.fd
        else:
            try:
                sock = socket.create_connection((self.host, self.port), self.connect_timeout)
            except OSError as exc:
                raise InputError(
                    f"modbus driver: cannot connect to {self.host}:{self.port}: {exc}"
                ) from None
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)
            self._sock, self._fd = sock, sock.fileno()
        self._buf = b""

    def close(self) -> None:
        sock, ser = self._sock, self._ser
        self._sock = self._ser = self._fd = None
        try:
            if sock is not None:
                sock.close()
            if ser is not None:
                ser.close()
        except (OSError, serial.SerialException):  # pragma: no cover
            pass

    def _write(self, frame: bytes) -> None:
        if self._fd is None:
            try:
                self.open()  # reconnect after a lost connection
            except InputError:
                self.stats.send_errors += 1
                return
        try:
            os.write(self._fd, frame)  # type: ignore[arg-type]
        except OSError:
            self.stats.send_errors += 1
            self.stats.disconnects += 1
            self.close()

    # -- commands -------------------------------------------------------------------------------
    def send(self, seq: int, displacement: float, enable: bool = True) -> None:
        check_command(seq, displacement)
        s16 = seq & 0xFFFF
        raw = round(displacement / DISPLACEMENT_LSB)
        ctl = 1 if enable else 0
        if self._rtu:
            body = _RTU_REQ.pack(
                self.device_id, FC_RW, READ_ADDRESS, READ_COUNT, WRITE_ADDRESS, WRITE_COUNT,
                2 * WRITE_COUNT, s16, ctl, raw,
            )  # fmt: skip
            frame = body + _rtu_crc(body).to_bytes(2, "big")
        else:
            frame = _TCP_REQ.pack(
                s16, 0, _TCP_REQ.size - 6, self.device_id, FC_RW, READ_ADDRESS, READ_COUNT,
                WRITE_ADDRESS, WRITE_COUNT, 2 * WRITE_COUNT, s16, ctl, raw,
            )  # fmt: skip
        self._last_sent = seq
        self.stats.sent += 1
        self._write(frame)

    def estop(self) -> None:
        """Write coil 0 ON (FC 5).

        Over TCP the request is sent at once and its echo is skipped by :meth:`receive`. Over RTU
        (half-duplex: one request at a time on the line) the driver waits up to
        ``estop_timeout`` for the echo before returning; a feedback that arrives meanwhile is
        kept for the next :meth:`receive`.
        """
        self.stats.estops += 1
        pdu = struct.pack(">BHH", FC_WRITE_COIL, COIL_ESTOP, 0xFF00)
        if self._rtu:
            body = bytes((self.device_id,)) + pdu
            frame = body + _rtu_crc(body).to_bytes(2, "big")
        else:
            frame = struct.pack(">HHHB", 0xFFFF, 0, len(pdu) + 1, self.device_id) + pdu
        self._write(frame)
        if self._rtu:
            self._coil_ack = False
            deadline = time.perf_counter() + self.estop_timeout
            timeouts = self.stats.timeouts
            while not self._coil_ack:
                remaining = deadline - time.perf_counter()
                if remaining <= 0:
                    break
                fb = self.receive(remaining)
                if fb is not None:
                    self._stash = fb
            self.stats.timeouts = timeouts  # waiting for the echo is not a feedback timeout

    # -- feedback -------------------------------------------------------------------------------
    def receive(self, timeout: float) -> Feedback | None:
        stats = self.stats
        if self._stash is not None:
            fb, self._stash = self._stash, None
            return fb
        deadline = time.perf_counter() + timeout
        parse = self._parse_rtu if self._rtu else self._parse_tcp
        while True:
            while self._buf:
                fb, more = parse()
                if fb is not None:
                    return fb
                if not more:
                    break
            fd = self._fd
            remaining = deadline - time.perf_counter()
            if fd is None:
                stats.timeouts += 1
                return None
            try:
                ready = select.select((fd,), (), (), max(remaining, 0.0))[0]
                data = os.read(fd, 4096) if ready else b""
                if ready and not data:
                    raise ConnectionResetError("peer closed the connection")
            except (OSError, ValueError):
                stats.disconnects += 1
                stats.timeouts += 1
                self.close()
                return None
            if data:
                self._buf += data
            elif remaining <= 0:
                if self._rtu and self._buf:  # an idle line ends an RTU frame: drop the rest
                    stats.count_malformed("bad_length")
                    self._buf = b""
                stats.timeouts += 1
                return None

    def _deliver(self, raw_seq: int, status: int, rd: int, rf: int) -> Feedback | None:
        seq = _extend_seq(raw_seq, self._last_sent, 16)
        if not self._classify(seq):
            return None
        stats = self.stats
        stats.received += 1
        disp = math.nan if rd == INVALID_S32 else rd * DISPLACEMENT_LSB
        force = math.nan if rf == INVALID_S32 else rf * FORCE_LSB
        if rd == INVALID_S32 or rf == INVALID_S32:
            stats.invalid_values += 1
        return Feedback(seq, disp, force, status)

    def _parse_tcp(self) -> tuple[Feedback | None, bool]:
        """Handle the first complete ADU; return (feedback or None, keep parsing)."""
        buf = self._buf
        stats = self.stats
        if len(buf) == _TCP_RESP.size and buf[2:9] == self._resp_head:
            # fast path: exactly one well-formed FC 23 response for the last command
            tid, _, _, _, _, _, seq16, status, rd, rf, crc = _TCP_RESP.unpack(buf)
            last = self._last_sent
            if (
                tid == seq16 == (last & 0xFFFF)
                and last != self._last_delivered
                and crc == _crc_hqx(buf[9:21], 0xFFFF)
            ):
                self._buf = b""
                return self._deliver(seq16, status, rd, rf), False
        if len(buf) < 8:
            return None, False
        pid = (buf[2] << 8) | buf[3]
        length = (buf[4] << 8) | buf[5]
        if pid != 0 or not 2 <= length <= 254:
            stats.count_malformed("bad_header")
            self._buf = b""  # no way to resynchronise a TCP stream: drop what we have
            return None, False
        end = 6 + length
        if len(buf) < end:
            return None, False
        frame, self._buf = buf[:end], buf[end:]
        if frame[6] != self.device_id:
            stats.count_malformed("unknown_id")
            return None, True
        fc = frame[7]
        if fc == FC_RW:
            if end != _TCP_RESP.size or frame[8] != 2 * READ_COUNT:
                stats.count_malformed("bad_length")
                return None, True
            tid, _, _, _, _, _, seq16, status, rd, rf, crc = _TCP_RESP.unpack(frame)
            if crc != _crc_hqx(frame[9:21], 0xFFFF):
                stats.count_malformed("bad_crc")
                return None, True
            if tid != seq16:
                stats.count_malformed("bad_frame")
                return None, True
            return self._deliver(seq16, status, rd, rf), True
        if fc == FC_WRITE_COIL:
            return None, True  # e-stop acknowledged
        stats.count_malformed("modbus_exception" if fc & 0x80 else "unknown_function")
        return None, True

    def _parse_rtu(self) -> tuple[Feedback | None, bool]:
        buf = self._buf
        stats = self.stats
        if len(buf) < 5:
            return None, False
        if buf[0] != self.device_id:
            stats.count_malformed("unknown_id")
            self._buf = b""
            return None, False
        fc = buf[1]
        size = _RTU_RESP.size if fc == FC_RW else 8 if fc == FC_WRITE_COIL else 5
        if len(buf) < size:
            return None, False
        frame, self._buf = buf[:size], buf[size:]
        if _rtu_crc(frame[:-2]) != ((frame[-2] << 8) | frame[-1]):
            stats.count_malformed("bad_crc")
            self._buf = b""  # resynchronise on the next frame
            return None, False
        if fc == FC_RW:
            if frame[2] != 2 * READ_COUNT:
                stats.count_malformed("bad_length")
                return None, True
            _, _, _, seq16, status, rd, rf, crc, _ = _RTU_RESP.unpack(frame)
            if crc != _crc_hqx(frame[3:15], 0xFFFF):
                stats.count_malformed("bad_crc")
                return None, True
            return self._deliver(seq16, status, rd, rf), True
        if fc == FC_WRITE_COIL:
            self._coil_ack = True
            return None, True
        stats.count_malformed("modbus_exception" if fc & 0x80 else "unknown_function")
        return None, True

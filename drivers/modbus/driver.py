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
17      STATUS       status flags (rths_hil.drivers.base.Status)                 —
18–19   DISPLACEMENT measured displacement, signed 32 bit, 0x80000000 = invalid  1e-7 m
20–21   FORCE        measured force, signed 32 bit, 0x80000000 = invalid         0.01 N
22      FB_CRC       CRC-16/CCITT-FALSE of registers 16–21 (12 bytes, big-end.)  —
coil 0  ESTOP        write ON (FC 5) = e-stop; reads back the latched state      —
======  ===========  ==========================================================  =========

Per step the driver sends one FC 23 request that writes registers 0–3 and reads 16–22; the
controller performs the write first (as FC 23 specifies), steps once and answers with the new
feedback. E-stop is a Write Single Coil (FC 5) on coil 0: over Modbus TCP on a second
connection of the driver's own (idle but for the e-stop, so nothing outstanding on the step's
link delays it), read back (FC 1 on coil 0) and written again until it reads latched or 0.5 s
have passed; over RTU (or without that connection) on the line at once.

The hot path packs the request and unpacks the response with precompiled ``struct`` layouts (a
few µs) instead of pymodbus's client stack; the tests check byte for byte that these frames are
the ones pymodbus's own ``ReadWriteMultipleRegistersRequest`` / ``FramerSocket`` /
``FramerRTU`` build, and a plain pymodbus client drives the twin using only this map. RTU frame
CRCs come from pymodbus (``FramerRTU.compute_CRC``), an RTU response is cut by the size its
pymodbus PDU class computes (:func:`.transport.rtu_frame_size`). The connection is the package's
one transport (:class:`.transport.Link`), which waits with ``select`` on the socket or serial
descriptor: unlike pymodbus's synchronous RTU client it never polls in 1 ms sleeps.

**Several actuators on one Modbus TCP connection.** Each controller is a Modbus *unit*
(``device_id``, 1–247, the MBAP unit identifier). The drivers of the units on one server (same
``host`` and ``port``) share one TCP connection (:class:`.transport.Link`), as CAN nodes share one
bus: every request carries its unit id, and a driver that reads another unit's response off the
connection hands it to that unit's inbox, so every byte is read once. The requests of one step are
pipelined — every channel's FC 23 is written before any response is awaited, as Modbus TCP allows
several outstanding transactions on one connection — and told apart by the unit id and by the
transaction id: ``SEQ`` XOR ``slot << 8``, where ``slot`` is the driver's place on the connection
(0 for the first, so a single driver's transaction id is ``SEQ`` itself). A server that handles one
transaction at a time answers them in order; the cost is then its processing time per unit, not a
round trip per unit. RTU lines are not shared (one driver per serial line).
"""

from __future__ import annotations

import binascii
import logging
import math
import socket
import struct
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import ClassVar

from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..base import DISPLACEMENT_LSB, FORCE_LSB, INVALID_S32, Driver, Feedback, LinkDown
from ..base import extend_seq as _extend_seq
from .transport import CONNECTION_KEYS, Link, rtu_frame_size

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

log = logging.getLogger(__name__)

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
FC_READ_COILS = 1
#: How long :meth:`ModbusDriver.estop` keeps writing and reading back over its own connection.
ESTOP_WINDOW = 0.5

# MBAP + PDU of the FC 23 request and response (big-endian, Modbus byte order).
_TCP_REQ = struct.Struct(">HHHBBHHHHBHHi")
_TCP_RESP = struct.Struct(">HHHBBBHHiiH")
_RTU_REQ = struct.Struct(">BBHHHHBHHi")
_RTU_RESP = struct.Struct(">BBBHHiiHH")  # with the RTU CRC
_FB_REGS = struct.Struct(">HHiiH")  # registers 16..22
_crc_hqx = binascii.crc_hqx
_RTU_DECODER = DecodePDU(False)  # the response classes, to cut an RTU frame by its size
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
        Modbus unit / slave id (1–247); drivers of different units on one ``host:port`` share
        one TCP connection (module docstring).
    baudrate, parity, stopbits : int, str, int
        RTU line settings (8 data bits).
    connect_timeout : float
        TCP connect timeout (s).
    estop_timeout : float
        How long :meth:`estop` waits for the coil write's answer (s).
    estop_connection : bool
        Modbus TCP: a second connection of this driver's own, idle but for the e-stop, which
        goes out there at once (whatever is outstanding on the shared link), is read back
        (coil 0, FC 1) and written again until the controller reports it latched or 0.5 s
        have passed (:meth:`estop`). Without it (or when it cannot be opened) the e-stop is
        written on the link, unconfirmed until the loop's status poll.

    Attributes
    ----------
    estop_latched : bool or None
        After :meth:`estop` over its own connection: coil 0 read back (``None``: no answer).
    """

    name: ClassVar[str] = "modbus"
    honours_deadline: ClassVar[bool] = True  # select() on the socket or serial descriptor
    # the units on one connection read it for each other (their inboxes): a late receive is
    # counted, never moved to a reader thread (Driver.reader_fallback)
    reader_fallback: ClassVar[bool] = False
    CONNECTION: ClassVar[Mapping[str, Key]] = CONNECTION_KEYS

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
        estop_connection: bool = True,
    ) -> None:
        super().__init__()
        if transport == "rtu" and not device:
            raise InputError("modbus driver: transport 'rtu' needs device= (serial port or URL)")
        self.transport = transport
        self.host, self.port = str(host), int(port)
        self.device = device
        self.device_id = int(device_id)
        self.baudrate, self.parity, self.stopbits = int(baudrate), str(parity), int(stopbits)
        self.connect_timeout = float(connect_timeout)
        self.estop_timeout = float(estop_timeout)
        self.estop_connection = estop_connection
        self.estop_latched: bool | None = None
        self._coil_ack = False
        self._stash: Feedback | None = None
        self._link: Link | None = None
        self._inbox: deque[bytes] = deque()  # this unit's ADUs read off the link by another unit
        self._tid_x = 0  # transaction id = SEQ ^ _tid_x (the driver's slot on a shared link)
        self._rtu = transport == "rtu"
        # MBAP length, unit id, function code and byte count of a good FC 23 response
        self._resp_head = struct.pack(">HHBBB", 0, _TCP_RESP.size - 6, self.device_id, FC_RW, 14)

    # -- transport ------------------------------------------------------------------------------
    @property
    def link(self) -> Link | None:
        """The transport this driver uses (shared with the other units on it over TCP)."""
        return self._link

    def open(self) -> None:
        if self._link is not None:
            return
        self._inbox.clear()
        self._link = Link.get(self)
        if self.estop_connection:  # one for the link: the units on it share it
            self._link.open_estop()

    @property
    def _esock(self) -> socket.socket | None:
        link = self._link
        return None if link is None or not self.estop_connection else link.esock

    def close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.release(self, self.device_id)

    def _write(self, frame: bytes) -> None:
        link = self._link
        if link is None:
            self.stats.send_errors += 1
            return
        link.write(frame, self.stats, reconnect=True)

    # -- commands -------------------------------------------------------------------------------
    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
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
                s16 ^ self._tid_x, 0, _TCP_REQ.size - 6, self.device_id, FC_RW, READ_ADDRESS,
                READ_COUNT, WRITE_ADDRESS, WRITE_COUNT, 2 * WRITE_COUNT, s16, ctl, raw,
            )  # fmt: skip
        self._write(frame)

    def estop(self) -> None:
        """Write coil 0 ON (FC 5).

        Over TCP the request is sent at once and its echo is skipped by :meth:`receive`. Over RTU
        (half-duplex: one request at a time on the line) the driver waits up to
        ``estop_timeout`` for the echo before returning; a feedback that arrives meanwhile is
        kept for the next :meth:`receive`.
        """
        self.stats.estops += 1
        if self._esock is not None and self._estop_own():
            return
        pdu = struct.pack(">BHH", FC_WRITE_COIL, COIL_ESTOP, 0xFF00)
        if self._rtu:
            body = bytes((self.device_id,)) + pdu
            frame = body + _rtu_crc(body).to_bytes(2, "big")
        else:
            tid = 0xFFFF ^ self._tid_x
            frame = struct.pack(">HHHB", tid, 0, len(pdu) + 1, self.device_id) + pdu
        self._write(frame)
        if self._rtu:
            self._coil_ack = False
            deadline = time.perf_counter() + self.estop_timeout
            while not self._coil_ack and time.perf_counter() < deadline:
                try:
                    fb = self._recv_internal(deadline)
                except LinkDown:
                    break
                if fb is not None:
                    self._stash = fb  # a feedback, not yet classified: for the next receive

    def _estop_own(self) -> bool:
        """The e-stop over its own connection: write coil 0 ON, read it back, again until it
        reads latched or ``ESTOP_WINDOW`` has passed. False: the connection is gone (the
        caller writes the e-stop on the link instead)."""
        link = self._link
        assert link is not None
        end = time.perf_counter() + ESTOP_WINDOW
        write = struct.pack(">BHH", FC_WRITE_COIL, COIL_ESTOP, 0xFF00)
        read = struct.pack(">BHH", FC_READ_COILS, COIL_ESTOP, 1)
        self.estop_latched = None
        writes = 0
        try:
            while time.perf_counter() < end:
                writes += 1
                for tid, pdu in ((0xFFFE ^ self._tid_x, write), (0xFFFD ^ self._tid_x, read)):
                    frame = struct.pack(">HHHB", tid, 0, len(pdu) + 1, self.device_id) + pdu
                    until = min(end, time.perf_counter() + self.estop_timeout)
                    got = link.ask(frame, tid, self.device_id, until)
                    if got is None:
                        break
                    if pdu is read and got[:2] == bytes((FC_READ_COILS, 1)) and len(got) > 2:
                        self.estop_latched = bool(got[2] & 1)
                if self.estop_latched:
                    break
        except OSError:  # (the link closed it)
            return False
        where = f"modbus driver: e-stop to unit {self.device_id} at {self.host}:{self.port}"
        if self.estop_latched:
            log.warning("%s over its own connection: latched (coil 0 reads ON)", where)
        else:
            state = "no answer" if self.estop_latched is None else "coil 0 reads OFF"
            log.error("%s: NOT confirmed after %d writes in 500 ms (%s)", where, writes, state)
        return True

    # -- feedback -------------------------------------------------------------------------------
    def _recv_internal(self, deadline: float) -> Feedback | None:
        fb: Feedback | None = self._stash
        if fb is not None:
            self._stash = None
            return fb
        inbox = self._inbox
        if inbox:  # read off the shared connection by another unit's driver
            return self._handle_tcp(inbox.popleft())
        link = self._link
        if link is None:
            raise LinkDown("modbus driver closed")
        parse = self._parse_rtu if self._rtu else self._parse_tcp
        fb = self._parse_all(link, parse)
        if fb is not None:
            return fb
        if link.fd is None:
            raise LinkDown("modbus connection lost")
        remaining = deadline - time.perf_counter()
        try:
            data = link.read(remaining)
        except (OSError, ValueError):
            self.stats.disconnects += 1
            link.disconnect()
            raise LinkDown("modbus connection lost") from None
        if data:
            link.buf += data
            return self._parse_all(link, parse)
        if remaining <= 0 and self._rtu and link.buf:
            # an idle line ends an RTU frame: drop the rest
            self.stats.count_malformed("bad_length")
            link.buf = b""
        return None

    @staticmethod
    def _parse_all(
        link: Link, parse: Callable[[Link], tuple[Feedback | None, bool]]
    ) -> Feedback | None:
        """The first feedback among the frames in ``link.buf`` (``parse`` takes them one by
        one), or ``None`` when none is complete."""
        while link.buf:
            fb, more = parse(link)
            if fb is not None:
                return fb
            if not more:
                break
        return None

    def _deliver(self, raw_seq: int, status: int, rd: int, rf: int) -> Feedback | None:
        seq = _extend_seq(raw_seq, self._last_sent, 16)
        disp = math.nan if rd == INVALID_S32 else rd * DISPLACEMENT_LSB
        force = math.nan if rf == INVALID_S32 else rf * FORCE_LSB
        return Feedback(seq, disp, force, status)

    def _parse_tcp(self, link: Link) -> tuple[Feedback | None, bool]:
        """Take the first complete ADU off ``link``; return (feedback or None, keep parsing).

        Another unit's response goes to that unit's inbox (a shared connection).
        """
        buf = link.buf
        n = _TCP_RESP.size
        if len(buf) >= n and buf[2:9] == self._resp_head:
            # fast path: a well-formed FC 23 response of this unit for the last command
            tid, _, _, _, _, _, seq16, status, rd, rf, crc = _TCP_RESP.unpack_from(buf)
            last = self._last_sent
            if (
                seq16 == (last & 0xFFFF)
                and tid == seq16 ^ self._tid_x
                and last != self._last_delivered
                and crc == _crc_hqx(buf[9:21], 0xFFFF)
            ):
                link.buf = buf[n:]
                return self._deliver(seq16, status, rd, rf), True
        if len(buf) < 8:
            return None, False
        pid = (buf[2] << 8) | buf[3]
        length = (buf[4] << 8) | buf[5]
        if pid != 0 or not 2 <= length <= 254:
            self.stats.count_malformed("bad_header")
            link.buf = b""  # no way to resynchronise a TCP stream: drop what we have
            return None, False
        end = 6 + length
        if len(buf) < end:
            return None, False
        frame, link.buf = buf[:end], buf[end:]
        if frame[6] != self.device_id:
            other = link.units.get(frame[6])
            if other is not None:  # another unit's response on the shared connection
                other._inbox.append(frame)
            else:
                self.stats.count_malformed("unknown_id")
            return None, True
        return self._handle_tcp(frame), True

    def _handle_tcp(self, frame: bytes) -> Feedback | None:
        """One complete ADU of this unit."""
        stats = self.stats
        fc = frame[7]
        if fc == FC_RW:
            if len(frame) != _TCP_RESP.size or frame[8] != 2 * READ_COUNT:
                stats.count_malformed("bad_length")
                return None
            tid, _, _, _, _, _, seq16, status, rd, rf, crc = _TCP_RESP.unpack(frame)
            if crc != _crc_hqx(frame[9:21], 0xFFFF):
                stats.count_malformed("bad_crc")
                return None
            if tid != seq16 ^ self._tid_x:
                stats.count_malformed("bad_frame")
                return None
            return self._deliver(seq16, status, rd, rf)
        if fc == FC_WRITE_COIL:
            return None  # e-stop acknowledged
        stats.count_malformed("modbus_exception" if fc & 0x80 else "unknown_function")
        return None

    def _parse_rtu(self, link: Link) -> tuple[Feedback | None, bool]:
        buf = link.buf
        stats = self.stats
        if len(buf) < 5:
            return None, False
        if buf[0] != self.device_id:
            stats.count_malformed("unknown_id")
            link.buf = b""
            return None, False
        fc = buf[1]
        size = rtu_frame_size(_RTU_DECODER, buf) or 5  # (an unknown function: its CRC)
        if len(buf) < size:
            return None, False
        frame, link.buf = buf[:size], buf[size:]
        if _rtu_crc(frame[:-2]) != ((frame[-2] << 8) | frame[-1]):
            stats.count_malformed("bad_crc")
            link.buf = b""  # resynchronise on the next frame
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

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
CRCs come from pymodbus (``FramerRTU.compute_CRC``). The driver waits with ``select`` on the
socket or serial descriptor: unlike pymodbus's synchronous RTU client it never polls in 1 ms
sleeps.

**Several actuators on one Modbus TCP connection.** Each controller is a Modbus *unit*
(``device_id``, 1–247, the MBAP unit identifier). The drivers of the units on one server
(same ``host`` and ``port``) share one TCP connection (:class:`Link`), as CAN nodes share one
bus: every request carries its unit id, and a driver that reads another unit's response off the
connection hands it to that unit's inbox, so every byte is read once. The requests of one step
are pipelined — every channel's FC 23 is written before any response is awaited, as Modbus TCP
allows several outstanding transactions on one connection — and told apart by the unit id and by
the transaction id: ``SEQ`` XOR ``slot << 8``, where ``slot`` is the driver's place on the
connection (0 for the first, so a single driver's transaction id is ``SEQ`` itself). A server that
handles one transaction at a time answers them in order; the cost is then its processing time
per unit, not a round trip per unit. RTU lines are not shared (one driver per serial line).
"""

from __future__ import annotations

import binascii
import logging
import math
import os
import select
import socket
import struct
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any, ClassVar

import serial
from pymodbus.framer import FramerRTU

from rths_hil.errors import InputError

if TYPE_CHECKING:
    from rths_hil.linkbudget import LinkLoad

from .base import DISPLACEMENT_LSB, FORCE_LSB, INVALID_S32, Driver, Feedback, LinkDown
from .base import extend_seq as _extend_seq

__all__ = [
    "COIL_ESTOP",
    "FORCE_LSB",
    "MAX_UNIT",
    "READ_ADDRESS",
    "READ_COUNT",
    "REG",
    "WRITE_ADDRESS",
    "WRITE_COUNT",
    "Link",
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
_rtu_crc = FramerRTU.compute_CRC


#: Highest Modbus unit id a controller can have (1–247; 0 is broadcast, 248–255 reserved).
MAX_UNIT = 247


def _await_tcp(
    sock: socket.socket, buf: bytes, tid: int, deadline: float
) -> tuple[bytes | None, bytes]:
    """The PDU of the Modbus TCP response ``tid`` on ``sock`` before ``deadline`` (``None``:
    none), and the bytes read past it. Raises OSError when the connection is gone."""
    while True:
        while len(buf) >= 8:
            end = 6 + ((buf[4] << 8) | buf[5])
            if len(buf) < end:
                break
            frame, buf = buf[:end], buf[end:]
            if (frame[0] << 8) | frame[1] == tid:
                return frame[7:], buf
        remaining = deadline - time.perf_counter()
        if remaining <= 0 or not select.select((sock,), (), (), remaining)[0]:
            return None, buf
        data = sock.recv(4096)
        if not data:
            raise ConnectionResetError("closed")
        buf += data


def feedback_crc(block12: bytes) -> int:
    """FB_CRC: CRC-16/CCITT-FALSE (``binascii.crc_hqx``, init 0xFFFF) of registers 16–21."""
    return _crc_hqx(block12, 0xFFFF)


class Link:
    """One transport (a TCP connection or a serial line) and the drivers of the units on it.

    A TCP link is shared by every driver in the process with the same ``host`` and ``port``
    (:meth:`get`); a serial line belongs to one driver. ``fd`` is ``None`` while the transport
    is down; the next write reconnects it.

    Attributes
    ----------
    fd : int or None
        Descriptor the drivers read and write.
    buf : bytes
        Bytes read but not yet parsed (shared: a read may hold several units' responses).
    units : dict
        Unit id → the driver of that unit on this link.
    """

    _shared: ClassVar[dict[tuple, Link]] = {}
    _lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, key: tuple | None, opener: Any) -> None:
        self.key = key
        self._opener = opener
        self.sock: socket.socket | None = None
        self.ser: Any = None
        self.fd: int | None = None
        self.buf = b""
        self.units: dict[int, ModbusDriver] = {}
        #: TCP: the e-stop's own connection, shared by the units (ModbusDriver.estop)
        self.esock: socket.socket | None = None

    @classmethod
    def get(cls, driver: ModbusDriver) -> Link:
        """The link of ``driver`` (TCP: shared by host and port), with the driver registered.

        Raises
        ------
        InputError
            Another open driver already speaks to this unit on this link, or the transport
            cannot be opened.
        """
        if driver._rtu:
            link = cls(None, driver._open_serial)
            link.units[driver.device_id] = driver
            link.connect()
            return link
        key = ("tcp", driver.host, driver.port)
        with cls._lock:
            link = cls._shared.get(key)
            if link is None:
                link = cls(key, driver._open_socket)
                link.connect()
                cls._shared[key] = link
            elif driver.device_id in link.units:
                raise InputError(
                    f"modbus driver: unit {driver.device_id} is already open on "
                    f"{driver.host}:{driver.port} (give each channel its own device_id)"
                )
            used = {d._tid_x for d in link.units.values()}
            driver._tid_x = next(s << 8 for s in range(256) if s << 8 not in used)
            link.units[driver.device_id] = driver
            return link

    def connect(self) -> None:
        """Open the transport if it is down (raises InputError)."""
        if self.fd is None:
            self.sock, self.ser, self.fd = self._opener()
            self.buf = b""

    def disconnect(self) -> None:
        """Close the transport (the drivers stay registered; a write reconnects)."""
        sock, ser = self.sock, self.ser
        self.sock = self.ser = self.fd = None
        self.buf = b""
        try:
            if sock is not None:
                sock.close()
            if ser is not None:
                ser.close()
        except (OSError, serial.SerialException):  # pragma: no cover
            pass

    def release(self, driver: ModbusDriver) -> None:
        """Drop ``driver``; the last one closes the transport."""
        with self._lock:
            if self.units.get(driver.device_id) is driver:
                del self.units[driver.device_id]
            if self.units:
                return
            if self.key is not None and self._shared.get(self.key) is self:
                del self._shared[self.key]
        self.disconnect()
        esock, self.esock = self.esock, None
        if esock is not None:
            esock.close()


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
    profile_protocol: ClassVar[str | None] = "modbus"
    honours_deadline: ClassVar[bool] = True  # select() on the socket or serial descriptor

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
        if not isinstance(estop_connection, bool):
            raise InputError(
                f"modbus driver: estop_connection must be true or false, got {estop_connection!r}"
            )
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

    # -- what this driver knows about its links and its twin (rths_hil.drivers.base.Driver) --------
    @classmethod
    def link_key(cls, connection: dict[str, Any]) -> str:
        from rths_hil.linkbudget import modbus_link_key

        return modbus_link_key(dict(connection or {}))

    @classmethod
    def link_load(
        cls,
        connection: dict[str, Any],
        channels_on_link: int,
        fs: float,
        *,
        heartbeat_hz: float = 0.0,
    ) -> LinkLoad:
        from rths_hil.linkbudget import modbus_load

        return modbus_load(connection, channels_on_link, fs, heartbeat_hz=heartbeat_hz)

    @classmethod
    def profile_driver(cls) -> type[Driver]:
        """A lab's own register map: :class:`~.modbus_profile.ModbusProfileDriver`."""
        from .modbus_profile import ModbusProfileDriver

        return ModbusProfileDriver

    @classmethod
    def check_sharing(cls, channels: list[tuple[int, str, dict[str, Any], bool]]) -> None:
        """Modbus TCP channels on one ``host:port`` need distinct unit ids (``device_id``,
        1–247); a Modbus RTU line carries one channel."""
        seen: dict[tuple, str] = {}
        tcp = [
            (c.get("host", "127.0.0.1"), c.get("port", 502))
            for _, _, c, _ in channels
            if c.get("transport", "tcp") == "tcp"
        ]
        for i, name, conn, twin in channels:
            if conn.get("transport", "tcp") == "rtu":
                if twin and not conn.get("device"):
                    continue  # each twin gets a pseudo-terminal of its own
                key: tuple = ("rtu", conn.get("device"))
                if key in seen:
                    raise InputError(
                        f"actuators: channels {seen[key]!r} and {name!r} use one Modbus RTU line "
                        "(an RTU line carries one channel; use one serial port per channel or "
                        "Modbus TCP)"
                    )
                seen[key] = name
                continue
            if twin and not conn.get("port"):
                continue  # each twin gets a port of its own
            unit = conn.get("device_id", 1)
            host, port = conn.get("host", "127.0.0.1"), conn.get("port", 502)
            bad = isinstance(unit, bool) or not isinstance(unit, int) or not 1 <= unit <= MAX_UNIT
            if bad and tcp.count((host, port)) > 1:  # alone, a device may answer unit 255
                raise InputError(
                    f"actuators[{i}] ({name}).driver.connection.device_id: {unit!r} is not a "
                    "Modbus unit id (1–247) for a connection it shares"
                )
            key = ("tcp", host, port, unit)
            if key in seen:
                raise InputError(
                    f"actuators: channels {seen[key]!r} and {name!r} both use Modbus unit "
                    f"{unit} on {host}:{port} (driver.connection.device_id): give each channel "
                    "its own unit id"
                )
            seen[key] = name

    # -- transport ------------------------------------------------------------------------------
    def _open_serial(self) -> tuple[None, Any, int]:
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
        return None, ser, ser.fd

    def _open_socket(self) -> tuple[socket.socket, None, int]:
        try:
            sock = socket.create_connection((self.host, self.port), self.connect_timeout)
        except OSError as exc:
            raise InputError(
                f"modbus driver: cannot connect to {self.host}:{self.port}: {exc}"
            ) from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        return sock, None, sock.fileno()

    @property
    def link(self) -> Link | None:
        """The transport this driver uses (shared with the other units on it over TCP)."""
        return self._link

    def open(self) -> None:
        if self._link is not None:
            return
        self._inbox.clear()
        self._link = Link.get(self)
        link = self._link
        if not self._rtu and self.estop_connection and link.esock is None:
            try:  # one for the link: the units on it share it, as they share the link
                link.esock = self._open_socket()[0]
            except InputError as exc:
                log.info("modbus driver: no second connection for the e-stop (%s)", exc)

    @property
    def _esock(self) -> socket.socket | None:
        link = self._link
        return None if link is None or not self.estop_connection else link.esock

    def close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.release(self)

    def _write(self, frame: bytes) -> None:
        link = self._link
        if link is None:
            self.stats.send_errors += 1
            return
        if link.fd is None:
            try:
                link.connect()  # reconnect after a lost connection
            except InputError:
                self.stats.send_errors += 1
                return
        try:
            os.write(link.fd, frame)  # type: ignore[arg-type]
        except OSError:
            self.stats.send_errors += 1
            self.stats.disconnects += 1
            link.disconnect()

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
        sock = self._esock
        assert sock is not None
        end = time.perf_counter() + ESTOP_WINDOW
        write = struct.pack(">BHH", FC_WRITE_COIL, COIL_ESTOP, 0xFF00)
        read = struct.pack(">BHH", FC_READ_COILS, COIL_ESTOP, 1)
        buf = b""
        self.estop_latched = None
        writes = 0
        try:
            while time.perf_counter() < end:
                writes += 1
                for tid, pdu in ((0xFFFE ^ self._tid_x, write), (0xFFFD ^ self._tid_x, read)):
                    sock.send(struct.pack(">HHHB", tid, 0, len(pdu) + 1, self.device_id) + pdu)
                    until = min(end, time.perf_counter() + self.estop_timeout)
                    got, buf = _await_tcp(sock, buf, tid, until)
                    if got is None:
                        break
                    if pdu is read and got[:2] == bytes((FC_READ_COILS, 1)) and len(got) > 2:
                        self.estop_latched = bool(got[2] & 1)
                if self.estop_latched:
                    break
        except OSError:
            sock.close()
            if self._link is not None:
                self._link.esock = None
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
        if self._stash is not None:
            fb, self._stash = self._stash, None
            return fb
        inbox = self._inbox
        if inbox:  # read off the shared connection by another unit's driver
            return self._handle_tcp(inbox.popleft())
        link = self._link
        if link is None:
            raise LinkDown("modbus driver closed")
        parse = self._parse_rtu if self._rtu else self._parse_tcp
        while link.buf:
            fb, more = parse(link)
            if fb is not None:
                return fb
            if not more:
                break
        fd = link.fd
        if fd is None:
            raise LinkDown("modbus connection lost")
        remaining = deadline - time.perf_counter()
        try:
            ready = select.select((fd,), (), (), remaining if remaining > 0.0 else 0.0)[0]
            data = os.read(fd, 4096) if ready else b""
            if ready and not data:
                raise ConnectionResetError("peer closed the connection")
        except (OSError, ValueError):
            self.stats.disconnects += 1
            link.disconnect()
            raise LinkDown("modbus connection lost") from None
        if data:
            link.buf += data
            while link.buf:
                fb, more = parse(link)
                if fb is not None:
                    return fb
                if not more:
                    break
        elif remaining <= 0 and self._rtu and link.buf:
            # an idle line ends an RTU frame: drop the rest
            self.stats.count_malformed("bad_length")
            link.buf = b""
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
        size = _RTU_RESP.size if fc == FC_RW else 8 if fc == FC_WRITE_COIL else 5
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

"""The Modbus transport, written once: the client's connection and the framing both ends share.

As in pymodbus, the client (the drivers, :mod:`.driver` and :mod:`.profile`) and the server (the
twins, :mod:`rths_hil.sim_backends.endpoints.modbus` and ``.modbus_profile``) share one framer
and one PDU layer: pymodbus's ``FramerSocket`` / ``FramerRTU`` and ``DecodePDU`` (:func:`framer`),
an RTU frame cut by the size its PDU class computes from the header (:func:`rtu_frame_size`:
RTU carries no length field), the request checks the application protocol answers with an
exception (:func:`illegal_data_value`) and the exception codes' names (:data:`EXCEPTIONS`).

The client's connection is a :class:`Link`: a TCP connection (``TCP_NODELAY``, non-blocking)
or a serial line (8 data bits, non-blocking), opened by :func:`open_tcp` / :func:`open_serial`,
written with one ``os.write`` per call and read after ``select`` with the time left (never
polled in sleeps). A TCP link can be shared by the drivers of the units on one server
(:meth:`Link.get`): every byte is read once and a response for another unit goes to that unit's
inbox. Over TCP a link also holds the e-stop's own connection (:meth:`Link.open_estop`), idle
but for the e-stop and its read-back (:meth:`Link.ask`), so that an e-stop never waits behind a
request outstanding on the step's connection.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

import serial
from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU

from rths_hil.errors import InputError
from rths_hil.keys import Key, seconds

__all__ = [
    "CONNECTION_KEYS",
    "EXCEPTIONS",
    "MAX_UNIT",
    "Link",
    "check_request",
    "framer",
    "illegal_data_value",
    "next_request",
    "open_serial",
    "open_tcp",
    "openers",
    "rtu_frame_size",
]

#: The connection settings of a Modbus driver (``driver.connection``,
#: :attr:`Driver.CONNECTION <rths_hil.drivers.base.Driver.CONNECTION>`): the transport, its
#: line or server, the unit and the e-stop's timing.
CONNECTION_KEYS: dict[str, Key] = {
    "transport": Key(
        "choice", "tcp", choices=("tcp", "rtu"), doc="Modbus TCP (host, port) or RTU (device)"
    ),
    "host": Key("str", "127.0.0.1", doc="TCP: the controller's Modbus TCP server"),
    "port": Key("int", 502, lo=0, hi=65535, doc="TCP: its port"),
    "device": Key("str", None, doc="RTU: serial device or pyserial URL (/dev/ttyUSB0, /dev/pts/N)"),
    "device_id": Key(
        "int",
        1,
        lo=0,
        hi=255,
        doc="Modbus unit id; units on one host:port share one TCP connection",
    ),
    "baudrate": Key("int", 115200, unit="bit/s", lo=1, doc="RTU: line speed"),
    "parity": Key("choice", "E", choices=("N", "E", "O", "M", "S"), doc="RTU: parity"),
    "stopbits": Key("int", 1, lo=1, hi=2, doc="RTU: stop bits (8 data bits)"),
    "connect_timeout": seconds(1.0, "TCP: connect (and start-up check) timeout"),
    "estop_timeout": seconds(0.1, "how long one e-stop write waits for its answer"),
    "estop_connection": Key(
        "bool",
        True,
        doc="TCP: a second connection, idle but for the e-stop and its read-back",
    ),
}

log = logging.getLogger(__name__)

#: Highest Modbus unit id a controller can have (1–247; 0 is broadcast, 248–255 reserved).
MAX_UNIT = 247
#: Names of the Modbus exception codes a controller answers with (V1.1b3 §7).
EXCEPTIONS = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    6: "server device busy",
}
#: Quantity limits of the requests (MODBUS Application Protocol V1.1b3, §6.1–6.17).
_QTY = {1: 2000, 2: 2000, 3: 125, 4: 125, 15: 1968, 16: 123}

#: What opens a link: the TCP socket or the serial port, and the descriptor to read and write.
Opener = Callable[[], tuple[socket.socket | None, Any, int]]


# -- framing (client and server) -----------------------------------------------------------------
def framer(rtu: bool, server: bool = False) -> FramerRTU | FramerSocket:
    """pymodbus's framer of the transport: ``FramerRTU`` or ``FramerSocket`` over its
    ``DecodePDU`` of requests (``server``) or responses."""
    return (FramerRTU if rtu else FramerSocket)(DecodePDU(server))


def rtu_frame_size(decoder: DecodePDU, buf: bytes) -> int | None:
    """Size of the RTU frame at the head of ``buf`` as pymodbus's PDU class computes it from the
    header (0 or more than ``len(buf)``: not complete yet); ``None`` when no PDU class has its
    function code."""
    cls = decoder.lookupPduClass(buf)
    if cls is None:
        return None
    return int(cls.calculateRtuFrameSize(buf))


def illegal_data_value(pdu: bytes) -> bool:
    """A request whose fields the Modbus application protocol answers with exception 03
    (ILLEGAL DATA VALUE) — checked on the raw PDU, which pymodbus's request classes decode
    without these checks: a quantity out of 1…the function's limit, a byte count that is not
    the quantity's, data bytes that are not the byte count's, and an FC 5 output value other
    than 0x0000 or 0xFF00 (V1.1b3 §6.1–6.17)."""
    fc = pdu[0] if pdu else 0
    try:
        if fc == 5:
            return len(pdu) != 5 or struct.unpack_from(">H", pdu, 3)[0] not in (0, 0xFF00)
        if fc in (1, 2, 3, 4):
            return len(pdu) != 5 or not 1 <= struct.unpack_from(">H", pdu, 3)[0] <= _QTY[fc]
        if fc in (15, 16):
            qty, nbytes = struct.unpack_from(">HB", pdu, 3)
            want = 2 * qty if fc == 16 else -(-qty // 8)
            return not 1 <= qty <= _QTY[fc] or nbytes != want or len(pdu) != 6 + nbytes
        if fc == 23:
            rq, _, wq, nbytes = struct.unpack_from(">HHHB", pdu, 3)
            bad_q = not (1 <= rq <= 125 and 1 <= wq <= 121)
            return bad_q or nbytes != 2 * wq or len(pdu) != 10 + nbytes
    except struct.error:
        return True
    return False


def next_request(frm: FramerRTU | FramerSocket, buf: bytes) -> tuple[int, int, int, bytes] | None:
    """The request at the head of a server's ``buf``: ``(bytes used, unit id, transaction id,
    PDU)``, ``None`` while no whole frame is there.

    An RTU request is cut by the size its PDU class computes (pymodbus's RTU framer would take
    the whole buffer), so that back-to-back requests are each served. The PDU is empty for
    garbage to count and drop: an RTU frame with a wrong CRC, a function code no PDU class has
    (``used`` 1: the hunt for the next frame start), a TCP buffer that grew past two frames
    without one whole frame in it (all of it).
    """
    data = buf
    if isinstance(frm, FramerRTU):
        if len(buf) < frm.MIN_SIZE:
            return None
        size = rtu_frame_size(frm.decoder, buf)
        if size is None:
            return 1, 0, 0, b""
        if not size or len(buf) < size:
            return None
        data = buf[:size]
    used, dev_id, tid, pdu = frm.decode(data)
    if not used:
        return (len(buf), 0, 0, b"") if len(buf) > 2 * frm.MAX_SIZE else None
    return used, dev_id, tid, bytes(pdu)


def check_request(decoder: DecodePDU, pdu: bytes) -> ModbusPDU:
    """The request ``pdu`` decoded by pymodbus, or the exception response the application
    protocol gives it: ILLEGAL DATA VALUE (:func:`illegal_data_value`), ILLEGAL FUNCTION (no
    request class has its function code). A server answers an :class:`ExceptionResponse` as
    it is and counts it malformed."""
    if illegal_data_value(pdu):
        return ExceptionResponse(pdu[0], ExcCodes.ILLEGAL_VALUE)
    request = decoder.decode(pdu)
    if request is None:
        return ExceptionResponse(pdu[0] & 0x7F, ExcCodes.ILLEGAL_FUNCTION)
    return request


# -- the client's connection ---------------------------------------------------------------------
def open_tcp(host: str, port: int, timeout: float) -> socket.socket:
    """A TCP connection to a Modbus server: ``TCP_NODELAY``, non-blocking (raises InputError)."""
    try:
        sock = socket.create_connection((host, port), timeout)
    except OSError as exc:
        raise InputError(f"modbus driver: cannot connect to {host}:{port}: {exc}") from None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setblocking(False)
    return sock


def open_serial(device: str | None, baudrate: int, parity: str, stopbits: int) -> Any:
    """An RTU line: the serial device or pyserial URL, 8 data bits, non-blocking (raises
    InputError; a URL without a descriptor, such as ``loop://``, is refused)."""
    try:
        ser = serial.serial_for_url(
            device, baudrate=baudrate, parity=parity, stopbits=stopbits, bytesize=8, timeout=0
        )
    except (serial.SerialException, OSError, ValueError) as exc:
        raise InputError(f"modbus driver: cannot open {device!r}: {exc}") from None
    if not hasattr(ser, "fd"):
        ser.close()
        raise InputError(f"modbus driver: RTU needs a serial device, got {device!r}")
    return ser


def openers(d: Any) -> tuple[Opener, Callable[[], socket.socket]]:
    """What opens the transport of driver ``d`` (its ``_rtu``, ``device``, ``baudrate``,
    ``parity``, ``stopbits``, ``host``, ``port`` and ``connect_timeout``) and what opens the
    e-stop's own connection (TCP)."""

    def estop() -> socket.socket:
        return open_tcp(d.host, d.port, d.connect_timeout)

    def line() -> tuple[socket.socket | None, Any, int]:
        if d._rtu:
            ser = open_serial(d.device, d.baudrate, d.parity, d.stopbits)
            return None, ser, ser.fd
        sock = estop()
        return sock, None, sock.fileno()

    return line, estop


class Link:
    """One transport (a TCP connection or a serial line) and the drivers of the units on it.

    A TCP link of the built-in driver is shared by every driver in the process with the same
    ``host`` and ``port`` (:meth:`get`); a serial line, and a profile driver's connection,
    belong to one driver. ``fd`` is ``None`` while the transport is down; :meth:`connect`
    opens it again.

    Parameters
    ----------
    key : tuple or None
        The shared link's key (``("tcp", host, port)``); ``None``: the link of one driver.
    opener : callable
        Opens the transport: returns ``(socket or None, serial port or None, descriptor)``.
    estop_opener : callable, optional
        Opens the e-stop's own connection (TCP): returns its socket.

    Attributes
    ----------
    fd : int or None
        Descriptor the drivers read and write.
    buf : bytes
        Bytes read but not yet parsed (shared: a read may hold several units' responses).
    units : dict
        Unit id → the driver of that unit on this link.
    esock : socket.socket or None
        The e-stop's own connection (TCP), shared by the units on the link.
    """

    _shared: ClassVar[dict[tuple, Link]] = {}
    _lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(
        self,
        key: tuple | None,
        opener: Opener,
        estop_opener: Callable[[], socket.socket] | None = None,
    ) -> None:
        self.key = key
        self._opener = opener
        self._estop_opener = estop_opener
        self.sock: socket.socket | None = None
        self.ser: Any = None
        self.fd: int | None = None
        self.buf = b""
        self.units: dict[int, Any] = {}
        self.esock: socket.socket | None = None
        self.ebuf = b""

    @classmethod
    def get(cls, driver: Any) -> Link:
        """The link of the built-in driver ``driver`` (TCP: shared by host and port), with the
        driver registered under its unit id and given its slot (``driver._tid_x``).

        Raises
        ------
        InputError
            Another open driver already speaks to this unit on this link, or the transport
            cannot be opened.
        """
        line, estop = openers(driver)
        if driver._rtu:
            link = cls(None, line)
            link.units[driver.device_id] = driver
            link.connect()
            return link
        key = ("tcp", driver.host, driver.port)
        with cls._lock:
            shared = cls._shared.get(key)
            if shared is None:
                link = cls(key, line, estop)
                link.connect()
                cls._shared[key] = link
            elif driver.device_id in shared.units:
                raise InputError(
                    f"modbus driver: unit {driver.device_id} is already open on "
                    f"{driver.host}:{driver.port} (give each channel its own device_id)"
                )
            else:
                link = shared
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
        """Close the transport (the drivers stay registered; :meth:`connect` reopens it)."""
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

    def release(self, driver: Any, unit: int) -> None:
        """Drop ``driver`` (of ``unit``); the last one closes the transport and the e-stop's
        connection."""
        with self._lock:
            if self.units.get(unit) is driver:
                del self.units[unit]
            if self.units:
                return
            if self.key is not None and self._shared.get(self.key) is self:
                del self._shared[self.key]
        self.disconnect()
        self.close_estop()

    def write(self, data: bytes, stats: Any, reconnect: bool = False) -> None:
        """Write ``data`` in one ``os.write``; a link that is down counts a send error
        (``reconnect``: it is opened again first), a failed write a disconnect too."""
        if self.fd is None and reconnect:
            try:
                self.connect()  # reconnect after a lost connection
            except InputError:
                pass
        fd = self.fd
        if fd is None:
            stats.send_errors += 1
            return
        try:
            os.write(fd, data)
        except OSError:
            stats.send_errors += 1
            stats.disconnects += 1
            self.disconnect()

    def read(self, timeout: float) -> bytes:
        """What arrives within ``timeout`` s (``b""``: nothing; another thread read it first).

        Raises
        ------
        OSError
            The connection is gone (closed by the peer, or the descriptor closed).
        ValueError
            The descriptor was closed meanwhile.
        """
        fd = self.fd
        if fd is None:
            raise ConnectionResetError("modbus connection closed")
        return self.recv(fd) if self.ready(fd, timeout) else b""

    @staticmethod
    def ready(fd: int, timeout: float) -> bool:
        """Whether ``fd`` is readable within ``timeout`` s (``select``; raises as :meth:`read`)."""
        return bool(select.select((fd,), (), (), timeout if timeout > 0.0 else 0.0)[0])

    def recv(self, fd: int) -> bytes:
        """Read what ``fd`` (found readable) holds: ``b""`` when it is no longer the link's or
        another thread read it meanwhile; raises ConnectionResetError when the peer closed."""
        if fd != self.fd:
            return b""
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            return b""
        if not data:
            raise ConnectionResetError("peer closed the connection")
        return data

    # -- the e-stop's own connection (TCP) -------------------------------------------------------
    def open_estop(self) -> None:
        """Open the e-stop's own connection if the link has none (none when the controller
        refuses a second one: the e-stop then goes over the step's connection)."""
        if self.esock is not None or self._estop_opener is None:
            return
        try:
            self.esock, self.ebuf = self._estop_opener(), b""
        except InputError as exc:
            log.info("modbus driver: no second connection for the e-stop (%s)", exc)

    def close_estop(self) -> None:
        """Close the e-stop's own connection."""
        sock, self.esock = self.esock, None
        if sock is not None:
            sock.close()

    def ask(self, frame: bytes, tid: int, unit: int, deadline: float) -> bytes | None:
        """Write one Modbus TCP request on the e-stop's own connection and return the PDU of
        its answer (transaction ``tid`` of ``unit``; ``None``: none before ``deadline``), as
        pymodbus's ``FramerSocket`` cuts it. A lost connection is closed (the caller's next
        attempt goes over the step's connection) and raises OSError."""
        sock = self.esock
        if sock is None:
            return None
        dec = _TCP_FRAMER
        try:
            sock.send(frame)
            while True:
                while len(self.ebuf) >= 8:
                    used, dev_id, rtid, pdu = dec.decode(self.ebuf)
                    if not used:
                        break
                    self.ebuf = self.ebuf[used:]
                    if rtid == tid and dev_id == unit and pdu:
                        return bytes(pdu)
                remaining = deadline - time.perf_counter()
                if remaining <= 0 or not select.select((sock,), (), (), remaining)[0]:
                    return None
                data = sock.recv(4096)
                if not data:
                    raise ConnectionResetError("closed")
                self.ebuf += data
        except OSError:
            self.close_estop()
            raise


_TCP_FRAMER = framer(rtu=False)

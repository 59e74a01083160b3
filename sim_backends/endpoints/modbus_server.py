"""The server side of the Modbus twins, written once: the line, the ``select`` loop, the requests.

Both Modbus twins — the built-in register map (:class:`~.modbus.ModbusTwin`) and a lab's
profile (:class:`~.modbus_profile.ModbusProfileTwin`) — are units of a :class:`ModbusServer`:
it opens the transport (a TCP listener on ``host:port``, a pseudo-terminal pair of its own or
a serial ``device`` for RTU), accepts the TCP connections, waits for input with ``select``,
drops an incomplete RTU frame when the line falls idle (one poll period without a byte), cuts
the requests out of each connection's bytes with the framer the drivers use
(:func:`rths_hil.drivers.modbus.transport.next_request`: pymodbus's ``FramerSocket`` /
``FramerRTU`` and ``DecodePDU``), routes each to its unit by the unit id, answers a malformed
one with the exception response the application protocol gives it
(:func:`~rths_hil.drivers.modbus.transport.check_request`) and hands the others to the unit
(:meth:`ModbusUnit.handle`), which answers through :meth:`ModbusServer.send` /
:meth:`ModbusServer.write_to`. What a request does (the register map, the profile) stays in
the twins.

The twins' servers differ where the controller they stand for does; each difference is a field
of :class:`ServerRules`, set by the twin.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import tty
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import serial
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from rths_hil.drivers.modbus.transport import check_request, framer, next_request

from rths_hil.errors import InputError

from .base import listen

if TYPE_CHECKING:
    from .base import TwinController

__all__ = ["Conn", "ModbusServer", "ModbusUnit", "ServerRules"]


@dataclass(frozen=True, slots=True)
class ServerRules:
    """Where the servers of the two Modbus twins differ (each twin sets its own).

    Attributes
    ----------
    shared : bool
        TCP: the server is registered by its ``host:port``, and a unit started on the address
        of a running one joins it (several units behind one listener, as a gateway serves
        them). Otherwise the server is the unit's own and a second twin on its port fails to
        listen.
    gateway : bool
        TCP: a request for a unit id the server does not have is answered with the exception
        GATEWAY TARGET DEVICE FAILED TO RESPOND, as from a gateway. Otherwise it is not
        answered (a single device ignores another unit's requests). Counted malformed either
        way.
    batch : bool
        The responses to the requests one read brought are written together, once the last is
        handled (a pipelined write + read is answered in one TCP segment). Otherwise each
        response is written as soon as it is made.
    reply_own_unit : bool
        RTU: a broadcast (unit 0) that the server's one unit answers is answered with that
        unit's id. Otherwise with the request's unit id, 0.
    """

    shared: bool
    gateway: bool
    batch: bool
    reply_own_unit: bool


class ModbusUnit(Protocol):
    """What :class:`ModbusServer` needs of a twin it serves."""

    transport: str
    host: str
    port: int
    allow_remote: bool
    device: str | None
    baudrate: int
    device_id: int
    controller: TwinController
    _gone: bool  # the disconnect fault: the unit fell silent

    def handle(self, conn: Conn, pdu: ModbusPDU) -> None:
        """Answer one well-formed request, whose ``dev_id`` and ``transaction_id`` are the
        response's."""


class Conn:
    """One client connection (TCP) or the serial line (RTU): its descriptor, its socket (TCP),
    the bytes not yet made into requests and, with :attr:`ServerRules.batch`, the responses not
    yet written."""

    __slots__ = ("buf", "fd", "out", "sock")

    def __init__(self, fd: int, sock: socket.socket | None = None) -> None:
        self.fd, self.sock, self.buf = fd, sock, b""
        self.out: list[bytes] = []


class ModbusServer:
    """One Modbus TCP listener (or RTU line) and the units (:class:`ModbusUnit`) it serves.

    ``serving`` is held by the thread that reads the line: every unit's thread tries it
    (:meth:`serve`), so the server is served while any of its units runs.

    Parameters
    ----------
    transport : str
        ``"tcp"`` or ``"rtu"``.
    rules : ServerRules
        How this twin's server answers (see :class:`ServerRules`).
    """

    _registry: ClassVar[dict[tuple[str, int], ModbusServer]] = {}
    _lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, transport: str, rules: ServerRules) -> None:
        self.transport = transport
        self.rules = rules
        self.framer = framer(transport == "rtu", server=True)
        self.units: dict[int, ModbusUnit] = {}
        self.listener: socket.socket | None = None
        self.conns: list[Conn] = []
        self.slave: int | None = None
        self.serial: Any = None
        self.key: tuple[str, int] | None = None
        self.serving = threading.Lock()
        self.accepted = 0  # TCP connections accepted

    # -- opening and closing ---------------------------------------------------------------------
    @classmethod
    def join(cls, unit: ModbusUnit, rules: ServerRules) -> ModbusServer:
        """The server ``unit`` is served by: with ``rules.shared``, a running one on its
        ``host:port``; else a new one on the unit's transport.

        Parameters
        ----------
        unit : ModbusUnit
            The twin: its transport, its ``host``/``port``/``allow_remote`` (TCP) or its
            ``device``/``baudrate`` (RTU) and its ``device_id``.
        rules : ServerRules
            The rules of a new server.

        Returns
        -------
        ModbusServer
            The server, with ``unit`` among its units.

        Raises
        ------
        InputError
            The unit is already served there, or the transport cannot be opened.
        """
        srv: ModbusServer | None
        if unit.transport != "tcp":
            srv = cls(unit.transport, rules)
            srv._open_rtu(unit.device, unit.baudrate)
            srv.units[unit.device_id] = unit
            return srv
        with cls._lock:
            srv = None
            if rules.shared and unit.port:
                srv = cls._registry.get((str(unit.host), int(unit.port)))
            if srv is None:
                srv = cls("tcp", rules)
                srv.listener = listen(unit.host, unit.port, unit.allow_remote, "modbus twin")
                srv.key = (str(unit.host), int(srv.listener.getsockname()[1]))
                if rules.shared:
                    cls._registry[srv.key] = srv
            elif unit.device_id in srv.units:
                raise InputError(
                    f"modbus twin: unit {unit.device_id} is already served on "
                    f"{unit.host}:{unit.port}"
                )
            srv.units[unit.device_id] = unit
            return srv

    def leave(self, unit: ModbusUnit) -> None:
        """Stop serving ``unit``; the last unit closes the server."""
        with self._lock:
            if self.units.get(unit.device_id) is unit:
                del self.units[unit.device_id]
            if self.units:
                return
            if self.key is not None and self._registry.get(self.key) is self:
                del self._registry[self.key]
        self.close()

    def _open_rtu(self, device: str | None, baudrate: int) -> None:
        """A pseudo-terminal pair of its own (the driver opens the slave end, which the server
        holds open too so that the line stays up between drivers), or ``device``."""
        if device is None:
            master, slave = os.openpty()
            tty.setraw(master)  # (on Linux the same as the slave's: a master's termios are its
            tty.setraw(slave)  # slave's; elsewhere each end is made raw)
            self.slave = slave
            self.conns = [Conn(master)]
            return
        try:
            self.serial = serial.serial_for_url(device, baudrate=baudrate, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise InputError(f"modbus twin: cannot open {device!r}: {exc}") from None
        self.conns = [Conn(self.serial.fd)]

    def close_conn(self, conn: Conn) -> None:
        """Close one connection (the serial port itself is closed by :meth:`close`)."""
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
        """Close every connection, the listener and the pseudo-terminal, and the serial port
        unless ``keep_serial`` (then only :meth:`close` without it closes the port)."""
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

    # -- serving ---------------------------------------------------------------------------------
    def serve(self, timeout: float, wait: Callable[[float], object]) -> None:
        """Serve for up to ``timeout`` s from the calling unit's thread, or ``wait`` (the unit's
        stop event's ``wait``) while another unit's thread serves the server."""
        if not self.serving.acquire(blocking=False):
            wait(timeout)
            return
        try:
            self._serve_once(timeout, wait)
        finally:
            self.serving.release()

    def _serve_once(self, timeout: float, wait: Callable[[float], object]) -> None:
        """Wait up to ``timeout`` for a connection or requests and answer them."""
        rlist: list[Any] = [c.fd for c in self.conns]
        if self.listener is not None:
            rlist.append(self.listener)
        if not rlist:  # closed (the disconnect fault)
            wait(timeout)
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
                self.conns.append(Conn(sock.fileno(), sock))
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
                else:  # nobody on the other end of the line (yet): do not spin on it
                    wait(timeout)
                continue
            conn.buf += data
            self._process(conn)

    def _process(self, conn: Conn) -> None:
        """Answer every complete request in ``conn``'s buffer (the rest of a frame comes with
        the next read)."""
        frm, rules = self.framer, self.rules
        while conn.buf and conn in self.conns:
            got = next_request(frm, conn.buf)
            if got is None:
                break
            used, dev_id, tid, pdu_bytes = got
            conn.buf = conn.buf[used:]
            if not pdu_bytes:
                self._malformed()  # garbage (an RTU CRC error, no such function code)
                continue
            unit = self.units.get(dev_id)
            reply_id = dev_id
            if unit is None and self.transport == "rtu":
                if dev_id != 0 or len(self.units) != 1:
                    continue  # another slave's request
                unit = next(iter(self.units.values()))  # a broadcast
                if rules.reply_own_unit:
                    reply_id = unit.device_id
            if unit is None:  # TCP: a unit this server does not have
                self._malformed()
                if rules.gateway:
                    exc = ExceptionResponse(pdu_bytes[0] & 0x7F, ExcCodes.GATEWAY_NO_RESPONSE)
                    self.send(conn, exc, dev_id, tid)
                continue
            if unit._gone:
                continue  # this unit fell silent (disconnect fault)
            pdu = check_request(frm.decoder, pdu_bytes)
            if isinstance(pdu, ExceptionResponse):
                unit.controller.stats.malformed += 1
                self.send(conn, pdu, reply_id, tid)
                continue
            pdu.dev_id, pdu.transaction_id = reply_id, tid
            unit.handle(conn, pdu)
        if conn.out:  # (batch) the responses to this read, in one write
            frames, conn.out = conn.out, []
            if conn in self.conns:  # (not when the disconnect fault closed it meanwhile)
                self._write(conn.fd, b"".join(frames))

    def _malformed(self) -> None:
        """Count garbage on the line: it belongs to no unit, the first one counts it."""
        if self.units:
            next(iter(self.units.values())).controller.stats.malformed += 1

    # -- answering -------------------------------------------------------------------------------
    def send(self, conn: Conn, response: ModbusPDU, dev_id: int, tid: int) -> None:
        """Frame ``response`` as unit ``dev_id``'s (transaction ``tid``) and write it to
        ``conn`` (:meth:`write_to`)."""
        response.dev_id, response.transaction_id = dev_id, tid
        self.write_to(conn, self.framer.buildFrame(response))

    def write_to(self, conn: Conn, frame: bytes) -> None:
        """Write one framed response to ``conn``: now, or with :attr:`ServerRules.batch` with
        the other responses to the same read."""
        if self.rules.batch:
            conn.out.append(frame)
        else:
            self._write(conn.fd, frame)

    @staticmethod
    def _write(fd: int, data: bytes) -> None:
        try:
            os.write(fd, data)
        except OSError:  # pragma: no cover - client gone
            pass

"""A lab's own actuator driver and its twin, outside rths_hil: one UDP datagram each way.

The worked example of ``docs/protocols.md`` ("Adding a driver"). The wire format, all
little-endian:

=========  ==================================================================  =====
datagram   fields                                                              bytes
=========  ==================================================================  =====
command    ``C``, seq u32, enable u8, displacement f64 (m)                     14
feedback   ``F``, seq u32, status u8 (rths_hil Status bits), displacement      22
           f64 (m), force f64 (N)
e-stop     ``E``                                                               1
heartbeat  ``H``                                                               1
=========  ==================================================================  =====

The driver implements only what the bus does — :meth:`UDPDriver._send_raw` writes a command,
:meth:`UDPDriver._recv_internal` returns the next feedback that arrived without waiting past the
deadline — and says what it knows about its link (:meth:`UDPDriver.link_key`,
:meth:`UDPDriver.link_load`, which the registry reads into the driver's protocol descriptor,
:meth:`rths_hil.drivers.protocol.Protocol.from_driver`). The base class keeps the sequence
rules, the timeouts and the counters. The twin is a
:class:`~rths_hil.sim_backends.endpoints.base.TwinEndpoint` around the same controller state
machine as the built-in twins (arming, e-stop latch, controller-side watchdog, faults). Each
declares the connection settings it takes (``CONNECTION``), which the configuration is read
against before anything starts. Both are found through the entry points in ``pyproject.toml``.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from collections.abc import Mapping
from typing import Any, ClassVar

from rths_hil.drivers.base import Driver, Feedback, LinkDown
from rths_hil.sim_backends.endpoints.base import TwinController, TwinEndpoint

from rths_hil.errors import InputError
from rths_hil.keys import Key
from rths_hil.linkbudget import LinkLoad

__all__ = ["COMMAND", "FEEDBACK", "UDPDriver", "UDPTwin"]

COMMAND = struct.Struct("<cIBd")
FEEDBACK = struct.Struct("<cIBdd")
#: IPv4 + UDP headers and the Ethernet frame around a datagram (bytes), for the link load.
UDP_OVERHEAD = 20 + 8 + 38


class UDPDriver(Driver):
    """Lockstep driver over UDP to ``host:port``.

    Parameters
    ----------
    host : str
        Controller address.
    port : int
        Controller UDP port.
    """

    name: ClassVar[str] = "mylab"
    #: ``driver.connection``: read (types, ranges, a misspelt key's closest match) before the
    #: driver is built; the defaults are ``__init__``'s
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        "host": Key("str", "127.0.0.1", doc="controller address"),
        "port": Key("int", 9000, lo=1, hi=65535, doc="controller UDP port"),
    }
    command_lsb: ClassVar[float | None] = None  # displacements travel as doubles
    honours_deadline: ClassVar[bool] = True  # select() with the time left

    def __init__(self, host: str = "127.0.0.1", port: int = 9000) -> None:
        super().__init__()
        self.host, self.port = str(host), int(port)
        self._sock: socket.socket | None = None

    def open(self) -> None:
        if self._sock is not None:
            return
        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.connect((self.host, self.port))
        except OSError as exc:
            raise InputError(f"mylab driver: cannot reach {self.host}:{self.port}: {exc}") from None
        sock.setblocking(False)
        self._sock = sock

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _write(self, data: bytes) -> None:
        try:
            self._sock.send(data)  # type: ignore[union-attr]
        except (OSError, AttributeError):
            self.stats.send_errors += 1

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        if seq > 0xFFFFFFFF:
            raise InputError(f"mylab driver: sequence number {seq} exceeds 32 bits")
        self._write(COMMAND.pack(b"C", seq, 1 if enable else 0, displacement))

    def _recv_internal(self, deadline: float) -> Feedback | None:
        sock = self._sock
        if sock is None:
            raise LinkDown("mylab driver closed")
        remaining = deadline - time.perf_counter()
        if not select.select((sock,), (), (), remaining if remaining > 0.0 else 0.0)[0]:
            return None
        try:
            data = sock.recv(64)
        except OSError:  # ICMP port unreachable: nobody listens (yet)
            self.stats.disconnects += 1
            return None
        if len(data) != FEEDBACK.size or data[:1] != b"F":
            self.stats.count_malformed("bad_frame")
            return None
        _, seq, status, disp, force = FEEDBACK.unpack(data)
        return Feedback(seq, disp, force, status)

    def estop(self) -> None:
        self.stats.estops += 1
        self._write(b"E")

    def heartbeat(self) -> None:
        self._write(b"H")

    @classmethod
    def link_key(cls, connection: dict[str, Any]) -> str:
        return f"mylab udp {connection.get('host', '127.0.0.1')}:{connection.get('port', 9000)}"

    @classmethod
    def link_load(
        cls,
        connection: dict[str, Any],
        channels_on_link: int,
        fs: float,
        *,
        heartbeat_hz: float = 0.0,
    ) -> LinkLoad:
        """UDP to the loopback interface has no limit; elsewhere an assumed 100 Mbit/s."""
        host = str(connection.get("host", "127.0.0.1"))
        bits = 8 * (COMMAND.size + FEEDBACK.size + 2 * UDP_OVERHEAD)
        frames = f"{channels_on_link} × ({COMMAND.size} + {FEEDBACK.size} bytes) at {fs:g} Hz"
        if host.startswith("127.") or host == "localhost":
            return LinkLoad(cls.link_key(connection), None, f"UDP loopback; {frames}",
                            channels=channels_on_link, fs=fs)  # fmt: skip
        rate = 100e6
        return LinkLoad(
            cls.link_key(connection),
            channels_on_link * bits * fs / rate,
            f"{frames} in UDP/IP/Ethernet of an assumed 100 Mbit/s",
            channels=channels_on_link,
            fs=fs,
            rate=rate,
            per_channel=bits / rate,
        )


class UDPTwin(TwinEndpoint):
    """The twin of :class:`UDPDriver`: a UDP socket on ``host:port`` (0: any free port)."""

    name = "mylab"
    seq_bits = None  # the command carries the full 32-bit step number
    #: what the twin takes (the driver is then given the address it bound)
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        "host": Key("str", "127.0.0.1", doc="twin: loopback address to bind"),
        "port": Key("int", 0, lo=0, hi=65535, doc="twin: UDP port (0: any free port)"),
    }

    def __init__(self, controller: TwinController, host: str = "127.0.0.1", port: int = 0) -> None:
        super().__init__(controller)
        if not str(host).startswith("127."):
            raise InputError(f"mylab twin: binds the loopback interface only, got {host!r}")
        self.host, self.port = str(host), int(port)
        self._sock: socket.socket | None = None
        self._peer: Any = None

    @classmethod
    def connection_from_args(cls, args: Any) -> dict[str, Any]:
        """``rths-hil twin serve --driver mylab [--host H] [--port P]``."""
        return {"host": args.host, "port": 0 if args.port is None else args.port}

    def _setup(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise InputError(f"mylab twin: cannot bind {self.host}:{self.port}: {exc}") from None
        self._sock = sock
        port = sock.getsockname()[1]
        self.connection = {"host": self.host, "port": port}
        self.where = f"udp {self.host}:{port}"

    def _teardown(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _serve_once(self, timeout: float) -> None:
        sock = self._sock
        if sock is None or not select.select((sock,), (), (), timeout)[0]:
            return
        data, self._peer = sock.recvfrom(64)
        ctl = self.controller
        if len(data) == COMMAND.size and data[:1] == b"C":
            _, seq, enable, disp = COMMAND.unpack(data)
            self.emit(ctl.command(seq, disp, bool(enable & 1)))
        elif data == b"E":
            ctl.estop()
        elif data == b"H":
            ctl.heartbeat()
        else:
            ctl.stats.malformed += 1

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        return [FEEDBACK.pack(b"F", seq, status & 0xFF, displacement, force)]

    def _corrupt(self, frame: bytes) -> bytes:
        return frame[:-1]  # a short datagram: the driver counts it as malformed

    def _write(self, frame: bytes) -> None:
        if self._sock is not None and self._peer is not None:
            try:
                self._sock.sendto(frame, self._peer)
            except OSError:  # pragma: no cover - peer gone
                pass

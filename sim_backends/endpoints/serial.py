"""Serial twin endpoint: the far end of a pseudo-terminal (or a TCP socket) speaking the
COBS/CRC frame format of :mod:`rths_hil.drivers.serial`.

``transport="pty"`` (default) opens a pseudo-terminal pair with :func:`os.openpty`; the twin
keeps the master side and the driver opens the slave path (``connection = {"url":
"/dev/pts/N"}``). ``transport="tcp"`` listens on ``host:port`` for one client at a time
(``connection = {"url": "socket://127.0.0.1:PORT"}``). The ``disconnect`` fault closes the
master side (the driver then reads end-of-file/EIO) or the client socket.
"""

from __future__ import annotations

import os
import select
import socket
import tty
from collections.abc import Mapping
from typing import Any, ClassVar

from rths_hil.drivers.serial.framing import (
    COMMAND,
    ESTOP_KEY,
    FEEDBACK,
    T_COMMAND,
    T_ESTOP,
    T_FEEDBACK,
    T_HEARTBEAT,
    cobs_frame,
    decode_frame,
    with_crc,
)
from rths_hil.drivers.serial.framing import encode_frame as _encode_frame

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..faults import Faults
from ..registry import TwinEntry
from .base import LISTEN_KEYS, TwinController, TwinEndpoint, listen

__all__ = ["SerialTwin"]


class SerialTwin(TwinEndpoint):
    """Serial twin on a pseudo-terminal (``transport="pty"``) or a TCP socket (``"tcp"``)."""

    name = "serial"
    #: The line the twin offers (the driver gets its ``url``); a TCP socket's listener.
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        "transport": Key(
            "choice",
            "pty",
            choices=("pty", "tcp"),
            doc="twin: the line it offers, a new pseudo-terminal (pty) or a TCP socket (tcp: "
            "host, port)",
        ),
        **LISTEN_KEYS,
    }

    def __init__(
        self,
        controller: TwinController,
        transport: str = "pty",
        host: str = "127.0.0.1",
        port: int = 0,
        allow_remote: bool = False,
    ) -> None:
        super().__init__(controller)
        if transport not in ("pty", "tcp"):
            raise InputError(f"serial twin: transport must be 'pty' or 'tcp', got {transport!r}")
        self.transport = transport
        self.host, self.port = host, port
        self.allow_remote = bool(allow_remote)
        self._fd: int | None = None  # pty master, or the connected client's socket fd
        self._slave: int | None = None
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._buf = b""

    def _setup(self) -> None:
        if self.transport == "pty":
            master, slave = os.openpty()
            tty.setraw(slave)
            self._fd, self._slave = master, slave
            path = os.ttyname(slave)
            self.connection = {"url": path}
            self.where = path
        else:
            lst = listen(self.host, self.port, self.allow_remote, "serial twin")
            self._listener = lst
            host, port = lst.getsockname()[:2]
            self.connection = {"url": f"socket://{host}:{port}"}
            self.where = f"socket://{host}:{port}"

    def _close_line(self) -> None:
        """Close the line: both ends of the pseudo-terminal (``pty``), or the connected client
        (``tcp``; the listener stays)."""
        if self.transport == "pty":
            for fd in (self._fd, self._slave):
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            self._slave = None
        elif self._client is not None:
            self._client.close()
            self._client = None
        self._fd = None

    def _teardown(self) -> None:
        self._close_line()
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def _go_away(self) -> None:
        super()._go_away()
        self._close_line()

    def _serve_once(self, timeout: float) -> None:
        if self.transport == "tcp" and self._client is None:
            if self._gone or self._listener is None:
                self._stop.wait(timeout)
                return
            if not select.select((self._listener,), (), (), timeout)[0]:
                return
            client, _ = self._listener.accept()
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client, self._fd, self._buf = client, client.fileno(), b""
            return
        fd = self._fd
        if fd is None:
            self._stop.wait(timeout)
            return
        if not select.select((fd,), (), (), timeout)[0]:
            return
        try:
            data = os.read(fd, 4096)
        except OSError:
            data = b""
        if not data:
            if self._client is not None:  # client hung up; wait for the next one
                self._client.close()
                self._client, self._fd = None, None
            return
        self._buf += data
        while b"\x00" in self._buf:
            frame, _, self._buf = self._buf.partition(b"\x00")
            if frame:
                self._handle(frame)

    def _handle(self, frame: bytes) -> None:
        ctl = self.controller
        body, _reason = decode_frame(frame)
        if body is None:
            ctl.stats.malformed += 1
            return
        kind = body[0]
        if kind == T_COMMAND and len(body) == COMMAND.size:
            _, seq, control, disp = COMMAND.unpack(body)
            self.emit(ctl.command(seq, disp, bool(control & 1)))
        elif kind == T_ESTOP and len(body) == 2 and body[1] == ESTOP_KEY:
            ctl.estop()
        elif kind == T_HEARTBEAT and len(body) == 2:
            ctl.heartbeat()
        else:
            ctl.stats.malformed += 1

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        return [_encode_frame(FEEDBACK.pack(T_FEEDBACK, seq, status & 0xFF, displacement, force))]

    def _corrupt(self, frame: bytes) -> bytes:
        # Flip a bit inside the CRC-protected body, keeping the COBS structure intact.
        body, _ = decode_frame(frame[:-1])
        assert body is not None
        return cobs_frame(Faults.flip_bit(with_crc(body), 8, 0))

    def _write(self, frame: bytes) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            os.write(fd, frame)
        except OSError:  # pragma: no cover - peer gone
            pass


#: This endpoint in the twins' registry (the twin of the driver of this module's name,
#: :func:`rths_hil.sim_backends.registry.builtin_entry`).
TWIN = TwinEntry(
    "rths_hil.sim_backends.endpoints.serial:SerialTwin",
    seq_bits=None,
    transports=("pty", "tcp"),
)

"""Serial driver: the frames of :mod:`.framing` (COBS, sequence number, CRC) over pyserial.

Any pyserial URL works: a device (``/dev/ttyUSB0``, a pseudo-terminal ``/dev/pts/N``),
``socket://host:port`` or ``loop://``. On POSIX ports the driver waits with ``select`` on the
file descriptor (no polling sleeps); other URL handlers use pyserial's own timeouts.
"""

from __future__ import annotations

import os
import select
import time
from collections.abc import Mapping
from typing import Any, ClassVar

import serial

from rths_hil.errors import InputError
from rths_hil.keys import REQUIRED, Key

from ..base import Driver, Feedback, LinkDown
from .framing import (
    COMMAND,
    ESTOP,
    ESTOP_KEY,
    FEEDBACK,
    HEARTBEAT,
    T_COMMAND,
    T_ESTOP,
    T_FEEDBACK,
    T_HEARTBEAT,
    decode_frame,
    encode_frame,
)

__all__ = ["SerialDriver"]

if os.name == "posix":
    from serial.serialposix import Serial as _PosixSerial
else:  # pragma: no cover - Windows
    _PosixSerial = None


class SerialDriver(Driver):
    """Lockstep actuator driver over a serial line (see the module docstring).

    Parameters
    ----------
    url : str
        pyserial port or URL (``/dev/ttyUSB0``, ``/dev/pts/3``, ``socket://127.0.0.1:5000``,
        ``loop://``).
    baudrate : int
        Line speed (ignored by pseudo-terminals and sockets).
    """

    name: ClassVar[str] = "serial"
    honours_deadline: ClassVar[bool] = True  # select() on POSIX ports, pyserial's own timeout
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        "url": Key(
            "str",
            REQUIRED,
            doc="serial device or pyserial URL (/dev/ttyUSB0, socket://host:port, loop://)",
        ),
        "baudrate": Key("int", 921600, unit="bit/s", lo=1, doc="line speed"),
    }
    command_lsb: ClassVar[float | None] = None  # displacements travel as IEEE-754 doubles

    def __init__(self, url: str, baudrate: int = 921600) -> None:
        super().__init__()
        self.url = str(url)
        self.baudrate = int(baudrate)
        self._ser: Any = None
        self._fd: int | None = None
        self._buf = b""
        self._hb = 0

    def open(self) -> None:
        if self._ser is not None:
            return
        try:
            ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise InputError(f"serial driver: cannot open {self.url!r}: {exc}") from None
        self._ser = ser
        self._fd = ser.fd if _PosixSerial is not None and isinstance(ser, _PosixSerial) else None
        self._buf = b""

    def close(self) -> None:
        ser, self._ser = self._ser, None
        self._fd = None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):  # pragma: no cover
                pass

    def _write(self, frame: bytes) -> None:
        if self._ser is None:
            try:
                self.open()  # reconnect after a lost line (sockets; a gone pty stays gone)
            except InputError:
                self.stats.send_errors += 1
                return
        ser = self._ser
        try:
            if self._fd is not None:
                os.write(self._fd, frame)
            else:
                ser.write(frame)
        except (serial.SerialException, OSError):
            self.stats.send_errors += 1

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        if seq > 0xFFFFFFFF:
            raise InputError(f"serial driver: sequence number {seq} exceeds 32 bits")
        self._write(encode_frame(COMMAND.pack(T_COMMAND, seq, 1 if enable else 0, displacement)))

    def estop(self) -> None:
        self.stats.estops += 1
        self._write(encode_frame(ESTOP.pack(T_ESTOP, ESTOP_KEY)))

    def heartbeat(self) -> None:
        self._hb = (self._hb + 1) & 0xFF
        self._write(encode_frame(HEARTBEAT.pack(T_HEARTBEAT, self._hb)))

    def _read(self, timeout: float) -> bytes | None:
        """Bytes available within ``timeout`` (b"" on timeout, None when the line is gone)."""
        fd = self._fd
        try:
            if fd is not None:
                if not select.select((fd,), (), (), timeout)[0]:
                    return b""
                data = os.read(fd, 4096)
                return data if data else None
            ser = self._ser
            ser.timeout = timeout
            data = ser.read(1)
            if data:
                n = ser.in_waiting
                if n:
                    data += ser.read(n)
            return data
        except (serial.SerialException, OSError):
            return None

    def _recv_internal(self, deadline: float) -> Feedback | None:
        if b"\x00" in self._buf:
            return self._drain()
        if self._ser is None:
            raise LinkDown("serial line closed")
        remaining = deadline - time.perf_counter()
        data = self._read(remaining if remaining > 0.0 else 0.0)
        if data is None:
            self.stats.disconnects += 1
            self.close()
            raise LinkDown("serial line gone")
        if data:
            self._buf += data
            if b"\x00" in self._buf:
                return self._drain()
        return None

    def _drain(self) -> Feedback | None:
        """Handle the first complete frame in the buffer."""
        stats = self.stats
        frame, _, self._buf = self._buf.partition(b"\x00")
        if not frame:
            return None
        body, reason = decode_frame(frame)
        if body is None:
            stats.count_malformed(reason or "bad_frame")
            return None
        if body[0] != T_FEEDBACK:
            stats.count_malformed("unknown_id")
            return None
        if len(body) != FEEDBACK.size:
            stats.count_malformed("bad_length")
            return None
        _, seq, status, disp, force = FEEDBACK.unpack(body)
        return Feedback(seq, disp, force, status)

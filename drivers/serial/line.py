"""The serial line (a UART), the physical layer several protocols share: the serial driver, Modbus
RTU and CAN through a USB–CAN adapter. Its characters (``1 + 8 + parity + stop`` bits,
:func:`bits_per_char`), the standard baud rates (:data:`BAUDRATES`, for "what would fit"), the
lines without a rate (:func:`serial_rate_kind`: pseudo-terminals, ``loop://`` and sockets to the
loopback interface report "no limit"; a connection that names no device is a twin's, whose own
pseudo-terminal pair is not checked) and the check of a device a twin serves
(:func:`check_device`). The link models of those protocols (their ``linkbudget`` modules) and
their ``twin serve`` options use it; the arithmetic every link shares is in
:mod:`rths_hil.linkbudget`.
"""

from __future__ import annotations

import os
import stat

from rths_hil.errors import InputError
from rths_hil.linkbudget import is_loopback

__all__ = ["BAUDRATES", "TWIN_PTY", "bits_per_char", "check_device", "serial_rate_kind"]

#: Standard serial baud rates, for "what would fit".
BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600, 1_000_000, 2_000_000)

#: Why a serial link without a device has no rate: only a twin serves one (its own pty).
TWIN_PTY = (
    "no device: the twin's own pseudo-terminal, which has no line rate (a real serial port, "
    "given as device or url, is checked at its baud rate)"
)


def bits_per_char(parity: str = "E", stopbits: float = 1) -> float:
    """Bits of one character on a serial line: start, 8 data bits, parity, stop bits.

    Parameters
    ----------
    parity : str
        ``N``, ``E``, ``O``, ``M`` or ``S`` (only the first letter counts, any case).
    stopbits : float
        Stop bits (1, 1.5 or 2).

    Returns
    -------
    float
        ``1 + 8 + (0 or 1) + stopbits``.

    Raises
    ------
    InputError
        An unknown parity.
    """
    p = str(parity).upper()[:1]
    if p not in ("N", "E", "O", "M", "S"):
        raise InputError(f"serial parity must be N, E, O, M or S, got {parity!r}")
    return 1 + 8 + (0 if p == "N" else 1) + float(stopbits)


def serial_rate_kind(device: str | None) -> str | None:
    """``None`` for a real UART; otherwise why the device has no rate limit (``device`` None:
    the twin's own pseudo-terminal, :data:`TWIN_PTY`).

    Parameters
    ----------
    device : str or None
        A serial device path or a pyserial URL (``loop://``, ``socket://host:port``).

    Returns
    -------
    str or None
        Why the line has no rate to check, or ``None``: a real serial port.
    """
    if device is None:
        return TWIN_PTY
    d = str(device)
    if "://" in d:
        scheme = d.split("://", 1)[0].lower()
        if scheme == "loop":
            return "loop:// has no line rate"
        if scheme == "socket":
            host = d.split("://", 1)[1].rsplit(":", 1)[0]
            if is_loopback(host):
                return "socket:// on the loopback interface has no line rate"
        return f"{scheme}:// URL: line rate unknown"
    if os.path.realpath(d).startswith(("/dev/pts/", "/dev/ptmx")):
        return "pseudo-terminal has no line rate"
    return None


def check_device(path: str, option: str = "--device") -> None:
    """Refuse a serial device to serve that does not exist or is not a character device.

    Parameters
    ----------
    path : str
        The device path.
    option : str
        The option that gave it, first in the message.

    Raises
    ------
    InputError
        One line: ``--device PATH: why``.
    """
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise InputError(f"{option} {path}: {exc.strerror}") from None
    if not stat.S_ISCHR(mode):
        raise InputError(f"{option} {path}: not a serial device (a character device)")

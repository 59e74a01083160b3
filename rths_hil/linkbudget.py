"""Link budget: how much of each bus's capacity a test uses, from the frames on the wire.

Every step each channel sends one command and receives one feedback. Before any software, the
bus has to carry those bits in time: this module computes, for each link, the fraction of its
capacity used per second from the frame sizes, the bit or baud rate and the loop rate, and
refuses a configuration above a limit (80 % by default) with one line saying what would fit.
The formulas (documented with a table of rates × channels in ``docs/protocols.md``):

**Classic CAN** (ISO 11898-1, 11-bit identifier, ``s`` data bytes). Without stuffing a data
frame plus the 3-bit interframe space is ``47 + 8s`` bits; the 34 + 8s bits from SOF to the end
of the CRC are bit-stuffed, at worst one stuff bit per 4 bits after the first
(Davis, Burns, Bril & Lukkien 2007, Eq. 1)::

    bits(s) = 47 + 8s + ⌊(34 + 8s − 1) / 4⌋          (8 bytes: 111 … 135 bits)
    load = channels · (bits(command) + bits(feedback)) · fs / bitrate

The frame lengths come from the DBC the driver uses (``drivers/can/actuator.dbc``: Command and
Feedback are 8 bytes each), or from a controller profile's DBC (29-bit identifiers counted as
extended frames: ``g`` = 54 in :func:`can_frame_bits`).

**CAN FD** (ISO 11898-1:2015, base format, for the "what would fit" advice): 34 bits at the
nominal rate (17 arbitration bits, ≤ 4 stuff bits in them, CRC delimiter, ACK, EOF, IFS) and at
the data rate ``5 + 8s`` (ESI, DLC, data), the remaining dynamic stuff bits
``⌊(21 + 8s)/4⌋ − 4``, the 4-bit stuff count, the CRC (17 bits up to 16 bytes, else 21) and
its fixed stuff bits ``⌈(4 + CRC)/4⌉``; ``s`` rounded up to a CAN FD length (…, 8, 12, 16, 20,
24, 32, 48, 64).

**Modbus RTU** (Modbus over Serial Line V1.02): one FC 23 transaction per channel and step —
request ``13 + 2·w`` bytes and response ``5 + 2·r`` bytes for ``w`` written and ``r`` read
registers (21 + 19 bytes with ``drivers/modbus.py``'s map, CRC included), each character
``1 + 8 + parity + stop`` bits (11 for the standard 8E1), and a silence of 3.5 characters after
each frame::

    T = (bytes_request + bytes_response + 2·3.5) · bits_per_char / baud
    load = channels · T · fs                         (one line, one master: transactions queue)

The spec recommends a fixed 1.75 ms silence above 19 200 baud; ``spec_silence=True`` uses it.

**Serial** (``drivers/serial.py``): COBS adds one byte per started 254 bytes and the frame ends
with a 0x00 delimiter: command 16 → 18 bytes, feedback 24 → 26 bytes, ``1 + 8 + parity + stop``
bits per character (the driver's 8N1: 10). In lockstep the feedback answers the command, so a
step needs the line for both frames in turn::

    load = channels · (bytes_command + bytes_feedback) · bits_per_char · fs / baud

**Modbus TCP** to another host: the MBAP frames (25 + 23 bytes) in TCP/IP/Ethernet segments
(+ 90 bytes each: preamble and interframe gap 20, Ethernet header and FCS 18, IPv4 20,
TCP with timestamps 32) on an assumed 100 Mbit/s link.

**CAN through a serial line** (python-can's ``slcan`` and ``serial`` interfaces: a USB–CAN
adapter, or the served CAN twin's pseudo-terminals). Each frame crosses the line between the
computer and the adapter as characters: ``slcan`` (Lawicel ASCII) ``t``, 3 hex identifier
digits, the DLC digit, 2 hex digits per data byte and CR = ``6 + 2s`` characters (8 bytes: 22);
python-can's ``serial`` framing 0xAA, 4-byte timestamp, DLC, 4-byte identifier, the data and
0xBB = ``11 + s`` bytes (8 bytes: 19); 10-bit characters (8N1). As on a serial line the two
frames of a step take the line in turn::

    load = channels · (chars_command + chars_feedback) · 10 · fs / baud

The baud rate is ``bus_options.tty_baudrate`` (``slcan``; or a channel ending in ``@baud``) or
``bus_options.baudrate`` (``serial``), python-can's default 115 200 otherwise. With a CAN
``bitrate`` too, the CAN bus behind the adapter is loaded as above and the larger of the two
loads is the link's.

Links without a rate — the python-can ``virtual`` bus, pseudo-terminals (so the served CAN
twin's ``slcan``/``serial`` pair), ``loop://`` and TCP to the loopback interface — report "no
limit". A Modbus RTU or serial connection that names no ``device`` / ``url`` is a twin's: the
twin opens a pseudo-terminal pair of its own (the drivers refuse a serial line without a device),
so its baud rate is not checked against the twin; a real serial port (``device`` or ``url``
given, with or without a twin on it) is checked at its baud rate. A CAN bus whose interface
sets the bit rate itself (no ``bitrate`` in the connection) reports its bits per step and "bit
rate unknown".

References
----------
R. I. Davis, A. Burns, R. J. Bril, J. J. Lukkien, "Controller Area Network (CAN) schedulability
analysis: refuted, revisited and revised", Real-Time Systems 35(3), 239–272, 2007.
ISO 11898-1:2015, Road vehicles — Controller area network (CAN) — Part 1.
Modbus Organization, "MODBUS over Serial Line, Specification and Implementation Guide V1.02",
2006, Section 2.5.1.1 (RTU framing, t3.5).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from typing import Any

from .errors import InputError
from .units import positive_number

log = logging.getLogger(__name__)

__all__ = [
    "CAN_FD_LENGTHS",
    "DEFAULT_LIMIT",
    "LinkLoad",
    "can_fd_frame_time",
    "can_frame_bits",
    "can_link_key",
    "can_load",
    "can_serial_frame_chars",
    "check_links",
    "cobs_frame_bytes",
    "format_loads",
    "link_key",
    "link_load",
    "modbus_link_key",
    "modbus_load",
    "modbus_rtu_frame_bytes",
    "rtu_transaction_time",
    "serial_frame_bytes",
    "serial_link_key",
    "serial_load",
]

#: Default refusal threshold: a link above 80 % of its capacity is refused.
DEFAULT_LIMIT = 0.8
#: Data lengths a CAN FD frame can carry (bytes).
CAN_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: Standard CAN bit rates (bit/s) and serial baud rates, for "what would fit".
CAN_BITRATES = (125_000, 250_000, 500_000, 1_000_000)
BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600, 1_000_000, 2_000_000)
#: Assumed rate of an Ethernet link to another host (bit/s).
ETHERNET_BITRATE = 100_000_000
#: Per-segment overhead of TCP/IPv4 on Ethernet (bytes): preamble+SFD 8, IFG 12, header 14,
#: FCS 4, IPv4 20, TCP with the timestamp option 32.
TCP_SEGMENT_OVERHEAD = 90
#: CAN FD rates used in the advice: 1 Mbit/s nominal, 5 Mbit/s data.
CAN_FD_RATES = (1_000_000, 5_000_000)
#: python-can interfaces that carry CAN frames over a serial line (see the module docstring).
CAN_SERIAL_INTERFACES = ("slcan", "serial")
#: python-can's default baud rate of those interfaces.
CAN_SERIAL_DEFAULT_BAUD = 115200


# --------------------------------------------------------------------------------------------
# frames on the wire
# --------------------------------------------------------------------------------------------
def can_frame_bits(data_bytes: int, *, stuffing: bool = True, extended: bool = False) -> int:
    """Bits a classic CAN data frame occupies on the bus, interframe space included.

    ``g + 8s + 13`` bits plus, with ``stuffing``, the worst-case stuff bits
    ``⌊(g + 8s − 1)/4⌋`` (Davis et al. 2007, Eq. 1), where ``g`` = 34 bits (11-bit id) or 54
    (29-bit id) are the stuffed control bits and 13 the CRC delimiter, ACK, EOF and IFS.
    An 8-byte standard frame: 111 bits without stuffing, 135 at worst.
    """
    s = int(data_bytes)
    if not 0 <= s <= 8:
        raise InputError(f"classic CAN carries 0–8 data bytes, got {data_bytes}")
    g = 54 if extended else 34
    stuff = (g + 8 * s - 1) // 4 if stuffing else 0
    return g + 8 * s + 13 + stuff


def can_fd_length(data_bytes: int) -> int:
    """The smallest CAN FD data length ≥ ``data_bytes`` (8, 12, 16, 20, 24, 32, 48, 64)."""
    for n in CAN_FD_LENGTHS:
        if n >= data_bytes:
            return n
    raise InputError(f"a CAN FD frame carries at most 64 data bytes, got {data_bytes}")


def can_fd_frame_time(
    data_bytes: int, nominal_bitrate: float = CAN_FD_RATES[0], data_bitrate: float = CAN_FD_RATES[1]
) -> float:
    """Worst-case time (s) of a CAN FD base-format frame with bit-rate switching.

    Nominal phase: 17 arbitration bits (SOF, 11-bit id, RRS, IDE, FDF, res, BRS), at most 4
    stuff bits in them, CRC delimiter, ACK slot and delimiter, EOF and IFS (13) — 34 bits.
    Data phase: ESI + DLC (5), the data (8s, ``s`` rounded up by :func:`can_fd_length`), the
    remaining dynamic stuff bits ``⌊(21 + 8s)/4⌋ − 4``, stuff count (4), CRC (17 or 21) and
    its fixed stuff bits ``⌈(4 + CRC)/4⌉`` (ISO 11898-1:2015).
    """
    s = can_fd_length(int(data_bytes))
    crc = 17 if s <= 16 else 21
    dynamic = (21 + 8 * s) // 4
    nominal_bits = 17 + 4 + 13
    data_bits = 5 + 8 * s + (dynamic - 4) + 4 + crc + math.ceil((4 + crc) / 4)
    return nominal_bits / float(nominal_bitrate) + data_bits / float(data_bitrate)


def modbus_rtu_frame_bytes(
    write_count: int | None = None, read_count: int | None = None
) -> tuple[int, int]:
    """Bytes of the FC 23 request and response on an RTU line, CRC included.

    Request: address, function, read address (2), read count (2), write address (2), write
    count (2), byte count, 2·w data bytes, CRC (2) = ``13 + 2w``. Response: address, function,
    byte count, 2·r data bytes, CRC (2) = ``5 + 2r``. Defaults: ``drivers/modbus.py``'s map
    (w = 4, r = 7 → 21 and 19 bytes).
    """
    if write_count is None or read_count is None:
        from rths_hil.drivers.modbus import READ_COUNT, WRITE_COUNT

        write_count = WRITE_COUNT if write_count is None else write_count
        read_count = READ_COUNT if read_count is None else read_count
    return 13 + 2 * int(write_count), 5 + 2 * int(read_count)


def _bits_per_char(parity: str = "E", stopbits: float = 1) -> float:
    p = str(parity).upper()[:1]
    if p not in ("N", "E", "O", "M", "S"):
        raise InputError(f"serial parity must be N, E, O, M or S, got {parity!r}")
    return 1 + 8 + (0 if p == "N" else 1) + float(stopbits)


def rtu_transaction_time(
    baudrate: float,
    parity: str = "E",
    stopbits: float = 1,
    *,
    frame_bytes: tuple[int, int] | None = None,
    spec_silence: bool = False,
) -> float:
    """Time (s) of one Modbus RTU FC 23 transaction on the line.

    ``(request + response + 2·3.5) · bits_per_char / baud``: both frames, each followed by the
    3.5-character silence that ends an RTU frame. With ``spec_silence`` the silence is the
    fixed 1.75 ms the spec recommends above 19 200 baud. Slave processing time not included.
    """
    req, resp = frame_bytes or modbus_rtu_frame_bytes()
    bpc = _bits_per_char(parity, stopbits)
    baud = float(baudrate)
    silence = 3.5 * bpc / baud
    if spec_silence and baud > 19200:
        silence = 1.75e-3
    return (req + resp) * bpc / baud + 2.0 * silence


def cobs_frame_bytes(body_bytes: int) -> int:
    """Bytes on the wire of a COBS-encoded frame of ``body_bytes`` (CRC included) + delimiter.

    COBS adds one code byte per started block of 254 bytes (Cheshire & Baker 1999); the frame
    ends with one 0x00.
    """
    n = int(body_bytes)
    return n + 1 + n // 254 + 1


def serial_frame_bytes() -> tuple[int, int]:
    """Command and feedback frame sizes of ``drivers/serial.py`` on the wire (18 and 26)."""
    from rths_hil.drivers.serial import COMMAND, FEEDBACK

    crc = 2
    return cobs_frame_bytes(COMMAND.size + crc), cobs_frame_bytes(FEEDBACK.size + crc)


def can_serial_frame_chars(interface: str, data_bytes: int) -> int:
    """Characters a standard-identifier CAN data frame takes on the serial line of ``interface``.

    ``slcan``: ``t`` + 3 identifier + 1 DLC + 2 per data byte + CR = ``6 + 2s``. ``serial``
    (python-can's framing): 0xAA + 4 timestamp + 1 DLC + 4 identifier + ``s`` + 0xBB = ``11 + s``.
    """
    n = int(data_bytes)
    if not 0 <= n <= 8:
        raise InputError(f"classic CAN carries 0–8 data bytes, got {data_bytes}")
    if interface == "slcan":
        return 6 + 2 * n
    if interface == "serial":
        return 11 + n
    raise InputError(f"python-can interface {interface!r} is not a serial-line interface")


def _can_serial_line(c: dict[str, Any], interface: str) -> tuple[str, float]:
    """The serial device and baud rate of a python-can ``slcan``/``serial`` connection."""
    device = str(c.get("channel", ""))
    opts = dict(c.get("bus_options") or {})
    baud: Any = opts.get("tty_baudrate" if interface == "slcan" else "baudrate")
    if interface == "slcan" and "@" in device:
        device, suffix = device.split("@", 1)
        baud = suffix
    if baud is None:
        baud = CAN_SERIAL_DEFAULT_BAUD
    try:
        baud = float(baud)
    except (TypeError, ValueError):
        raise InputError(
            f"CAN {interface} {device}: baud rate must be a number, got {baud!r}"
        ) from None
    return device, baud


def _can_frame_lengths(dbc: str | None) -> tuple[int, int, int]:
    """Command, feedback and heartbeat data lengths from the DBC the driver uses."""
    from rths_hil.drivers.can.codec import load

    c = load(dbc)
    return c.command.length, c.feedback.length, c.heartbeat.length


# --------------------------------------------------------------------------------------------
# links
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LinkLoad:
    """The load of one link (bus, line or connection) shared by ``channels`` channels.

    Attributes
    ----------
    link : str
        Name of the link (driver, transport and where: ``can virtual:rths-hil``,
        ``modbus rtu /dev/ttyUSB0``, ``serial /dev/ttyUSB0``).
    load : float or None
        Fraction of the link's capacity used (1.0 = full); ``None`` when the link has no rate
        (virtual bus, pseudo-terminal, loopback) or its rate is unknown.
    detail : str
        One line: frames, bits or bytes per step, rate.
    channels : int
        Channels on the link.
    fs : float
        Loop rate (Hz).
    enforced : bool
        Whether :func:`check_links` refuses the link above the limit (``False`` for a load
        computed for information only, e.g. a virtual bus with a ``bitrate``).
    kind : str
        ``can``, ``modbus-rtu``, ``modbus-tcp``, ``serial`` or ``other``.
    rate : float or None
        Bit rate (CAN, Ethernet) or baud rate (serial lines).
    per_channel : float
        Link time (s) of one channel's step traffic (command + feedback).
    per_second : float
        Link time (s) per second that does not scale with the loop rate (heartbeats).
    """

    link: str
    load: float | None
    detail: str
    channels: int = 1
    fs: float = 0.0
    enforced: bool = True
    kind: str = "other"
    rate: float | None = None
    per_channel: float = 0.0
    per_second: float = 0.0

    @property
    def limited(self) -> bool:
        """True when the link has a rate and the load is checked."""
        return self.load is not None and self.enforced

    def summary(self) -> str:
        """One line for the console: link, load, detail."""
        if self.load is None:
            return f"{self.link}: no limit ({self.detail})"
        tail = "" if self.enforced else ", not enforced"
        return f"{self.link}: {self.load * 100:.1f} % ({self.detail}{tail})"


def _rate_text(bits_per_s: float) -> str:
    if bits_per_s >= 1e6:
        return f"{bits_per_s / 1e6:g} Mbit/s"
    return f"{bits_per_s / 1e3:g} kbit/s"


def _is_loopback(host: str) -> bool:
    h = str(host).strip().lower()
    return h in ("localhost", "::1", "ip6-localhost") or h.startswith("127.")


#: Why a serial link without a device has no rate: only a twin serves one (its own pty).
TWIN_PTY = (
    "no device: the twin's own pseudo-terminal, which has no line rate (a real serial port, "
    "given as device or url, is checked at its baud rate)"
)


def _serial_rate_kind(device: str | None) -> str | None:
    """``None`` for a real UART; otherwise why the device has no rate limit (``device`` None:
    the twin's own pseudo-terminal, :data:`TWIN_PTY`)."""
    if device is None:
        return TWIN_PTY
    d = str(device)
    if "://" in d:
        scheme = d.split("://", 1)[0].lower()
        if scheme == "loop":
            return "loop:// has no line rate"
        if scheme == "socket":
            host = d.split("://", 1)[1].rsplit(":", 1)[0]
            if _is_loopback(host):
                return "socket:// on the loopback interface has no line rate"
        return f"{scheme}:// URL: line rate unknown"
    if os.path.realpath(d).startswith(("/dev/pts/", "/dev/ptmx")):
        return "pseudo-terminal has no line rate"
    return None


def _channels(channels_on_link: int) -> int:
    ch = int(channels_on_link)
    if ch < 1:
        raise InputError(f"channels on a link must be ≥ 1, got {channels_on_link}")
    return ch


def _driver_class(driver_name: str) -> Any:
    """The registered driver class of ``driver_name``, or ``None`` for an unknown name."""
    from rths_hil.drivers.registry import available, driver_class

    if str(driver_name) not in available():
        return None
    return driver_class(str(driver_name))


def link_key(driver_name: str, connection: dict[str, Any]) -> str:
    """Name of the physical link a channel's connection uses; equal names share one link.

    Asks the driver class (``Driver.link_key``): CAN: interface and channel; Modbus TCP: host
    and port; Modbus RTU: the serial device; serial: the port or URL. Other drivers (and
    unknown names): the driver name and its sorted settings.
    """
    c = dict(connection or {})
    cls = _driver_class(driver_name)
    if cls is None:
        return f"{driver_name} " + ",".join(f"{k}={c[k]}" for k in sorted(c))
    return cls.link_key(c)


def can_link_key(connection: dict[str, Any]) -> str:
    """CAN: interface and channel."""
    c = connection
    return f"can {c.get('interface', 'virtual')}:{c.get('channel', 'rths-hil')}"


def modbus_link_key(connection: dict[str, Any]) -> str:
    """Modbus TCP: host and port; RTU: the serial device."""
    c = connection
    if c.get("transport", "tcp") == "rtu":
        return f"modbus rtu {c.get('device') or 'twin pty'}"
    return f"modbus tcp {c.get('host', '127.0.0.1')}:{c.get('port', 502)}"


def serial_link_key(connection: dict[str, Any]) -> str:
    """Serial: the port or URL."""
    return f"serial {connection.get('url') or 'twin pty'}"


_positive = positive_number  # one checker for the package (rths_hil.units)


def link_load(
    driver_name: str,
    connection: dict[str, Any],
    channels_on_link: int,
    fs: float,
    *,
    heartbeat_hz: float = 0.0,
) -> LinkLoad:
    """Load of the link used by ``channels_on_link`` channels of ``driver_name`` at ``fs``.

    The driver class computes it (``Driver.link_load``; the built-in drivers call
    :func:`can_load`, :func:`modbus_load` and :func:`serial_load` below); a driver that does
    not know its frames, or an unknown name, reports "not checked".

    Parameters
    ----------
    driver_name : str
        Driver registry name (``can``, ``modbus``, ``serial`` or a lab's entry point).
    connection : dict
        The driver's connection settings (as given to ``rths_hil.drivers.registry.create_driver``).
    channels_on_link : int
        Channels sharing this link (see :func:`link_key`).
    fs : float
        Loop rate (Hz): one command and one feedback per channel and step.
    heartbeat_hz : float
        Heartbeat frames per second per channel (0: none), e.g. ``1 / loop.heartbeat``.

    Returns
    -------
    LinkLoad
    """
    c = dict(connection or {})
    fs = _positive(fs, "loop rate fs (Hz)")
    ch = _channels(channels_on_link)
    cls = _driver_class(driver_name)
    if cls is None:
        return LinkLoad(
            link_key(driver_name, c),
            None,
            f"driver {driver_name!r}: frame sizes unknown, not checked",
            channels=ch,
            fs=fs,
        )
    return cls.link_load(c, ch, fs, heartbeat_hz=float(heartbeat_hz))


def can_load(
    connection: dict[str, Any],
    channels_on_link: int,
    fs: float,
    *,
    heartbeat_hz: float = 0.0,
) -> LinkLoad:
    """Classic CAN: command + feedback frames from the DBC, worst-case stuffing (module
    docstring); CAN through a serial line (``slcan``, ``serial``)."""
    c = dict(connection or {})
    fs = _positive(fs, "loop rate fs (Hz)")
    ch = _channels(channels_on_link)
    hb = float(heartbeat_hz)
    base = {"channels": ch, "fs": fs}
    name = can_link_key(c)
    n_cmd, n_fb, n_hb = _can_frame_lengths(c.get("dbc"))
    ext = (False, False, False)
    profile = c.get("profile")
    if profile not in (None, "", "rths-hil"):  # a controller profile: its DBC's frames
        from rths_hil.drivers.profile import load_profile

        prof: Any = load_profile(profile)
        hb_msg = (
            prof.database.get_message_by_name(prof.heartbeat.message) if prof.heartbeat else None
        )
        msgs = (prof.command, prof.feedback, hb_msg or prof.command)
        n_cmd, n_fb, n_hb = (int(m.length) for m in msgs)
        ext = tuple(bool(m.is_extended_frame) for m in msgs)  # type: ignore[assignment]
    b_cmd, b_fb, b_hb = (
        can_frame_bits(n, extended=e) for n, e in zip((n_cmd, n_fb, n_hb), ext, strict=True)
    )
    bits_step = ch * (b_cmd + b_fb)
    frames = (
        f"{ch} × ({n_cmd}-byte command {b_cmd} + {n_fb}-byte feedback {b_fb}) bits at {fs:g} Hz"
    )
    if hb > 0:
        frames += f" + heartbeats {ch} × {b_hb} bits at {hb:g} Hz"
    bitrate = c.get("bitrate")
    interface = str(c.get("interface", "virtual"))
    if interface in CAN_SERIAL_INTERFACES:
        return _can_serial_load(c, interface, name, (n_cmd, n_fb, n_hb), bits_step, hb, base)
    if bitrate is None:
        why = "virtual bus" if interface == "virtual" else "bit rate set by the interface"
        return LinkLoad(
            name, None, f"{why}; {frames} = {bits_step * fs:.0f} bit/s", kind="can", **base
        )
    rate = _positive(bitrate, f"{name}: bitrate (bit/s)")
    load = (bits_step * fs + ch * b_hb * hb) / rate
    detail = f"{frames}, worst-case stuffing, of {_rate_text(rate)}"
    if interface == "virtual":
        detail += "; virtual bus"
    return LinkLoad(
        name,
        load,
        detail,
        enforced=interface != "virtual",
        kind="can",
        rate=rate,
        per_channel=(b_cmd + b_fb) / rate,
        per_second=ch * b_hb * hb / rate,
        **base,
    )


def modbus_load(
    connection: dict[str, Any],
    channels_on_link: int,
    fs: float,
    *,
    heartbeat_hz: float = 0.0,
) -> LinkLoad:
    """Modbus RTU (FC 23 transactions and silences) or Modbus TCP (MBAP in Ethernet frames)."""
    c = dict(connection or {})
    fs = _positive(fs, "loop rate fs (Hz)")
    ch = _channels(channels_on_link)
    del heartbeat_hz  # Modbus has no heartbeat frame
    base = {"channels": ch, "fs": fs}
    name = modbus_link_key(c)
    if c.get("transport", "tcp") == "rtu":
        why = _serial_rate_kind(c.get("device"))
        req, resp = modbus_rtu_frame_bytes()
        baud = _positive(c.get("baudrate", 115200), f"{name}: baudrate")
        parity, stop = c.get("parity", "E"), c.get("stopbits", 1)
        t = rtu_transaction_time(baud, parity, stop, frame_bytes=(req, resp))
        bpc = _bits_per_char(parity, stop)
        frames = (
            f"{ch} × FC 23 ({req} + {resp} bytes + 2 × 3.5 characters of {bpc:g} bits "
            f"= {t * 1e3:.2f} ms) at {fs:g} Hz"
        )
        profile = c.get("profile")
        if profile not in (None, "", "rths-hil"):  # a controller profile: its transactions
            from rths_hil.drivers.profile import load_profile

            pairs = load_profile(profile).rtu_frames()  # type: ignore[union-attr]
            t = sum(rtu_transaction_time(baud, parity, stop, frame_bytes=fb) for fb in pairs)
            frames = (
                f"{ch} × ({' + '.join(f'{a} + {b}' for a, b in pairs)} bytes + "
                f"{2 * len(pairs)} × 3.5 characters of {bpc:g} bits = {t * 1e3:.2f} ms) at "
                f"{fs:g} Hz (profile)"
            )
        if why is not None:
            return LinkLoad(name, None, f"{why}; {frames}", kind="modbus-rtu", **base)
        return LinkLoad(
            name,
            ch * t * fs,
            f"{frames} on {baud:g} baud",
            kind="modbus-rtu",
            rate=baud,
            per_channel=t,
            **base,
        )
    host = str(c.get("host", "127.0.0.1"))
    req, resp = 25, 23  # MBAP header (7) + FC 23 PDU
    fcs, sizes, n = "FC 23", f"{req} + {resp}", 1
    profile = c.get("profile")
    if profile not in (None, "", "rths-hil"):  # a controller profile: its requests
        from rths_hil.drivers.profile import load_profile

        prof = load_profile(profile)
        pairs = [(a + 4, b + 4) for a, b in prof.rtu_frames()]  # MBAP (7) for address + CRC
        fcs = " + ".join(f"FC {f}" for f in prof.step_functions())  # type: ignore[union-attr]
        sizes = " + ".join(f"{a} + {b}" for a, b in pairs)
        req, resp, n = sum(a for a, _ in pairs), sum(b for _, b in pairs), len(pairs)
    if _is_loopback(host):
        return LinkLoad(
            name,
            None,
            f"TCP loopback; {ch} × {fcs} ({sizes} bytes) at {fs:g} Hz",
            kind="modbus-tcp",
            **base,
        )
    bits = 8 * (req + resp + 2 * n * TCP_SEGMENT_OVERHEAD)
    return LinkLoad(
        name,
        ch * bits * fs / ETHERNET_BITRATE,
        f"{ch} × {fcs} in TCP/IP/Ethernet ({bits} bits) at {fs:g} Hz of an assumed "
        f"{_rate_text(ETHERNET_BITRATE)} Ethernet",
        kind="modbus-tcp",
        rate=ETHERNET_BITRATE,
        per_channel=bits / ETHERNET_BITRATE,
        **base,
    )


def serial_load(
    connection: dict[str, Any],
    channels_on_link: int,
    fs: float,
    *,
    heartbeat_hz: float = 0.0,
) -> LinkLoad:
    """The serial driver's COBS frames on the line (module docstring)."""
    c = dict(connection or {})
    fs = _positive(fs, "loop rate fs (Hz)")
    ch = _channels(channels_on_link)
    hb = float(heartbeat_hz)
    base = {"channels": ch, "fs": fs}
    name = serial_link_key(c)
    why = _serial_rate_kind(c.get("url"))
    n_cmd, n_fb = serial_frame_bytes()
    n_hb = cobs_frame_bytes(4)
    baud = _positive(c.get("baudrate", 921600), f"{name}: baudrate")
    bpc = _bits_per_char("N", 1)  # drivers/serial.py opens 8N1
    frames = (
        f"{ch} × (command {n_cmd} bytes out, feedback {n_fb} bytes in) of {bpc:g}-bit "
        f"characters at {fs:g} Hz"
    )
    if hb > 0:
        frames += f" + heartbeats {ch} × {n_hb} bytes at {hb:g} Hz"
    if why is not None:
        return LinkLoad(name, None, f"{why}; {frames}", kind="serial", **base)
    # lockstep: the feedback answers the command, so each step needs the line for both
    # frames in turn (full duplex does not overlap them); heartbeats go with the commands
    t_step = (n_cmd + n_fb) * bpc / baud
    t_hb = ch * n_hb * bpc * hb / baud
    return LinkLoad(
        name,
        ch * t_step * fs + t_hb,
        f"{frames} on {baud:g} baud",
        kind="serial",
        rate=baud,
        per_channel=t_step,
        per_second=t_hb,
        **base,
    )


def _can_serial_load(
    c: dict[str, Any],
    interface: str,
    name: str,
    lengths: tuple[int, int, int],
    can_bits_step: int,
    hb: float,
    base: dict[str, Any],
) -> LinkLoad:
    """Load of a CAN link through a serial line (``slcan``, ``serial``): module docstring."""
    ch, fs = base["channels"], base["fs"]
    device, baud = _can_serial_line(c, interface)
    baud = _positive(baud, f"{name}: baud rate")
    c_cmd, c_fb, c_hb = (can_serial_frame_chars(interface, n) for n in lengths)
    bpc = _bits_per_char("N", 1)  # python-can opens both 8N1
    unit = "characters" if interface == "slcan" else "bytes"
    frames = f"{ch} × ({c_cmd} + {c_fb} {interface} {unit} of {bpc:g} bits per step) at {fs:g} Hz"
    if hb > 0:
        frames += f" + heartbeats {ch} × {c_hb} {unit} at {hb:g} Hz"
    why = _serial_rate_kind(device)
    if why is not None:
        return LinkLoad(name, None, f"{why}; {frames}", kind="serial", **base)
    t_step = (c_cmd + c_fb) * bpc / baud
    t_hb = ch * c_hb * bpc * hb / baud
    line = ch * t_step * fs + t_hb
    detail = f"{frames} on {baud:.0f} baud"
    bitrate = c.get("bitrate")
    if bitrate is not None:
        rate = _positive(bitrate, f"{name}: bitrate (bit/s)")
        b_hb = can_frame_bits(lengths[2])
        bus = (can_bits_step * fs + ch * b_hb * hb) / rate
        detail += f"; the CAN bus behind it {bus * 100:.1f} % of {_rate_text(rate)}"
        if bus > line:
            b_step = can_frame_bits(lengths[0]) + can_frame_bits(lengths[1])
            return LinkLoad(
                name,
                bus,
                detail,
                kind="can",
                rate=rate,
                per_channel=b_step / rate,
                per_second=ch * b_hb * hb / rate,
                **base,
            )
    return LinkLoad(
        name,
        line,
        detail,
        kind="serial",
        rate=baud,
        per_channel=t_step,
        per_second=t_hb,
        **base,
    )


def _next_rate(needed: float, rates: tuple[int, ...]) -> int | None:
    for r in rates:
        if r >= needed:
            return r
    return None


def _what_fits(ld: LinkLoad, limit: float) -> str:
    """The alternatives that would bring ``ld`` under ``limit``, as one phrase."""
    options = []
    if ld.per_channel > 0 and limit > ld.per_second:
        budget = limit - ld.per_second
        fs_max = budget / (ld.channels * ld.per_channel)
        options.append(f"a loop rate ≤ {math.floor(fs_max):d} Hz")
        per_bus = math.floor(budget / (ld.per_channel * ld.fs))
        if 1 <= per_bus < ld.channels:
            options.append(f"≤ {per_bus} channel{'s' if per_bus > 1 else ''} per link")
        elif per_bus < 1:
            options.append("not even one channel per link at this rate")
    if ld.rate and ld.load:
        needed = ld.rate * ld.load / limit
        if ld.kind == "can":
            r = _next_rate(needed, CAN_BITRATES)
            if r is not None and r > ld.rate:
                options.append(f"a bit rate of {_rate_text(r)}")
            nb = can_fd_length(8 * ld.channels) if 8 * ld.channels <= 64 else None
            if nb is not None:
                t = 2 * can_fd_frame_time(8 * ld.channels, *CAN_FD_RATES)
                fd = t * ld.fs
                if fd <= limit:
                    rates = (
                        f"{_rate_text(CAN_FD_RATES[0])} nominal, {_rate_text(CAN_FD_RATES[1])} data"
                    )
                    if ld.channels > 1:
                        what = (
                            f"with all {ld.channels} channels in one {nb}-byte command and one "
                            "feedback frame"
                        )
                    else:
                        what = "frames"
                    options.append(f"CAN FD ({rates}) {what}: {fd * 100:.0f} %")
        elif ld.kind in ("serial", "modbus-rtu"):
            r = _next_rate(needed, BAUDRATES)
            if r is not None and r > ld.rate:
                options.append(f"{r} baud")
            elif r is None:
                options.append(f"a line faster than {BAUDRATES[-1]} baud")
            if ld.kind == "modbus-rtu":
                options.append("Modbus TCP")
    return "; ".join(options) if options else "nothing at this rate"


def check_links(loads: list[LinkLoad] | tuple[LinkLoad, ...], limit: float = DEFAULT_LIMIT) -> None:
    """Refuse the configuration if an enforced link is loaded above ``limit``.

    Raises
    ------
    InputError
        One line naming the most loaded link, its load, and what would fit (lower rate, fewer
        channels per link, higher bit rate, CAN FD); other links over the limit are counted.
    """
    limit = _positive(limit, "link load limit")
    over = sorted(
        (ld for ld in loads if ld.limited and ld.load is not None and ld.load > limit),
        key=lambda ld: -(ld.load or 0.0),
    )
    for ld in loads:
        log.info("link budget: %s", ld.summary())
    if not over:
        return
    ld = over[0]
    more = (
        f" (and {len(over) - 1} more link{'s' if len(over) > 2 else ''} over)"
        if len(over) > 1
        else ""
    )
    raise InputError(
        f"link {ld.link} is {ld.load * 100:.0f} % loaded with {ld.channels} channel"
        f"{'s' if ld.channels > 1 else ''} at {ld.fs:g} Hz (limit {limit * 100:.0f} %): "
        f"{ld.detail}; would fit: {_what_fits(ld, limit)}{more}"
    )


def format_loads(loads: list[LinkLoad] | tuple[LinkLoad, ...]) -> str:
    """One line per link, for the start-up console."""
    return "\n".join("link " + ld.summary() for ld in loads)

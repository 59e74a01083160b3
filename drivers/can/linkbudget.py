"""The CAN link model: the bits of a step's frames on a classic CAN bus (and through a serial
line to a USB–CAN adapter), the load of a set of nodes, what would fit (a higher bit rate, CAN
FD), and the planning facts of the protocol (who may share a bus, whether its twin runs inline).

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

The python-can ``virtual`` bus and pseudo-terminals (so the served CAN twin's
``slcan``/``serial`` pair) report "no limit". A CAN bus whose interface sets the bit rate
itself (no ``bitrate`` in the connection) reports its bits per step and "bit rate unknown".

References
----------
R. I. Davis, A. Burns, R. J. Bril, J. J. Lukkien, "Controller Area Network (CAN) schedulability
analysis: refuted, revisited and revised", Real-Time Systems 35(3), 239–272, 2007.
ISO 11898-1:2015, Road vehicles — Controller area network (CAN) — Part 1.
"""

from __future__ import annotations

import math
from typing import Any

from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad, positive, rate_text

from ..protocol import ChannelUse, LinkInputs, link_model
from ..serial.line import bits_per_char, serial_rate_kind

__all__ = [
    "CAN_BITRATES",
    "CAN_FD_LENGTHS",
    "CAN_FD_RATES",
    "can_fd_frame_time",
    "can_fd_length",
    "can_frame_bits",
    "can_serial_frame_chars",
    "check_sharing",
    "inline_twin",
    "link_advice",
    "link_key",
    "link_load",
]

#: Data lengths a CAN FD frame can carry (bytes).
CAN_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: Standard CAN bit rates (bit/s), for "what would fit".
CAN_BITRATES = (125_000, 250_000, 500_000, 1_000_000)
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
    from .codec import load

    c = load(dbc)
    return c.command.length, c.feedback.length, c.heartbeat.length


# --------------------------------------------------------------------------------------------
# the link
# --------------------------------------------------------------------------------------------
def link_key(connection: dict[str, Any]) -> str:
    """CAN: interface and channel."""
    c = connection or {}
    return f"can {c.get('interface', 'virtual')}:{c.get('channel', 'rths-hil')}"


@link_model(link_key)
def link_load(i: LinkInputs) -> LinkLoad:
    """Classic CAN: command + feedback frames from the DBC, worst-case stuffing (module
    docstring); CAN through a serial line (``slcan``, ``serial``)."""
    c, name, ch, fs, hb = i.connection, i.link, i.channels, i.fs, i.heartbeat_hz
    n_cmd, n_fb, n_hb = _can_frame_lengths(c.get("dbc"))
    ext = (False, False, False)
    profile = c.get("profile")
    if profile not in (None, "", "rths-hil"):  # a controller profile: its DBC's frames
        from ..profile import load_profile

        prof: Any = load_profile(str(profile))
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
        return _can_serial_load(i, interface, (n_cmd, n_fb, n_hb), bits_step)
    if bitrate is None:
        why = "virtual bus" if interface == "virtual" else "bit rate set by the interface"
        return LinkLoad(
            name, None, f"{why}; {frames} = {bits_step * fs:.0f} bit/s", kind="can", **i.base
        )
    rate = positive(bitrate, f"{name}: bitrate (bit/s)")
    load = (bits_step * fs + ch * b_hb * hb) / rate
    detail = f"{frames}, worst-case stuffing, of {rate_text(rate)}"
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
        **i.base,
    )


def _can_serial_load(
    i: LinkInputs, interface: str, lengths: tuple[int, int, int], can_bits_step: int
) -> LinkLoad:
    """Load of a CAN link through a serial line (``slcan``, ``serial``): module docstring."""
    c, name, ch, fs, hb = i.connection, i.link, i.channels, i.fs, i.heartbeat_hz
    device, baud = _can_serial_line(c, interface)
    baud = positive(baud, f"{name}: baud rate")
    c_cmd, c_fb, c_hb = (can_serial_frame_chars(interface, n) for n in lengths)
    bpc = bits_per_char("N", 1)  # python-can opens both 8N1
    unit = "characters" if interface == "slcan" else "bytes"
    frames = f"{ch} × ({c_cmd} + {c_fb} {interface} {unit} of {bpc:g} bits per step) at {fs:g} Hz"
    if hb > 0:
        frames += f" + heartbeats {ch} × {c_hb} {unit} at {hb:g} Hz"
    why = serial_rate_kind(device)
    if why is not None:
        return LinkLoad(name, None, f"{why}; {frames}", kind="serial", **i.base)
    t_step = (c_cmd + c_fb) * bpc / baud
    t_hb = ch * c_hb * bpc * hb / baud
    line = ch * t_step * fs + t_hb
    detail = f"{frames} on {baud:.0f} baud"
    bitrate = c.get("bitrate")
    if bitrate is not None:
        rate = positive(bitrate, f"{name}: bitrate (bit/s)")
        b_hb = can_frame_bits(lengths[2])
        bus = (can_bits_step * fs + ch * b_hb * hb) / rate
        detail += f"; the CAN bus behind it {bus * 100:.1f} % of {rate_text(rate)}"
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
                **i.base,
            )
    return LinkLoad(
        name,
        line,
        detail,
        kind="serial",
        rate=baud,
        per_channel=t_step,
        per_second=t_hb,
        **i.base,
    )


def link_advice(ld: LinkLoad, limit: float) -> list[str]:
    """What would bring a CAN bus (``kind`` ``can``: the CAN and CANopen drivers') under
    ``limit``: the next standard bit rate, and CAN FD with every channel in one command and
    one feedback frame when that fits."""
    if ld.kind != "can" or not (ld.rate and ld.load):
        return []
    options = []
    needed = ld.rate * ld.load / limit
    r = next((b for b in CAN_BITRATES if b >= needed), None)
    if r is not None and r > ld.rate:
        options.append(f"a bit rate of {rate_text(r)}")
    if 8 * ld.channels <= 64:
        nb = can_fd_length(8 * ld.channels)
        fd = 2 * can_fd_frame_time(8 * ld.channels, *CAN_FD_RATES) * ld.fs
        if fd <= limit:
            rates = f"{rate_text(CAN_FD_RATES[0])} nominal, {rate_text(CAN_FD_RATES[1])} data"
            if ld.channels > 1:
                what = (
                    f"with all {ld.channels} channels in one {nb}-byte command and one "
                    "feedback frame"
                )
            else:
                what = "frames"
            options.append(f"CAN FD ({rates}) {what}: {fd * 100:.0f} %")
    return options


def inline_twin(connection: dict[str, Any]) -> bool:
    """The twin on python-can's in-process ``virtual`` bus can be served inline (the built-in
    protocol only)."""
    from ..profile import is_builtin

    c = connection or {}
    return str(c.get("interface", "virtual")) == "virtual" and is_builtin(c.get("profile"))


def check_sharing(channels: list[ChannelUse]) -> None:
    """Channels on one bus need distinct CAN nodes (``driver.connection.node``)."""
    seen: dict[tuple, str] = {}
    for _, name, conn, twin in channels:
        if conn.get("channel") is None and twin:
            continue  # each twin gets a bus of its own
        key = (conn.get("interface", "virtual"), conn.get("channel"), conn.get("node", 0))
        if key in seen:
            raise InputError(
                f"actuators: channels {seen[key]!r} and {name!r} use the same CAN node on "
                "one bus (set driver.connection.node)"
            )
        seen[key] = name

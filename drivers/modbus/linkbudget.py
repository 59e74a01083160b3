"""The Modbus link model: the bytes of a step on an RTU line or in TCP segments, the load of a
set of units, and the planning facts of the protocol (its link, who may share it).

**Modbus RTU** (Modbus over Serial Line V1.02): one FC 23 transaction per channel and step —
request ``13 + 2·w`` bytes and response ``5 + 2·r`` bytes for ``w`` written and ``r`` read
registers (21 + 19 bytes with the built-in map of :mod:`.driver`, CRC included), each character
``1 + 8 + parity + stop`` bits (11 for the standard 8E1), and a silence of 3.5 characters after
each frame::

    T = (bytes_request + bytes_response + 2·3.5) · bits_per_char / baud
    load = channels · T · fs                         (one line, one master: transactions queue)

The spec recommends a fixed 1.75 ms silence above 19 200 baud; ``spec_silence=True`` uses it.
A profile's map (:mod:`.profile`) counts its own transactions
(``ModbusProfile.rtu_frames``).

**Modbus TCP** to another host: the MBAP frames (25 + 23 bytes) in TCP/IP/Ethernet segments
(+ 90 bytes each: preamble and interframe gap 20, Ethernet header and FCS 18, IPv4 20,
TCP with timestamps 32) on an assumed 100 Mbit/s link. TCP to the loopback interface, and an
RTU connection that names no ``device`` (a twin's own pseudo-terminal), report "no limit"
(:func:`rths_hil.drivers.serial.line.serial_rate_kind`).

References
----------
Modbus Organization, "MODBUS over Serial Line, Specification and Implementation Guide V1.02",
2006, Section 2.5.1.1 (RTU framing, t3.5).
"""

from __future__ import annotations

from typing import Any

from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad, is_loopback, positive, rate_text

from ..protocol import ChannelUse, LinkInputs, link_model
from ..serial.line import BAUDRATES, bits_per_char, serial_rate_kind
from .transport import MAX_UNIT

__all__ = [
    "ETHERNET_BITRATE",
    "TCP_SEGMENT_OVERHEAD",
    "check_sharing",
    "link_advice",
    "link_key",
    "link_load",
    "rtu_frame_bytes",
    "rtu_transaction_time",
]

#: Assumed rate of an Ethernet link to another host (bit/s).
ETHERNET_BITRATE = 100_000_000
#: Per-segment overhead of TCP/IPv4 on Ethernet (bytes): preamble+SFD 8, IFG 12, header 14,
#: FCS 4, IPv4 20, TCP with the timestamp option 32.
TCP_SEGMENT_OVERHEAD = 90


def rtu_frame_bytes(
    write_count: int | None = None, read_count: int | None = None
) -> tuple[int, int]:
    """Bytes of the FC 23 request and response on an RTU line, CRC included.

    Request: address, function, read address (2), read count (2), write address (2), write
    count (2), byte count, 2·w data bytes, CRC (2) = ``13 + 2w``. Response: address, function,
    byte count, 2·r data bytes, CRC (2) = ``5 + 2r``. Defaults: the built-in map of
    :mod:`.driver` (w = 4, r = 7 → 21 and 19 bytes).
    """
    from .driver import READ_COUNT, WRITE_COUNT

    write_count = WRITE_COUNT if write_count is None else write_count
    read_count = READ_COUNT if read_count is None else read_count
    return 13 + 2 * int(write_count), 5 + 2 * int(read_count)


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
    req, resp = frame_bytes or rtu_frame_bytes()
    bpc = bits_per_char(parity, stopbits)
    baud = float(baudrate)
    silence = 3.5 * bpc / baud
    if spec_silence and baud > 19200:
        silence = 1.75e-3
    return (req + resp) * bpc / baud + 2.0 * silence


def link_key(connection: dict[str, Any]) -> str:
    """Modbus TCP: host and port; RTU: the serial device."""
    c = connection or {}
    if c.get("transport", "tcp") == "rtu":
        return f"modbus rtu {c.get('device') or 'twin pty'}"
    return f"modbus tcp {c.get('host', '127.0.0.1')}:{c.get('port', 502)}"


def _profile(c: dict[str, Any]) -> Any:
    """The connection's controller profile (``None``: the built-in map)."""
    profile = c.get("profile")
    if profile in (None, "", "rths-hil"):
        return None
    from ..profile import load_profile

    return load_profile(str(profile))


@link_model(link_key)
def link_load(i: LinkInputs) -> LinkLoad:
    """Modbus RTU (FC 23 transactions and silences) or Modbus TCP (MBAP in Ethernet frames)."""
    c, name, ch, fs = i.connection, i.link, i.channels, i.fs  # Modbus has no heartbeat frame
    prof = _profile(c)
    if c.get("transport", "tcp") == "rtu":
        why = serial_rate_kind(c.get("device"))
        req, resp = rtu_frame_bytes()
        baud = positive(c.get("baudrate", 115200), f"{name}: baudrate")
        parity, stop = c.get("parity", "E"), c.get("stopbits", 1)
        t = rtu_transaction_time(baud, parity, stop, frame_bytes=(req, resp))
        bpc = bits_per_char(parity, stop)
        frames = (
            f"{ch} × FC 23 ({req} + {resp} bytes + 2 × 3.5 characters of {bpc:g} bits "
            f"= {t * 1e3:.2f} ms) at {fs:g} Hz"
        )
        if prof is not None:  # a controller profile: its transactions
            pairs = prof.rtu_frames()
            t = sum(rtu_transaction_time(baud, parity, stop, frame_bytes=fb) for fb in pairs)
            frames = (
                f"{ch} × ({' + '.join(f'{a} + {b}' for a, b in pairs)} bytes + "
                f"{2 * len(pairs)} × 3.5 characters of {bpc:g} bits = {t * 1e3:.2f} ms) at "
                f"{fs:g} Hz (profile)"
            )
        if why is not None:
            return LinkLoad(name, None, f"{why}; {frames}", kind="modbus-rtu", **i.base)
        return LinkLoad(
            name,
            ch * t * fs,
            f"{frames} on {baud:g} baud",
            kind="modbus-rtu",
            rate=baud,
            per_channel=t,
            **i.base,
        )
    host = str(c.get("host", "127.0.0.1"))
    req, resp = 25, 23  # MBAP header (7) + FC 23 PDU
    fcs, sizes, n = "FC 23", f"{req} + {resp}", 1
    if prof is not None:  # a controller profile: its requests
        pairs = [(a + 4, b + 4) for a, b in prof.rtu_frames()]  # MBAP (7) for address + CRC
        fcs = " + ".join(f"FC {f}" for f in prof.step_functions())
        sizes = " + ".join(f"{a} + {b}" for a, b in pairs)
        req, resp, n = sum(a for a, _ in pairs), sum(b for _, b in pairs), len(pairs)
    if is_loopback(host):
        return LinkLoad(
            name,
            None,
            f"TCP loopback; {ch} × {fcs} ({sizes} bytes) at {fs:g} Hz",
            kind="modbus-tcp",
            **i.base,
        )
    bits = 8 * (req + resp + 2 * n * TCP_SEGMENT_OVERHEAD)
    return LinkLoad(
        name,
        ch * bits * fs / ETHERNET_BITRATE,
        f"{ch} × {fcs} in TCP/IP/Ethernet ({bits} bits) at {fs:g} Hz of an assumed "
        f"{rate_text(ETHERNET_BITRATE)} Ethernet",
        kind="modbus-tcp",
        rate=ETHERNET_BITRATE,
        per_channel=bits / ETHERNET_BITRATE,
        **i.base,
    )


def link_advice(load: LinkLoad, limit: float) -> list[str]:
    """An RTU line over the limit: the next standard baud rate, or Modbus TCP."""
    if load.kind != "modbus-rtu" or not (load.rate and load.load):
        return []
    needed = load.rate * load.load / limit
    r = next((b for b in BAUDRATES if b >= needed), None)
    out = []
    if r is not None and r > load.rate:
        out.append(f"{r} baud")
    elif r is None:
        out.append(f"a line faster than {BAUDRATES[-1]} baud")
    return [*out, "Modbus TCP"]


def check_sharing(channels: list[ChannelUse]) -> None:
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

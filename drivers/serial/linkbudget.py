"""The serial link model: the COBS frames of a step on the line, the load of a channel, and the
planning facts of the protocol (its link, who may share it).

COBS adds one byte per started 254 bytes and the frame ends with a 0x00 delimiter: command
16 → 18 bytes, feedback 24 → 26 bytes (:mod:`.framing`, CRC included), ``1 + 8 + parity +
stop`` bits per character (the driver's 8N1: 10). In lockstep the feedback answers the
command, so a step needs the line for both frames in turn::

    load = channels · (bytes_command + bytes_feedback) · bits_per_char · fs / baud

A connection that names no ``url`` is a twin's own pseudo-terminal, which has no line rate
(:func:`.line.serial_rate_kind`).
"""

from __future__ import annotations

from typing import Any

from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad, positive

from ..protocol import ChannelUse, LinkInputs, link_model
from .framing import COMMAND, FEEDBACK
from .line import BAUDRATES, bits_per_char, serial_rate_kind

__all__ = [
    "baud_advice",
    "check_sharing",
    "cobs_frame_bytes",
    "link_advice",
    "link_key",
    "link_load",
    "serial_frame_bytes",
]


def baud_advice(ld: LinkLoad, limit: float) -> list[str]:
    """The next standard baud rate that brings the line ``ld`` under ``limit``."""
    if not (ld.rate and ld.load):
        return []
    needed = ld.rate * ld.load / limit
    r = next((b for b in BAUDRATES if b >= needed), None)
    if r is None:
        return [f"a line faster than {BAUDRATES[-1]} baud"]
    return [f"{r} baud"] if r > ld.rate else []


def cobs_frame_bytes(body_bytes: int) -> int:
    """Bytes on the wire of a COBS-encoded frame of ``body_bytes`` (CRC included) + delimiter.

    COBS adds one code byte per started block of 254 bytes (Cheshire & Baker 1999); the frame
    ends with one 0x00.
    """
    n = int(body_bytes)
    return n + 1 + n // 254 + 1


def serial_frame_bytes() -> tuple[int, int]:
    """Command and feedback frame sizes of the serial driver on the wire (18 and 26)."""
    crc = 2
    return cobs_frame_bytes(COMMAND.size + crc), cobs_frame_bytes(FEEDBACK.size + crc)


def link_key(connection: dict[str, Any]) -> str:
    """Serial: the port or URL."""
    return f"serial {(connection or {}).get('url') or 'twin pty'}"


@link_model(link_key)
def link_load(i: LinkInputs) -> LinkLoad:
    """The serial driver's COBS frames on the line (module docstring)."""
    c, name, ch, fs, hb = i.connection, i.link, i.channels, i.fs, i.heartbeat_hz
    why = serial_rate_kind(c.get("url"))
    n_cmd, n_fb = serial_frame_bytes()
    n_hb = cobs_frame_bytes(4)
    baud = positive(c.get("baudrate", 921600), f"{name}: baudrate")
    bpc = bits_per_char("N", 1)  # the driver opens 8N1
    frames = (
        f"{ch} × (command {n_cmd} bytes out, feedback {n_fb} bytes in) of {bpc:g}-bit "
        f"characters at {fs:g} Hz"
    )
    if hb > 0:
        frames += f" + heartbeats {ch} × {n_hb} bytes at {hb:g} Hz"
    if why is not None:
        return LinkLoad(name, None, f"{why}; {frames}", kind="serial", **i.base)
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
        **i.base,
    )


def link_advice(load: LinkLoad, limit: float) -> list[str]:
    """A serial line over the limit (``kind`` ``serial``: this driver's, or a CAN adapter's
    line): the next standard baud rate."""
    return baud_advice(load, limit) if load.kind == "serial" else []


def check_sharing(channels: list[ChannelUse]) -> None:
    """A serial port carries one channel."""
    seen: dict[tuple, str] = {}
    for _, name, conn, twin in channels:
        if twin and not (conn.get("url") or conn.get("port")):
            continue
        key = (conn.get("url"), conn.get("port"))
        if key in seen:
            raise InputError(
                f"actuators: channels {seen[key]!r} and {name!r} use one serial port "
                "(serial links carry one channel each)"
            )
        seen[key] = name

"""``rths-hil twin serve`` options of a twin on a CAN line (CAN and CANopen): the python-can
interface, channel and bit rate. The twin endpoints turn them into their settings
(:func:`rths_hil.sim_backends.endpoints.nullmodem.can_line_from_args`)."""

from __future__ import annotations

import argparse

__all__ = ["bitrate", "serve_options"]


def bitrate(text: str) -> int:
    """A CAN bit rate: a positive integer (bit/s), at most 8 Mbit/s (CAN FD's data phase)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of bit/s") from None
    if not 0 < v <= 8_000_000:
        raise argparse.ArgumentTypeError(f"{v} bit/s is not a CAN bit rate (1 … 8 000 000)")
    return v


def serve_options(group: argparse._ArgumentGroup) -> None:
    """Add ``--interface``, ``--channel`` and ``--bitrate`` to ``twin serve``'s parser."""
    group.add_argument(
        "--interface",
        default="socketcan",
        help="CAN: python-can interface (default socketcan; serial or slcan: a pseudo-terminal "
        "pair on this machine)",
    )
    group.add_argument(
        "--channel",
        default=None,
        help="CAN: channel (default vcan0; serial, slcan: pty = a new pseudo-terminal pair)",
    )
    group.add_argument("--bitrate", type=bitrate, default=None, help="CAN: bit rate (bit/s)")

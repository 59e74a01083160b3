"""The serial protocol's package: :mod:`.framing` (the COBS/CRC frames the driver and its twin
share), :mod:`.driver` (:class:`SerialDriver`) and :mod:`.linkbudget` (its link model)."""

from .driver import SerialDriver
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

__all__ = [
    "COMMAND",
    "ESTOP",
    "ESTOP_KEY",
    "FEEDBACK",
    "HEARTBEAT",
    "T_COMMAND",
    "T_ESTOP",
    "T_FEEDBACK",
    "T_HEARTBEAT",
    "SerialDriver",
    "decode_frame",
    "encode_frame",
]

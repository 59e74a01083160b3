"""The serial protocol's frames: binary frames with a sequence number and a CRC, COBS-framed.

Frame (before framing), all little-endian; the last two bytes are the CRC-16/CCITT-FALSE
(poly 0x1021, init 0xFFFF, ``binascii.crc_hqx(body, 0xFFFF)``) of everything before them:

=========  ====  ===================================================  =====
type       id    body after the type byte                             bytes
=========  ====  ===================================================  =====
command    0x01  seq u32, control u8 (bit 0 enable), displacement f64  16
estop      0x02  key u8 = 0xA5                                         4
heartbeat  0x03  counter u8                                            4
feedback   0x81  seq u32, status u8, displacement f64, force f64       24
=========  ====  ===================================================  =====

Each frame is COBS-encoded (``cobs.cobs``, Cheshire & Baker 1999) and terminated by one 0x00
byte, so a receiver resynchronises at the next zero after any line error. Displacements are
in metres and forces in newtons as IEEE-754 doubles; NaN marks an invalid measurement. The
driver (:mod:`.driver`) and the twin (:mod:`rths_hil.sim_backends.endpoints.serial`) both
frame with this module.
"""

from __future__ import annotations

import binascii
import struct

from cobs import cobs

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
    "cobs_frame",
    "decode_frame",
    "encode_frame",
    "with_crc",
]

T_COMMAND, T_ESTOP, T_HEARTBEAT, T_FEEDBACK = 0x01, 0x02, 0x03, 0x81
ESTOP_KEY = 0xA5
COMMAND = struct.Struct("<BIBd")
ESTOP = struct.Struct("<BB")
HEARTBEAT = struct.Struct("<BB")
FEEDBACK = struct.Struct("<BIBdd")
_CRC = struct.Struct("<H")
_crc = binascii.crc_hqx
_cobs_encode = cobs.encode
_cobs_decode = cobs.decode


def with_crc(body: bytes) -> bytes:
    """``body`` followed by its CRC-16/CCITT-FALSE (initial 0xFFFF), little-endian."""
    return body + _CRC.pack(_crc(body, 0xFFFF))


def cobs_frame(raw: bytes) -> bytes:
    """COBS-encode ``raw`` and add the 0x00 delimiter."""
    return _cobs_encode(raw) + b"\x00"


def encode_frame(body: bytes) -> bytes:
    """Append the CRC to ``body``, COBS-encode it and add the 0x00 delimiter."""
    return cobs_frame(with_crc(body))


def decode_frame(encoded: bytes) -> tuple[bytes | None, str | None]:
    """Undo :func:`encode_frame` for one frame without its delimiter.

    Returns ``(body, None)`` or ``(None, reason)`` with reason ``bad_cobs``, ``bad_length`` or
    ``bad_crc``.
    """
    try:
        raw = _cobs_decode(encoded)
    except cobs.DecodeError:
        return None, "bad_cobs"
    if len(raw) < 3:
        return None, "bad_length"
    body = raw[:-2]
    if _CRC.unpack_from(raw, len(raw) - 2)[0] != _crc(body, 0xFFFF):
        return None, "bad_crc"
    return body, None

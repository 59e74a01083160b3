"""The CAN message layout, read from the shipped DBC with cantools and compiled for the hot path.

``drivers/can/actuator.dbc`` is the single source of truth (identifiers, signal positions,
sizes, scaling, the reserved "invalid" raw value). At load time cantools parses it and every
message the driver uses is compiled to a list of (start bit, length, signed, scale, offset), all
Intel (little-endian) signals. Packing and unpacking then work on the frame as one little-endian
integer (shift and mask per signal): a few microseconds per frame instead of the ≈ 20–40 µs of
``cantools.Message.encode``/``decode``. The tests assert that this codec and cantools produce
identical bytes and values, so a lab may edit scales in the DBC (e.g. a finer force factor for a
small specimen) and both stay in agreement.

Integrity on CAN is the bus's own CRC-15 (checked by the CAN controller); frames of the wrong
length or with an unknown identifier are rejected and counted by the driver.

:class:`Frame` is the ``can.Message`` the driver and the twin send on the hot path: one object
per message kind, reused, its payload rewritten in place. python-can's virtual bus
deep-copies every frame it delivers; ``can.Message.__deepcopy__`` costs ≈ 10 µs (the
generic deep copy of the ``bytearray`` payload), :meth:`Frame.__deepcopy__` builds the same
plain ``can.Message`` in ≈ 1.5 µs. Interfaces that serialise the frame in ``send`` (SocketCAN
and the others) never copy it; either way the frame on the bus is unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import can
import cantools

from rths_hil.errors import InputError, check_regular_file

__all__ = [
    "DBC_PATH",
    "MAX_DBC_BYTES",
    "ActuatorCodecs",
    "Frame",
    "MessageCodec",
    "load",
    "load_dbc",
]

DBC_PATH = Path(__file__).with_name("actuator.dbc")
#: Largest DBC file read (bytes). An axis controller's DBC is a few kB, a whole vehicle's a few
#: MB; cantools parses about 0.25 MB/s, so this bounds the parse to seconds, not minutes.
MAX_DBC_BYTES = 4 << 20


def _printable(text: str, limit: int = 160) -> str:
    """``text`` with control characters shown as escapes and cut at ``limit`` characters (a
    garbage file's bytes must not reach the operator's terminal as they are)."""
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return out if len(out) <= limit else out[: limit - 1] + "…"


def load_dbc(path: str | Path, what: str = "DBC") -> cantools.database.can.Database:
    """Read a DBC file with cantools, refusing what cannot be one in one line.

    A device (``/dev/zero``), FIFO or directory is refused before it is opened (it would be
    read for ever), a file larger than :data:`MAX_DBC_BYTES` before it is parsed; a parse error
    (cantools: a signal that does not fit its message, a syntax error) names the file, with
    any control bytes of the file escaped.

    Raises
    ------
    InputError
        The one line naming ``what``, the path and the reason.
    """
    p = Path(path)
    check_regular_file(p, f"a {what}", max_bytes=MAX_DBC_BYTES)
    try:
        db = cantools.database.load_file(str(p))
    except OSError as exc:
        raise InputError(f"cannot load {what} {p}: {exc.strerror or exc}") from None
    except (cantools.database.errors.Error, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"cannot load {what} {p}: {_printable(str(exc))}") from None
    if not isinstance(db, cantools.database.can.Database):
        raise InputError(f"cannot load {what} {p}: not a CAN database")
    seen: dict[tuple[int, bool], str] = {}
    for m in db.messages:  # cantools only warns, and decodes frames of that id as the last one
        key = (m.frame_id, m.is_extended_frame)
        if key in seen:
            raise InputError(
                f"cannot load {what} {p}: messages {seen[key]} and {m.name} share the frame id "
                f"0x{m.frame_id:X}: a received frame could not be told apart"
            )
        seen[key] = m.name
    return db


class Frame(can.Message):
    """A ``can.Message`` with a cheap deep copy (see the module docstring).

    The copy is a plain ``can.Message`` with every field of this one and a fresh ``bytearray``
    payload: what ``can.Message.__deepcopy__`` returns, without its keyword-argument
    constructor and the generic ``deepcopy`` of the payload and channel (the channel is a name
    or number; the virtual bus overwrites it anyway). The tests compare every slot of
    ``can.Message`` with python-can's own copy, so a python-can release adding a field fails
    them rather than sending incomplete frames.
    """

    __slots__ = ()

    @classmethod
    def blank(cls, frame_id: int, length: int) -> Frame:
        """A standard-ID data frame of ``length`` zero bytes, to be rewritten in place."""
        return cls(
            arbitration_id=frame_id, is_extended_id=False, dlc=length, data=bytearray(length)
        )

    def __deepcopy__(self, memo: dict | None) -> can.Message:
        m = _new_message(can.Message)
        m.timestamp = self.timestamp
        m.arbitration_id = self.arbitration_id
        m.is_extended_id = self.is_extended_id
        m.is_remote_frame = self.is_remote_frame
        m.is_error_frame = self.is_error_frame
        m.channel = self.channel
        m.dlc = self.dlc
        m.data = bytearray(self.data)
        m.is_fd = self.is_fd
        m.is_rx = self.is_rx
        m.bitrate_switch = self.bitrate_switch
        m.error_state_indicator = self.error_state_indicator
        return m


_new_message = can.Message.__new__


@dataclass(frozen=True)
class MessageCodec:
    """One DBC message compiled to shifts and masks (signals in start-bit order).

    Attributes
    ----------
    frame_id, length : int
        Identifier and DLC from the DBC.
    names : tuple of str
        Signal names in start-bit order.
    starts, lengths : tuple of int
        Start bit and size of each signal (Intel numbering).
    signed : tuple of bool
        Two's-complement signals.
    scales, offsets : tuple of float
        Physical = raw · scale + offset.
    invalid : tuple of int or None
        Raw value named ``INVALID`` in the DBC's value table (decoded as NaN), if any.
    """

    frame_id: int
    length: int
    names: tuple[str, ...]
    starts: tuple[int, ...]
    lengths: tuple[int, ...]
    signed: tuple[bool, ...]
    scales: tuple[float, ...]
    offsets: tuple[float, ...]
    invalid: tuple[int | None, ...]

    @classmethod
    def from_cantools(cls, message: cantools.database.can.Message) -> MessageCodec:
        """Compile ``message``; raise :class:`InputError` for Motorola (big-endian) signals."""
        sigs = sorted(message.signals, key=lambda s: s.start)
        for s in sigs:
            if s.byte_order != "little_endian" or s.is_multiplexer or s.multiplexer_ids:
                raise InputError(
                    f"DBC message {message.name} signal {s.name}: only plain Intel "
                    "(little-endian) signals are supported"
                )
        invalid = []
        for s in sigs:
            named = [int(k) for k, v in (s.choices or {}).items() if str(v) == "INVALID"]
            invalid.append(named[0] if named else None)
        return cls(
            frame_id=message.frame_id,
            length=message.length,
            names=tuple(s.name for s in sigs),
            starts=tuple(s.start for s in sigs),
            lengths=tuple(s.length for s in sigs),
            signed=tuple(bool(s.is_signed) for s in sigs),
            scales=tuple(float(s.scale) for s in sigs),
            offsets=tuple(float(s.offset) for s in sigs),
            invalid=tuple(invalid),
        )

    def pack(self, *raw: int) -> bytes:
        """Pack raw signal values (in :attr:`names` order) into the frame payload."""
        value = 0
        for r, start, n in zip(raw, self.starts, self.lengths, strict=True):
            value |= (r & ((1 << n) - 1)) << start
        return value.to_bytes(self.length, "little")

    def unpack(self, data: bytes | bytearray) -> list[int]:
        """Raw signal values (in :attr:`names` order) of a payload of :attr:`length` bytes."""
        value = int.from_bytes(data, "little")
        out = []
        for start, n, sgn in zip(self.starts, self.lengths, self.signed, strict=True):
            r = (value >> start) & ((1 << n) - 1)
            if sgn and r >> (n - 1):
                r -= 1 << n
            out.append(r)
        return out

    def field(self, index: int) -> tuple[int, int]:
        """Bit position and mask (``(1 << length) − 1``) of signal ``index``."""
        return self.starts[index], (1 << self.lengths[index]) - 1

    def sign_bit(self, index: int) -> int:
        """The sign bit of signal ``index`` as a value (0 for an unsigned signal)."""
        return 1 << (self.lengths[index] - 1) if self.signed[index] else 0

    def raw_range(self, index: int) -> tuple[int, int]:
        """Smallest and largest raw value of signal ``index``."""
        n = self.lengths[index]
        if self.signed[index]:
            return -(1 << (n - 1)), (1 << (n - 1)) - 1
        return 0, (1 << n) - 1


@dataclass(frozen=True)
class ActuatorCodecs:
    """All messages of the actuator DBC, compiled."""

    database: cantools.database.can.Database
    estop: MessageCodec
    command: MessageCodec
    feedback: MessageCodec
    heartbeat: MessageCodec
    estop_key: int


_NEEDED = {
    "EStop": ("EStopKey",),
    "Command": ("Seq", "Displacement", "Control"),
    "Feedback": ("Seq", "Status", "Displacement", "Force"),
    "Heartbeat": ("Counter",),
}


@cache
def load(path: str | None = None) -> ActuatorCodecs:
    """Load and compile the actuator DBC (``drivers/can/actuator.dbc`` by default).

    Raises
    ------
    InputError
        Missing or unreadable file, or a message the driver needs is absent or carries other
        signals (the message names them).
    """
    p = Path(path) if path else DBC_PATH
    db = load_dbc(p)
    codecs = {}
    for name, signals in _NEEDED.items():
        try:
            msg = db.get_message_by_name(name)
        except KeyError:
            raise InputError(f"DBC {p}: message {name} is missing") from None
        codec = MessageCodec.from_cantools(msg)
        if codec.names != signals:
            raise InputError(
                f"DBC {p}: message {name} must carry signals {', '.join(signals)} "
                f"in this bit order, found {', '.join(codec.names)}"
            )
        codecs[name] = codec
    estop_key = db.get_message_by_name("EStop").get_signal_by_name("EStopKey")
    choices: Mapping[int, object] = estop_key.choices or {}
    keys = [int(k) for k, v in choices.items() if str(v) == "ESTOP"]
    return ActuatorCodecs(
        database=db,
        estop=codecs["EStop"],
        command=codecs["Command"],
        feedback=codecs["Feedback"],
        heartbeat=codecs["Heartbeat"],
        estop_key=keys[0] if keys else 0xA5,
    )

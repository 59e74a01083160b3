"""CAN driver: python-can bus, messages from the shipped DBC (``actuator.dbc``).

Per step the bridge sends one ``Command`` (ID 0x100: 16-bit ``Seq``, displacement, control
byte) and the controller answers with one ``Feedback`` frame (0x180: low byte of ``Seq``,
status, measured displacement, measured force), so that a 1024 Hz loop costs two frames per
step (≈ 260 µs of a 1 Mbit/s bus). ``EStop`` (0x010) has the lowest identifier of the set, so it
wins arbitration on a busy bus. ``Heartbeat`` (0x700) is optional. Layout and scaling are in
``docs/protocols.md`` and the DBC; :mod:`drivers.can.codec` compiles the DBC for the hot path.

The bus is opened through python-can from configuration: ``interface`` (default
``"virtual"``, in-process only), ``channel``, ``bitrate`` and any extra python-can options in
``bus_options``. On Linux with SocketCAN use ``interface="socketcan", channel="vcan0"``
(or ``can0``).
"""

from __future__ import annotations

import math
import time
from typing import Any, ClassVar

import can

from rths_hil.errors import InputError

from ..base import Driver, Feedback, check_command, extend_seq
from .codec import ActuatorCodecs, load

__all__ = ["CANDriver"]

_BUS_ERRORS = (can.CanError, OSError, ValueError, ImportError, NotImplementedError)


class CANDriver(Driver):
    """Lockstep actuator driver over CAN (see the module docstring).

    Parameters
    ----------
    interface : str
        python-can interface name (``virtual``, ``socketcan``, ``pcan``, ``kvaser`` …).
    channel : str
        Bus channel (``vcan0``, ``can0``, or any name on the virtual interface).
    bitrate : int, optional
        Bit rate in bit/s, for interfaces that set it.
    dbc : str, optional
        Path to a DBC replacing the shipped one (same message and signal names).
    bus_options : dict, optional
        Extra keyword arguments for ``can.Bus``.
    """

    name: ClassVar[str] = "can"

    def __init__(
        self,
        interface: str = "virtual",
        channel: str = "rths-hil",
        bitrate: int | None = None,
        dbc: str | None = None,
        bus_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.interface = str(interface)
        self.channel = str(channel)
        self.bitrate = None if bitrate is None else int(bitrate)
        self.bus_options = dict(bus_options or {})
        self.codecs: ActuatorCodecs = load(dbc)
        cmd, fb = self.codecs.command, self.codecs.feedback
        # Command: Seq, Displacement, Control — shifts and masks precompiled from the DBC.
        self._c_seq_bits = cmd.lengths[0]
        self._c_seq_mask = (1 << cmd.lengths[0]) - 1
        self._c_d_shift, self._c_d_mask = cmd.starts[1], (1 << cmd.lengths[1]) - 1
        self._c_ctl_shift = cmd.starts[2]
        self._c_scale, self._c_offset = cmd.scales[1], cmd.offsets[1]
        self._c_lo, self._c_hi = cmd.raw_range(1)
        self._c_len = cmd.length
        # Feedback: Seq, Status, Displacement, Force.
        self._f_seq_bits = fb.lengths[0]
        self._f_seq_shift, self._f_seq_mask = fb.starts[0], (1 << fb.lengths[0]) - 1
        self._f_st_shift, self._f_st_mask = fb.starts[1], (1 << fb.lengths[1]) - 1
        self._f_d_shift, self._f_d_mask = fb.starts[2], (1 << fb.lengths[2]) - 1
        self._f_d_sign = 1 << (fb.lengths[2] - 1) if fb.signed[2] else 0
        self._f_f_shift, self._f_f_mask = fb.starts[3], (1 << fb.lengths[3]) - 1
        self._f_f_sign = 1 << (fb.lengths[3] - 1) if fb.signed[3] else 0
        self._f_d_scale, self._f_d_offset = fb.scales[2], fb.offsets[2]
        self._f_f_scale, self._f_f_offset = fb.scales[3], fb.offsets[3]
        self._f_d_invalid, self._f_f_invalid = fb.invalid[2], fb.invalid[3]
        self._f_id, self._f_len = fb.frame_id, fb.length
        self._cmd_msg = can.Message(
            arbitration_id=cmd.frame_id, is_extended_id=False, dlc=cmd.length
        )
        self._bus: can.BusABC | None = None
        self._hb = 0

    def open(self) -> None:
        if self._bus is not None:
            return
        kwargs = dict(self.bus_options)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **kwargs)
        except _BUS_ERRORS as exc:
            raise InputError(
                f"CAN driver: cannot open interface {self.interface!r} channel "
                f"{self.channel!r}: {exc}"
            ) from None

    def close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except _BUS_ERRORS:  # pragma: no cover - already gone
                pass

    def _send_frame(self, msg: can.Message) -> None:
        if self._bus is None:
            self.stats.send_errors += 1
            return
        try:
            self._bus.send(msg)
        except (can.CanError, OSError):
            self.stats.send_errors += 1

    def send(self, seq: int, displacement: float, enable: bool = True) -> None:
        check_command(seq, displacement)
        raw = round((displacement - self._c_offset) / self._c_scale)
        if not self._c_lo <= raw <= self._c_hi:
            raise InputError(
                f"command displacement {displacement} m for step {seq}: out of DBC range"
            )
        value = (
            (seq & self._c_seq_mask)
            | ((raw & self._c_d_mask) << self._c_d_shift)
            | ((1 if enable else 0) << self._c_ctl_shift)
        )
        msg = self._cmd_msg
        msg.data = bytearray(value.to_bytes(self._c_len, "little"))
        self._last_sent = seq
        self.stats.sent += 1
        self._send_frame(msg)

    def estop(self) -> None:
        c = self.codecs.estop
        self.stats.estops += 1
        data = c.pack(self.codecs.estop_key)
        self._send_frame(can.Message(arbitration_id=c.frame_id, data=data, is_extended_id=False))

    def heartbeat(self) -> None:
        c = self.codecs.heartbeat
        self._hb = (self._hb + 1) & 0xFF
        self._send_frame(
            can.Message(arbitration_id=c.frame_id, data=c.pack(self._hb), is_extended_id=False)
        )

    def receive(self, timeout: float) -> Feedback | None:
        bus = self._bus
        stats = self.stats
        if bus is None:
            stats.timeouts += 1
            return None
        deadline = time.perf_counter() + timeout
        remaining = timeout
        while True:
            try:
                msg = bus.recv(remaining)
            except (can.CanError, OSError):
                stats.disconnects += 1
                msg = None
            if msg is None:
                stats.timeouts += 1
                return None
            fb = self._handle(msg)
            if fb is not None:
                return fb
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                stats.timeouts += 1
                return None

    def _handle(self, msg: can.Message) -> Feedback | None:
        stats = self.stats
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            stats.count_malformed("bad_frame")
            return None
        if msg.arbitration_id != self._f_id:
            stats.count_malformed("unknown_id")
            return None
        data = msg.data
        if len(data) != self._f_len:
            stats.count_malformed("bad_length")
            return None
        v = int.from_bytes(data, "little")
        seq = extend_seq(
            (v >> self._f_seq_shift) & self._f_seq_mask, self._last_sent, self._f_seq_bits
        )
        if not self._classify(seq):
            return None
        status = (v >> self._f_st_shift) & self._f_st_mask
        rd = (v >> self._f_d_shift) & self._f_d_mask
        if rd & self._f_d_sign:
            rd -= self._f_d_sign << 1
        rf = (v >> self._f_f_shift) & self._f_f_mask
        if rf & self._f_f_sign:
            rf -= self._f_f_sign << 1
        stats.received += 1
        if rd == self._f_d_invalid or rf == self._f_f_invalid:
            stats.invalid_values += 1
        disp = math.nan if rd == self._f_d_invalid else rd * self._f_d_scale + self._f_d_offset
        force = math.nan if rf == self._f_f_invalid else rf * self._f_f_scale + self._f_f_offset
        return Feedback(seq, disp, force, status)

"""CAN twin endpoint: a controller node on a python-can bus, in a thread.

It answers every ``Command`` (DBC ``drivers/can/actuator.dbc``) with one ``Feedback`` frame
echoing the low byte of ``Seq``, latches on ``EStop`` (key 0xA5) and records ``Heartbeat``
frames. Malformed frames (wrong length, unknown ID, error frames) are counted and ignored.
The ``corrupt`` fault sends the feedback truncated by one byte (what a broken gateway or a
DLC error looks like to software; the bus CRC-15 discards bit errors before software sees them).
"""

from __future__ import annotations

import math
from typing import Any

import can

from drivers.can.codec import load
from rths_hil.errors import InputError

from .base import TwinController, TwinEndpoint

__all__ = ["CANTwin"]


class CANTwin(TwinEndpoint):
    """Controller node on ``interface``/``channel`` (``virtual`` buses are in-process only)."""

    name = "can"

    def __init__(
        self,
        controller: TwinController,
        interface: str = "virtual",
        channel: str = "rths-hil",
        bitrate: int | None = None,
        dbc: str | None = None,
        bus_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(controller)
        self.interface, self.channel, self.bitrate = str(interface), str(channel), bitrate
        self.dbc = dbc
        self.bus_options = dict(bus_options or {})
        self.codecs = load(dbc)
        fb = self.codecs.feedback
        self._d_range, self._f_range = fb.raw_range(2), fb.raw_range(3)
        self._bus: can.BusABC | None = None

    def _setup(self) -> None:
        kwargs = dict(self.bus_options)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **kwargs)
        except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
            raise InputError(
                f"CAN twin: cannot open interface {self.interface!r} channel "
                f"{self.channel!r}: {exc}"
            ) from None
        self.connection = {"interface": self.interface, "channel": self.channel}
        if self.bitrate is not None:
            self.connection["bitrate"] = self.bitrate
        if self.dbc is not None:
            self.connection["dbc"] = self.dbc
        if self.bus_options:
            self.connection["bus_options"] = dict(self.bus_options)
        self.where = f"CAN interface {self.interface} channel {self.channel}"

    def _teardown(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    @property
    def supports_inline(self) -> bool:  # type: ignore[override]
        """Only python-can's in-process ``virtual`` bus delivers frames synchronously."""
        return self.interface == "virtual"

    def pump(self) -> int:
        """Serve every frame already on the bus (inline mode); return how many."""
        bus = self._bus
        n = 0
        while bus is not None:
            msg = bus.recv(0.0)
            if msg is None:
                break
            if not self._gone:
                self._handle(msg)
            n += 1
        self.controller.check_watchdog()
        return n

    def _serve_once(self, timeout: float) -> None:
        bus = self._bus
        assert bus is not None
        msg = bus.recv(timeout)
        if msg is None or self._gone:
            return
        self._handle(msg)

    def _handle(self, msg: can.Message) -> None:
        c = self.codecs
        fid = msg.arbitration_id
        ctl = self.controller
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            ctl.stats.malformed += 1
        elif fid == c.command.frame_id:
            if len(msg.data) != c.command.length:
                ctl.stats.malformed += 1
                return
            raw_seq, raw_d, control = c.command.unpack(msg.data)
            disp = raw_d * c.command.scales[1] + c.command.offsets[1]
            self.emit(ctl.command(raw_seq, disp, bool(control & 1)))
        elif fid == c.estop.frame_id:
            if len(msg.data) == 1 and msg.data[0] == c.estop_key:
                ctl.estop()
            else:
                ctl.stats.malformed += 1
        elif fid == c.heartbeat.frame_id:
            ctl.heartbeat()
        else:
            ctl.stats.malformed += 1

    @staticmethod
    def _raw(
        value: float, scale: float, offset: float, rng: tuple[int, int], invalid: int | None
    ) -> int:
        if not math.isfinite(value):
            return rng[0] if invalid is None else invalid
        lo = rng[0] + (1 if invalid == rng[0] else 0)
        return max(lo, min(rng[1], round((value - offset) / scale)))

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        fb = self.codecs.feedback
        data = fb.pack(
            seq,
            status,
            self._raw(displacement, fb.scales[2], fb.offsets[2], self._d_range, fb.invalid[2]),
            self._raw(force, fb.scales[3], fb.offsets[3], self._f_range, fb.invalid[3]),
        )
        return [can.Message(arbitration_id=fb.frame_id, data=data, is_extended_id=False)]

    def _corrupt(self, frame: can.Message) -> can.Message:
        return can.Message(
            arbitration_id=frame.arbitration_id, data=frame.data[:-1], is_extended_id=False
        )

    def _write(self, frame: can.Message) -> None:
        assert self._bus is not None
        try:
            self._bus.send(frame)
        except (can.CanError, OSError):  # pragma: no cover - bus gone
            pass

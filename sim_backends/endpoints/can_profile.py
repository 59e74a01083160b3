"""CAN twin for a profile: a controller node speaking the lab's own DBC.

The twin loads the same profile as the driver (:mod:`rths_hil.drivers.profile`) and answers each
command frame with one feedback frame, both encoded and decoded by cantools from the DBC
(Motorola or Intel signals, standard or extended identifiers). Like the lab's controller it
echoes no sequence number. Controller behaviour (the :class:`~.base.TwinController` of every
twin): a command with the enable signal at ``actions.enable``'s value is one plant step; one
with it at ``actions.disable``'s value holds; the acknowledge signal at its value (sent with the
enable flag off) starts a new run as the built-in twins' arming command does (latch cleared,
plant at rest, step count from 0); the e-stop frame latches; a command or a heartbeat frame
feeds the controller-side watchdog. A force-controlled plant (``plant.control == "force"``)
takes the ``roles.force_setpoint`` signal's value in N unchanged (a profile without it is
refused). Frame faults of a fault plan (drop, corrupt, delay, duplicate) apply to the feedback
frames; a ``nan`` fault sets the status word's ``sensor_invalid`` bit (when the profile maps
one) and repeats the last position, as an integer signal cannot carry NaN.
"""

from __future__ import annotations

import math
import queue
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import can
from rths_hil.drivers.can import SharedBus, release_bus, shared_bus
from rths_hil.drivers.can.codec import Frame
from rths_hil.drivers.can.profile_format import CANProfile
from rths_hil.drivers.profile import load_profile, word_from_status

from rths_hil.errors import InputError

from .base import TwinController, TwinEndpoint
from .nullmodem import LINE_KEYS, CANLine

if TYPE_CHECKING:
    from rths_hil.keys import Key

__all__ = ["CANProfileTwin"]


class CANProfileTwin(CANLine, TwinEndpoint):
    """Controller node on ``interface``/``channel`` speaking ``profile``."""

    name = "can"
    #: The line (:data:`~.nullmodem.LINE_KEYS`); the profile comes apart.
    CONNECTION: ClassVar[Mapping[str, Key]] = LINE_KEYS

    def __init__(
        self,
        controller: TwinController,
        profile: str,
        interface: str = "virtual",
        channel: str | None = None,
        bitrate: int | None = None,
        bus_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(controller)
        prof = load_profile(profile)
        if not isinstance(prof, CANProfile):
            raise InputError(f"can twin: profile {profile} is not a CAN profile")
        self.profile_path = str(profile)
        self.profile = prof
        self.interface = str(interface)
        self.channel = str(channel or "rths-hil")
        self.bitrate = bitrate
        self.bus_options = dict(bus_options or {})
        db = prof.database
        self._cmd, self._fb = prof.command, prof.feedback
        self._estop = db.get_message_by_name(prof.actions["estop"].message)
        self._hb = db.get_message_by_name(prof.heartbeat.message) if prof.heartbeat else None
        r = prof.roles
        try:  # the set-point the controller follows: roles.setpoint, or the force set-point
            sp = prof.for_control(self.control).roles["setpoint"]
        except InputError as exc:
            raise InputError(f"can twin: {exc}") from None
        self._sp = (sp.signal, sp.factor)
        self._fbsig = {
            "position": (r["position"].signal, r["position"].factor),
            "force": (r["force"].signal, r["force"].factor),
        }
        self._status_sig = r["status"].signal
        acts = prof.actions
        self._enable = (acts["enable"].signal, acts["enable"].value) if "enable" in acts else None
        self._ack = (
            (acts["acknowledge"].signal, acts["acknowledge"].value)
            if "acknowledge" in acts
            else None
        )
        self._estop_sig = (acts["estop"].signal, acts["estop"].value)
        #: a controller that selects its loop on command: the force loop's signal and value
        #: (any other value of it, or none, is the displacement loop)
        self._modes = bool({"force_mode", "displacement_mode"} & set(acts))
        fm = acts.get("force_mode")
        self._force_loop = (fm.signal, fm.value) if fm is not None else None
        self._fb_limits = {s.name: (s.minimum, s.maximum) for s in self._fb.signals}
        self._share: SharedBus | None = None
        self._bus: can.BusABC | None = None
        self._k = 0
        self._last: dict[str, float] = {}  # the last value sent of each feedback signal

    def _setup(self) -> None:
        # serial or slcan with channel "pty": a null-modem pair of pseudo-terminals
        channel, bridge_channel, kwargs, options = self._open_line("can twin")
        try:
            self._share = shared_bus("twin", self.interface, channel, **kwargs)
        except InputError:
            self._close_cable()
            raise
        self._bus = self._share.bus
        conn = {
            "interface": self.interface,
            "channel": bridge_channel,
            "profile": self.profile_path,
        }
        self.connection = self._bridge_end(conn, options)
        self.where = f"can {self.interface}:{bridge_channel} ({self.profile_path}){self._line_note}"

    def _teardown(self) -> None:
        share, self._share = self._share, None
        self._bus = None
        if share is not None:
            release_bus(share)
        self._close_cable()

    def _serve_once(self, timeout: float) -> None:
        share = self._share
        if share is None or self._gone:
            self._stop.wait(timeout)
            return
        q = share.rxq
        try:
            msg = q.get(True, timeout) if q is not None else share.bus.recv(timeout)
        except queue.Empty:
            return
        except (can.CanError, OSError):  # pragma: no cover - bus gone
            self._stop.wait(timeout)
            return
        if msg is not None:
            self._handle(msg)

    def _handle(self, msg: can.Message) -> None:
        ctl = self.controller
        aid, ext = msg.arbitration_id, bool(msg.is_extended_id)
        try:
            if aid == self._cmd.frame_id and ext == bool(self._cmd.is_extended_frame):
                v = self._cmd.decode(msg.data, decode_choices=False)
                x = float(v[self._sp[0]]) * self._sp[1]  # type: ignore[arg-type]
                enable = self._enable is None or v[self._enable[0]] == self._enable[1]
                if self._modes:  # the loop the frame selects must be the plant's
                    fl = self._force_loop
                    force = fl is not None and v[fl[0]] == fl[1]
                    enable = enable and force == (self.control == "force")
                if self._ack is not None and not enable and v[self._ack[0]] == self._ack[1]:
                    reply = ctl.command(0, x, False)  # a new run: arm; the run's step 0 next
                    self._k = 0
                else:
                    reply = ctl.command(self._k, x, bool(enable))
                    self._k += 1
                self.emit(reply)
            elif aid == self._estop.frame_id and ext == bool(self._estop.is_extended_frame):
                v = self._estop.decode(msg.data, decode_choices=False)
                if v[self._estop_sig[0]] == self._estop_sig[1]:
                    ctl.estop()
            elif (
                self._hb is not None
                and aid == self._hb.frame_id
                and ext == bool(self._hb.is_extended_frame)
            ):
                ctl.heartbeat()
        except (ValueError, KeyError):
            ctl.stats.malformed += 1

    def _clamp(self, name: str, value: float) -> float:
        if not math.isfinite(value):  # not representable in an integer signal: the last value
            return self._last.get(name, 0.0)
        lo, hi = self._fb_limits[name]
        if lo is not None and value < lo:
            return float(lo)
        if hi is not None and value > hi:
            return float(hi)
        return value

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        (ps, pf), (fs, ff) = self._fbsig["position"], self._fbsig["force"]
        values = {s.name: 0.0 for s in self._fb.signals}
        values[ps] = self._last[ps] = self._clamp(ps, displacement / pf)
        values[fs] = self._last[fs] = self._clamp(fs, force / ff)
        values[self._status_sig] = word_from_status(status, self.profile.masks)
        data = self._fb.encode(values, strict=False)
        return [
            Frame(
                arbitration_id=self._fb.frame_id,
                is_extended_id=bool(self._fb.is_extended_frame),
                dlc=len(data),
                data=bytearray(data),
            )
        ]

    def _corrupt(self, frame: can.Message) -> can.Message:
        data = bytes(frame.data[:-1])  # a short frame: the driver counts it as malformed
        return can.Message(
            arbitration_id=frame.arbitration_id,
            is_extended_id=frame.is_extended_id,
            data=data,
        )

    def _write(self, frame: can.Message) -> None:
        self._send(self._bus, frame)

"""CAN driver for a controller described by the lab's own DBC and a profile (:mod:`..profile`).

The profile names, for each role, a DBC message and signal; cantools encodes the command and
decodes the feedback with the DBC's byte order (Intel or Motorola), sign, scale and offset, and
the profile's (or the DBC's) unit converts to SI. Standard and extended identifiers come from
the DBC. Every frame is encoded and decoded by cantools (``Message.encode`` with ``scaling``
and without its range check, which the driver does for the set-point itself;
``Message.decode`` without choices): the standard comes through its library. The e-stop
frame is encoded once. Per step the driver sends one command frame: the set-point
signal, the enable signal (``actions.enable`` / ``actions.disable``) and, with the enable flag
off, the acknowledge signal; the e-stop is a frame of its own (``actions.estop``), the
heartbeat a counter signal.

Such a controller echoes no sequence number, so the base class's rule for it applies
(:attr:`~..base.Driver.echoes_seq` false): the first feedback frame received after a command
answers it, and its age (time since the command was sent) is recorded. Feedback frames that
arrived before the command (answers to an earlier one, e.g. after a timeout) are taken off
the bus when the command is sent and counted as ``late``.

The bus is opened as for :class:`~.CANDriver` (python-can, shared per interface and channel).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import partial
from typing import Any, ClassVar

import can
from cantools.database.errors import Error as CantoolsError

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..base import Feedback
from ..profile import MODE_ACTIONS, status_from_word
from ..profile_driver import ProfileDriver
from . import BUS_KEYS, SharedBusDriver
from .codec import Frame
from .profile_format import CANProfile

__all__ = ["CANProfileDriver"]


class CANProfileDriver(ProfileDriver, SharedBusDriver):
    """Lockstep driver for a CAN controller with its own DBC (see the module docstring).

    Parameters
    ----------
    profile : str
        Path of the profile file (``protocol = "can"``).
    interface, channel, bitrate, bus_options
        The python-can bus, as for :class:`~.CANDriver`.
    """

    name: ClassVar[str] = "can"
    honours_deadline: ClassVar[bool] = True
    echoes_seq: ClassVar[bool] = False
    #: the bus settings (the profile is ``driver.profile``)
    CONNECTION: ClassVar[Mapping[str, Key]] = BUS_KEYS

    def __init__(
        self,
        profile: str,
        interface: str = "virtual",
        channel: str = "rths-hil",
        bitrate: int | None = None,
        bus_options: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        prof = self._load_profile(profile, CANProfile, "CAN")
        cmd, fb = prof.command, prof.feedback
        self._init_bus(interface, channel, bitrate, bus_options, fb.frame_id)
        self._cmd = cmd
        self._fb = fb
        r = prof.roles
        self._use_setpoint()
        self._estop_sent = False  # an e-stop sent and not yet acknowledged
        # the command's signals: every one 0 (or its DBC initial value) unless a role sets it
        self._values: dict[str, float] = {
            s.name: float(s.raw_initial or 0) * s.scale + s.offset for s in cmd.signals
        }
        acts = prof.actions
        # (signal, value) each action writes (an action's value is always given: default 1)
        self._on, self._off, self._ack = (
            (acts[a].signal, float(acts[a].value or 0.0)) if a in acts else None
            for a in ("enable", "disable", "acknowledge")
        )
        self._use_mode()
        self._pos = (r["position"].signal, r["position"].factor)
        self._force = (r["force"].signal, r["force"].factor)
        self._status = r["status"].signal
        self._masks = prof.masks
        self._flags: dict[int, int] = {}
        self._fb_ext = bool(fb.is_extended_frame)
        # one command frame, reused: send() rewrites its payload in place (codec.Frame copies
        # cheaply on the virtual bus)
        self._cmd_frame = Frame(
            arbitration_id=cmd.frame_id,
            is_extended_id=bool(cmd.is_extended_frame),
            dlc=cmd.length,
            data=bytearray(cmd.length),
        )
        self._cmd_data = self._cmd_frame.data
        self._decode = partial(
            fb.decode if fb.is_container else fb.decode_simple, decode_choices=False, scaling=True
        )
        self._encode = partial(cmd.encode, scaling=True, padding=False, strict=False)
        est = prof.actions["estop"]
        emsg = prof.database.get_message_by_name(est.message)
        self._estop_frame = can.Message(
            arbitration_id=emsg.frame_id,
            is_extended_id=bool(emsg.is_extended_frame),
            data=emsg.encode(
                {s.name: est.value if s.name == est.signal else 0 for s in emsg.signals}
            ),
        )
        self._hb_msg = None
        if prof.heartbeat is not None:
            self._hb_msg = prof.database.get_message_by_name(prof.heartbeat.message)
        self._hb = 0

    def _use_setpoint(self) -> None:
        """The set-point signal of the command frame: ``roles.setpoint``, or
        ``roles.force_setpoint`` in force mode (:meth:`set_control`)."""
        sp = self.profile.roles["setpoint"]
        self._sp_sig, self._sp_factor = sp.signal, sp.factor
        sig = self._cmd.get_signal_by_name(sp.signal)
        self._sp_range = (sig.minimum, sig.maximum)

    def set_control(self, mode: str) -> None:
        """Select the wire mode before :meth:`open` (:meth:`ProfileDriver.set_control`): the
        set-point signal of every command frame, and the loop's mode signal (:meth:`_use_mode`).
        """
        super().set_control(mode)
        self._use_mode()

    def _use_mode(self) -> None:
        """A controller that selects its loop on command: the signal of the channel's loop
        (``actions.force_mode`` / ``actions.displacement_mode``) at its value in every frame."""
        acts = self.profile.actions
        act = acts.get(MODE_ACTIONS[self.control])
        if act is not None:
            self._values[act.signal] = float(act.value or 0.0)
        elif "force_mode" in acts:  # the displacement loop: the force loop's signal at rest
            sig = self._cmd.get_signal_by_name(acts["force_mode"].signal)
            self._values[sig.name] = float(sig.raw_initial or 0) * sig.scale + sig.offset

    # -- transport: the shared bus (SharedBusDriver) -----------------------------------------
    def _holder(self) -> str:
        return f"a driver for feedback id 0x{self._fb_id:X}"

    # -- commands -------------------------------------------------------------------------------
    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        value = displacement / self._sp_factor
        lo, hi = self._sp_range
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            what = "force" if self.control == "force" else "displacement"
            unit = "N" if self.control == "force" else "m"
            raise InputError(
                f"command {what} {displacement} {unit} for step {seq}: out of the DBC range "
                f"of {self._cmd.name}.{self._sp_sig}"
            )
        values = self._values
        values[self._sp_sig] = value
        if enable:
            if self._on is not None:
                values[self._on[0]] = self._on[1]
        elif self._off is not None:
            values[self._off[0]] = self._off[1]
        if self._ack is not None:
            # the arming command (a new run) or the first disable after our e-stop acknowledges;
            # the hand-back at a normal end only disables
            ack = not enable and (seq == 0 or self._estop_sent)
            values[self._ack[0]] = self._ack[1] if ack else 0
            if ack:
                self._estop_sent = False
        self._cmd_data[:] = self._encode(values)
        self._drain_stale()
        self._send_frame(self._cmd_frame)

    def _drain_stale(self) -> None:
        """Feedback already waiting answers an earlier command: count it late, drop it."""
        box = self._box
        while box:
            if self._parse(box.popleft()) is not None:
                self.stats.late += 1
        q = self._rxq
        if q is not None:
            frames = q.queue
            while frames:
                if self._parse(frames.popleft()) is not None:
                    self.stats.late += 1

    def estop(self) -> None:
        self.stats.estops += 1
        self._estop_sent = True  # the next disable acknowledges it
        self._send_frame(self._estop_frame)

    def heartbeat(self) -> None:
        m = self._hb_msg
        hb = self.profile.heartbeat
        if m is None or hb is None:
            return
        self._hb = (self._hb + 1) & 0xFF
        data = m.encode(
            {s.name: self._hb if s.name == hb.signal else 0 for s in m.signals}, strict=False
        )
        self._send_frame(
            can.Message(
                arbitration_id=m.frame_id, is_extended_id=bool(m.is_extended_frame), data=data
            )
        )

    # -- feedback -------------------------------------------------------------------------------
    def _parse(self, msg: can.Message) -> Feedback | None:
        if msg.is_error_frame or msg.is_remote_frame:
            self.stats.count_malformed("bad_frame")
            return None
        if msg.arbitration_id != self._fb_id or bool(msg.is_extended_id) != self._fb_ext:
            other = self._routes.get(msg.arbitration_id)
            if other is not None and other is not self._box:
                other.append(msg)
            else:
                self.stats.count_malformed("unknown_id")
            return None
        if len(msg.data) != self._fb.length:
            self.stats.count_malformed("bad_length")
            return None
        try:
            v = self._decode(msg.data)
        except (ValueError, KeyError, CantoolsError):
            self.stats.count_malformed("bad_frame")
            return None
        ps, pf = self._pos
        fs, ff = self._force
        word = int(v[self._status])  # type: ignore[arg-type]
        d = float(v[ps]) * pf  # type: ignore[arg-type]
        f = float(v[fs]) * ff  # type: ignore[arg-type]
        flags = self._flags.get(word)
        if flags is None:  # the bridge's flags of a status word, looked up once per word
            flags = self._flags[word] = status_from_word(word, self._masks)
        return Feedback(-1, d if math.isfinite(d) else math.nan, f, flags)

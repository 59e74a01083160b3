"""CAN twin endpoint: a controller node on a python-can bus, in a thread.

It answers every ``Command`` (DBC ``drivers/can/actuator.dbc``) with one ``Feedback`` frame
echoing the low byte of ``Seq``, latches on ``EStop`` (key 0xA5) and records ``Heartbeat``
frames. Malformed frames (wrong length, unknown ID, error frames) are counted and ignored.
The ``corrupt`` fault sends the feedback truncated by one byte (what a broken gateway or a
DLC error looks like to software; the bus CRC-15 discards bit errors before software sees them).

Per frame the endpoint decodes the command and encodes the feedback with shifts and masks compiled
once from the DBC (the same layout as :class:`rths_hil.drivers.can.codec.MessageCodec`, whose tests
check it against cantools) and sends one reused :class:`rths_hil.drivers.can.codec.Frame` whose
payload is rewritten in place. Served inline on python-can's virtual bus, :meth:`CANTwin.pump` reads
the bus's receive queue directly (:func:`rths_hil.drivers.can.virtual_rx_queue`).

Several twins on one bus are CAN nodes (``node``: every identifier offset by the node number, see
:mod:`rths_hil.drivers.can`). They share one python-can bus object
(:func:`rths_hil.drivers.can.shared_bus`, twin side); whichever endpoint reads a frame hands it to
the endpoint of its identifier, so pumping any of them (inline) or any of their threads serves them
all.

**As its own process** (``rths-hil twin serve --driver can --interface serial`` or ``slcan``):
python-can's serial-line interfaces over a virtual null-modem cable of two pseudo-terminals
(:class:`~rths_hil.sim_backends.endpoints.nullmodem.NullModem`). The twin opens one end with
python-can and hands the bridge the other (``connection = {"interface": "serial", "channel":
"/dev/pts/N"}``); both sides use python-can's framing, and nothing leaves the machine. ``slcan`` is
the ASCII protocol of USB–CAN adapters (Lawicel, CANable): 22 characters per 8-byte frame, parsed by
python-can one byte at a time (≈ 0.8 ms round trip here, enough for paced runs up to ≈ 512 Hz);
``serial`` is python-can's binary framing (19 bytes per frame, ≈ 0.3 ms round trip: paced 1024 Hz).
``channel="pty"`` (their default) asks for the cable; any other channel is a serial device opened as
it is.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import can
from rths_hil.drivers.can import CANDriver, SharedBus, check_node, release_bus, shared_bus
from rths_hil.drivers.can.codec import Frame, load

from rths_hil.errors import InputError

from ..registry import TwinEntry
from .base import TwinController, TwinEndpoint
from .can_profile import CANProfileTwin
from .nullmodem import LINE_KEYS, PTY_CHANNEL, PTY_INTERFACES, CANLine, can_line_from_args

if TYPE_CHECKING:
    from rths_hil.keys import Key

log = logging.getLogger(__name__)

__all__ = ["PTY_CHANNEL", "PTY_INTERFACES", "CANTwin"]

#: What :meth:`CANTwin._recv` returns for bytes on the line that are no frame.
_GARBLED = object()


class CANTwin(CANLine, TwinEndpoint):
    """Controller node on ``interface``/``channel`` (``virtual`` buses are in-process only;
    ``serial`` or ``slcan`` with ``channel="pty"`` reaches other processes on this machine, see
    the module docstring)."""

    name = "can"
    #: The line (:data:`~.nullmodem.LINE_KEYS`), the driver's ``dbc`` and ``node``.
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        **LINE_KEYS,
        **{k: CANDriver.CONNECTION[k] for k in ("dbc", "node")},
    }

    @classmethod
    def profile_twin(cls) -> type[TwinEndpoint]:
        """A lab's own DBC: :class:`~.can_profile.CANProfileTwin`."""
        return CANProfileTwin

    @classmethod
    def connection_from_args(cls, args: Any) -> dict[str, Any]:
        """``--interface``, ``--channel`` and ``--bitrate``
        (:func:`~.nullmodem.can_line_from_args`; python-can's ``virtual`` bus is refused: it
        cannot leave the process)."""
        return can_line_from_args(args, "can twin")

    def __init__(
        self,
        controller: TwinController,
        interface: str = "virtual",
        channel: str | None = None,
        bitrate: int | None = None,
        dbc: str | None = None,
        bus_options: dict[str, Any] | None = None,
        node: int = 0,
    ) -> None:
        super().__init__(controller)
        self.node = check_node(node)
        if channel is None:
            channel = PTY_CHANNEL if interface in PTY_INTERFACES else "rths-hil"
        self.interface, self.channel, self.bitrate = str(interface), str(channel), bitrate
        self.dbc = dbc
        self.bus_options = dict(bus_options or {})
        self.codecs = c = load(dbc)
        fb, cmd = c.feedback, c.command
        self._d_range, self._f_range = fb.raw_range(2), fb.raw_range(3)
        # Command (Seq, Displacement, Control) decoding, compiled: one tuple read per frame.
        sign = cmd.sign_bit(1)
        self._cmd_layout = (
            cmd.frame_id + node,
            cmd.length,
            *cmd.field(0),
            *cmd.field(1),
            sign,
            sign << 1,
            *cmd.field(2),
            cmd.scales[1],
            cmd.offsets[1],
        )
        # Feedback (Seq, Status, Displacement, Force) encoding, compiled.
        d_inv, f_inv = fb.invalid[2], fb.invalid[3]
        self._fb_layout = (
            *fb.field(0),
            *fb.field(1),
            *fb.field(2),
            *fb.field(3),
            fb.scales[2],
            fb.offsets[2],
            self._d_range[0] + (1 if d_inv == self._d_range[0] else 0),
            self._d_range[1],
            self._d_range[0] if d_inv is None else d_inv,
            fb.scales[3],
            fb.offsets[3],
            self._f_range[0] + (1 if f_inv == self._f_range[0] else 0),
            self._f_range[1],
            self._f_range[0] if f_inv is None else f_inv,
            fb.length,
        )
        # the feedback frame, reused: _encode rewrites its payload in place
        self._fb_frame = Frame.blank(fb.frame_id + node, fb.length)
        self._estop_id = c.estop.frame_id + node
        self._hb_id = c.heartbeat.frame_id + node
        self._ids = (cmd.frame_id + node, self._estop_id, self._hb_id)
        self._share: SharedBus | None = None
        self._handlers: dict[int, CANTwin] = {}
        self._fb_data = self._fb_frame.data
        self._fb_frames = [self._fb_frame]
        self._bus: can.BusABC | None = None
        self._rxq = None

    def _setup(self) -> None:
        channel, bridge_channel, kwargs, options = self._open_line("CAN twin")
        try:
            share = shared_bus("twin", self.interface, channel, **kwargs)
        except InputError as exc:
            self._close_cable()
            raise InputError(f"CAN twin: {exc}") from None
        if any(i in share.handlers for i in self._ids):
            release_bus(share)
            self._close_cable()
            raise InputError(f"CAN twin: node {self.node} already served on {self.channel!r}")
        for i in self._ids:
            share.handlers[i] = self
        self._share = share
        self._handlers = share.handlers
        self._bus = share.bus
        conn: dict[str, Any] = {"interface": self.interface, "channel": bridge_channel}
        if self.node:
            conn["node"] = self.node
        if self.dbc is not None:
            conn["dbc"] = self.dbc
        self.connection = self._bridge_end(conn, options)
        self.where = (
            f"CAN interface {self.interface} channel {bridge_channel} node {self.node}"
            + self._line_note
        )
        self._rxq = share.rxq

    def _teardown(self) -> None:
        share, self._share = self._share, None
        self._bus = None
        self._rxq = None
        if share is not None:
            for i in self._ids:
                if share.handlers.get(i) is self:
                    del share.handlers[i]
            release_bus(share)
        self._close_cable()

    def _dispatch(self, msg: can.Message) -> None:
        """Handle ``msg`` in the endpoint of its identifier (this one when unknown)."""
        ep = self._handlers.get(msg.arbitration_id, self)
        if not ep._gone:
            ep._handle(msg)

    @property
    def supports_inline(self) -> bool:  # type: ignore[override]
        """Only python-can's in-process ``virtual`` bus delivers frames synchronously."""
        return self.interface == "virtual"

    def pump(self) -> int:
        """Serve every frame already on the bus (inline mode); return how many."""
        bus = self._bus
        n = 0
        if self._held is not None and self._paused():  # a delayed reply: a stalled controller
            return 0
        q = self._rxq
        if q is not None:  # python-can's virtual bus: its receive queue, no filters
            # the queue's deque: inline mode has no other reader, and a deque's popleft is
            # atomic against the sender's put (Queue.get_nowait would add two lock round trips)
            frames = q.queue
            while frames and self._held is None:
                self._dispatch(frames.popleft())
                n += 1
        else:
            while bus is not None and self._held is None:
                msg = self._recv(bus, 0.0)
                if msg is None:
                    break
                if msg is not _GARBLED:
                    self._dispatch(msg)
                n += 1
        self.controller.check_watchdog()
        return n

    def _recv(self, bus: can.BusABC, timeout: float):
        """One frame from ``bus``; :data:`_GARBLED` when the interface could not decode one.

        A second writer on the line (a pseudo-terminal or serial cable) can put bytes on it
        that python-can's decoder refuses (``ValueError`` "DLC may not exceed 8 bytes",
        ``CanError``): like a controller, the twin counts the frame as malformed and goes on.
        """
        try:
            return bus.recv(timeout)
        except (can.CanError, ValueError, IndexError, struct.error) as exc:
            self.controller.stats.malformed += 1
            log.warning("CAN twin %s: malformed frame on the line (%s); ignored", self.where, exc)
            return _GARBLED

    def _serve_once(self, timeout: float) -> None:
        bus = self._bus
        assert bus is not None
        msg = self._recv(bus, timeout)
        if msg is None or msg is _GARBLED:
            return
        self._dispatch(msg)

    def _handle(self, msg: can.Message) -> None:
        ctl = self.controller
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            ctl.stats.malformed += 1
            return
        fid = msg.arbitration_id
        (cid, clen, s_sh, s_m, d_sh, d_m, d_sign, d_wrap, c_sh, c_m, scale, offset) = (
            self._cmd_layout
        )
        if fid == cid:
            data = msg.data
            if len(data) != clen:
                ctl.stats.malformed += 1
                return
            v = int.from_bytes(data, "little")
            raw_d = (v >> d_sh) & d_m
            if raw_d & d_sign:
                raw_d -= d_wrap
            self.emit(
                ctl.command((v >> s_sh) & s_m, raw_d * scale + offset, bool((v >> c_sh) & c_m & 1))
            )
            return
        c = self.codecs
        if fid == self._estop_id:
            if len(msg.data) == 1 and msg.data[0] == c.estop_key:
                ctl.estop()
            else:
                ctl.stats.malformed += 1
        elif fid == self._hb_id:
            ctl.heartbeat()
        else:
            ctl.stats.malformed += 1

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        """The feedback frame (the reused one, payload rewritten; same bytes as
        ``feedback.pack(seq, status, _raw(displacement …), _raw(force …))``)."""
        (s_sh, s_m, st_sh, st_m, d_sh, d_m, f_sh, f_m) = self._fb_layout[:8]
        (d_scale, d_off, d_lo, d_hi, d_bad, f_scale, f_off, f_lo, f_hi, f_bad, n) = self._fb_layout[
            8:
        ]
        if displacement - displacement == 0.0:  # finite
            rd = round((displacement - d_off) / d_scale)
            rd = d_lo if rd < d_lo else (d_hi if rd > d_hi else rd)
        else:
            rd = d_bad
        if force - force == 0.0:
            rf = round((force - f_off) / f_scale)
            rf = f_lo if rf < f_lo else (f_hi if rf > f_hi else rf)
        else:
            rf = f_bad
        self._fb_data[:] = (
            ((seq & s_m) << s_sh)
            | ((status & st_m) << st_sh)
            | ((rd & d_m) << d_sh)
            | ((rf & f_m) << f_sh)
        ).to_bytes(n, "little")
        return self._fb_frames

    def _corrupt(self, frame: can.Message) -> can.Message:
        return Frame(
            arbitration_id=frame.arbitration_id, data=frame.data[:-1], is_extended_id=False
        )

    def _write(self, frame: can.Message) -> None:
        assert self._bus is not None
        try:
            self._bus.send(frame)
        except (can.CanError, OSError):  # pragma: no cover - bus gone
            pass


#: This endpoint in the twins' registry (the twin of the driver of this module's name,
#: :func:`rths_hil.sim_backends.registry.builtin_entry`).
TWIN = TwinEntry("rths_hil.sim_backends.endpoints.can:CANTwin", fresh_channel=True)

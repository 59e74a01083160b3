"""CAN driver: python-can bus, messages from the shipped DBC (``actuator.dbc``).

Per step the bridge sends one ``Command`` (ID 0x100: 16-bit ``Seq``, displacement, control
byte) and the controller answers with one ``Feedback`` frame (0x180: low byte of ``Seq``,
status, measured displacement, measured force), so that a 1024 Hz loop costs two frames per
step (≈ 260 µs of a 1 Mbit/s bus). ``EStop`` (0x010) has the lowest identifier of the set, so it
wins arbitration on a busy bus. ``Heartbeat`` (0x700) is optional. Layout and scaling are in
``docs/protocols.md`` and the DBC; :mod:`rths_hil.drivers.can.codec` compiles the DBC for the hot
path.

The bus is opened through python-can from configuration: ``interface`` (default
``"virtual"``, in-process only), ``channel``, ``bitrate`` and any extra python-can options in
``bus_options``. On Linux with SocketCAN use ``interface="socketcan", channel="vcan0"``
(or ``can0``); a USB–CAN adapter or a twin served as its own process on this machine
(``rths-hil twin serve --driver can --interface serial``) is reached through python-can's
``serial`` or ``slcan`` interface with the serial device as ``channel``.

**Several actuators on one bus.** Each controller is a CAN *node* ``n`` (``node``, 0–15): all
its message identifiers are the DBC's plus ``n`` (``Command`` 0x100 + n, ``Feedback``
0x180 + n, ``EStop`` 0x010 + n, ``Heartbeat`` 0x700 + n), so node 0 is the plain DBC and every
node's e-stop still outranks every command. The drivers of the nodes on one bus share one
python-can bus object (:func:`shared_bus`): a driver that reads another node's feedback off it
hands the frame to that node's inbox, so every frame is read once.

Every receive honours its timeout. Not every python-can interface does: ``serial`` (and other
interfaces built on a blocking read) wait their own read timeout (0.1 s) whatever ``recv`` is
given, which would make a paced loop's watchdog count wall-clock seconds as single steps. On
such interfaces the driver reads the bus through python-can's own :class:`can.Notifier`
thread into a :class:`can.BufferedReader`, whose queue honours the timeout to the
microsecond; interfaces known to honour it (:data:`TIMEOUT_HONOURED`) are read directly.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Mapping
from typing import Any, ClassVar

import can
from can.interfaces.virtual import VirtualBus

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..base import Driver, Feedback, LinkDown
from ..protocol import Protocol
from . import linkbudget, options
from .codec import ActuatorCodecs, Frame, load

__all__ = [
    "BUS_KEYS",
    "MAX_NODE",
    "PROTOCOL",
    "TIMEOUT_HONOURED",
    "CANDriver",
    "SharedBus",
    "SharedBusDriver",
    "check_node",
    "release_bus",
    "shared_bus",
    "virtual_rx_queue",
]

#: Highest CAN node number (identifier offset) of an actuator on a shared bus.
MAX_NODE = 15

#: The bus settings of every driver on a python-can bus (:class:`SharedBusDriver`):
#: ``driver.connection`` keys (:attr:`Driver.CONNECTION <rths_hil.drivers.base.Driver.CONNECTION>`).
BUS_KEYS: dict[str, Key] = {
    "interface": Key(
        "str",
        "virtual",
        doc="python-can interface (virtual: in-process only; socketcan, pcan, kvaser, serial, "
        "slcan …)",
    ),
    "channel": Key(
        "str|int", "rths-hil", doc="bus channel (vcan0, can0, a serial device, a virtual name)"
    ),
    "bitrate": Key(
        "int",
        None,
        unit="bit/s",
        lo=1,
        doc="bit rate, for interfaces that set it (none: the interface's)",
    ),
    "bus_options": Key("table", None, doc="further keyword arguments of python-can's can.Bus"),
}

#: python-can interfaces whose ``recv(timeout)`` returns within the timeout (read directly);
#: any other is read through a :class:`can.Notifier` thread (see the module docstring).
TIMEOUT_HONOURED = frozenset({"virtual", "socketcan"})

_BUS_ERRORS = (can.CanError, OSError, ValueError, ImportError, NotImplementedError)

log = logging.getLogger(__name__)
_perf = time.perf_counter


class _Reader(can.BufferedReader):
    """python-can's buffered reader that takes the notifier thread's error (the bus gone, e.g.
    the far end of a pseudo-terminal closed) instead of letting the thread die with a traceback.

    A handled error does not end python-can's notifier loop, which would retry the dead bus at
    once, forever: the reader stops its notifier (``stop(timeout=0)`` from its own thread joins
    nothing), and the driver reports the bus as disconnected through ``Notifier.exception``.
    """

    notifier: can.Notifier | None = None

    def on_error(self, exc: Exception) -> None:
        log.warning("CAN: reading the bus failed, no more frames: %s", exc)
        notifier, self.notifier = self.notifier, None
        if notifier is not None:
            notifier.stop(timeout=0.0)


def virtual_rx_queue(bus: can.BusABC | None) -> queue.Queue | None:
    """The receive queue of a python-can virtual bus without filters, else ``None``.

    ``VirtualBus.recv`` is ``BusABC.recv`` around a ``queue.Queue.get`` of this queue plus a
    filter check (none set) and a debug log line; reading the queue directly returns the same
    message objects, in the same order, ≈ 3 µs sooner per frame. Any other bus (SocketCAN,
    hardware, a virtual bus with filters or a subclass) is read through ``recv``.
    """
    if type(bus) is not VirtualBus or bus.filters is not None:
        return None
    q = getattr(bus, "queue", None)
    return q if isinstance(q, queue.Queue) else None


class SharedBus:
    """One python-can bus opened once per (side, interface, channel) and shared by its nodes.

    Attributes
    ----------
    bus : can.BusABC
    rxq : queue.Queue or None
        The virtual bus's receive queue (:func:`virtual_rx_queue`), else None.
    inboxes : dict
        Arbitration id → deque of frames read by another user of the bus (driver side).
    handlers : dict
        Arbitration id → endpoint that handles it (twin side).
    """

    def __init__(self, key: tuple, bus: can.BusABC) -> None:
        self.key = key
        self.bus = bus
        self.rxq = virtual_rx_queue(bus)
        self.refs = 0
        self.inboxes: dict[int, deque] = {}
        self.handlers: dict[int, Any] = {}
        self.reader: can.BufferedReader | None = None
        self.notifier: can.Notifier | None = None


_SHARED: dict[tuple, SharedBus] = {}
_SHARED_LOCK = threading.Lock()


def shared_bus(side: str, interface: str, channel: str, **kwargs: Any) -> SharedBus:
    """The bus of ``side`` (``"bridge"`` or ``"twin"``) on ``interface``/``channel``, opened once.

    Raises
    ------
    InputError
        The bus cannot be opened.
    """
    key = (side, str(interface), str(channel))
    with _SHARED_LOCK:
        share = _SHARED.get(key)
        if share is None:
            try:
                bus = can.Bus(interface=interface, channel=channel, **kwargs)
            except _BUS_ERRORS as exc:
                raise InputError(
                    f"CAN: cannot open interface {interface!r} channel {channel!r}: {exc}"
                ) from None
            share = _SHARED[key] = SharedBus(key, bus)
            if side == "bridge" and str(interface) not in TIMEOUT_HONOURED:
                share.reader = reader = _Reader()
                share.notifier = reader.notifier = can.Notifier(bus, [reader], timeout=0.01)
        share.refs += 1
        return share


def release_bus(share: SharedBus) -> None:
    """Drop one user of ``share``; the last one shuts the bus down."""
    with _SHARED_LOCK:
        share.refs -= 1
        if share.refs > 0:
            return
        _SHARED.pop(share.key, None)
    notifier, share.notifier = share.notifier, None
    if notifier is not None:
        try:
            notifier.stop(timeout=1.0)
        except _BUS_ERRORS:  # pragma: no cover - already gone
            pass
    try:
        share.bus.shutdown()
    except _BUS_ERRORS:  # pragma: no cover - already gone
        pass


def check_node(node: int) -> int:
    """``node`` checked: a CAN node number 0..:data:`MAX_NODE` (else :class:`InputError`)."""
    if isinstance(node, bool) or not isinstance(node, int) or not 0 <= node <= MAX_NODE:
        raise InputError(f"CAN: node must be an integer 0..{MAX_NODE}, got {node!r}")
    return node


class SharedBusDriver(Driver):
    """A driver that is one node on a python-can bus shared per interface and channel
    (:func:`shared_bus`, bridge side): its bus settings, opening and closing its share, sending
    a frame and reading its feedback (frames for another node go to that node's inbox; see the
    module docstring for the receive paths).

    A subclass calls :meth:`_init_bus` from its ``__init__`` and defines :meth:`_parse` (a
    frame read off the bus → its feedback, or ``None``, counted) and :meth:`_holder` (who holds
    the feedback identifier, for the refusal of a second driver on it).

    Every read waits with the deadline as its timeout (the virtual bus's queue, python-can's
    reader, ``bus.recv``), and the nodes share the bus: a late receive is counted, never moved
    to a reader thread (:attr:`~rths_hil.drivers.base.Driver.reader_fallback`).
    """

    reader_fallback: ClassVar[bool] = False

    def _init_bus(
        self,
        interface: str,
        channel: str,
        bitrate: int | None,
        bus_options: dict[str, Any] | None,
        feedback_id: int,
    ) -> None:
        """The bus settings and the node's feedback identifier (``_fb_id``); not yet open."""
        self.interface, self.channel = str(interface), str(channel)
        self.bitrate = None if bitrate is None else int(bitrate)
        self.bus_options = dict(bus_options or {})
        self._fb_id = feedback_id
        self._bus: can.BusABC | None = None
        self._rxq: queue.Queue | None = None
        self._share: SharedBus | None = None
        self._box: deque = deque()  # frames for this node read off the bus by another node
        self._routes: dict[int, deque] = {}
        self._reader: can.BufferedReader | None = None

    def _parse(self, msg: can.Message) -> Feedback | None:
        """The feedback in ``msg``, or ``None`` (counted; another node's frame to its inbox)."""
        raise NotImplementedError

    def _holder(self) -> str:
        """Who the feedback identifier belongs to, as the refusal of a second driver says."""
        raise NotImplementedError

    def open(self) -> None:
        if self._bus is not None:
            return
        kwargs = dict(self.bus_options)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            share = shared_bus("bridge", self.interface, self.channel, **kwargs)
        except InputError as exc:
            raise InputError(f"CAN driver: {exc}") from None
        if self._fb_id in share.inboxes:
            release_bus(share)
            raise InputError(
                f"CAN driver: {self._holder()} is already open on channel {self.channel!r}"
            )
        self._share = share
        self._box = share.inboxes[self._fb_id] = deque()
        self._routes = share.inboxes
        self._bus, self._rxq, self._reader = share.bus, share.rxq, share.reader

    def close(self) -> None:
        share, self._share = self._share, None
        self._bus = self._rxq = self._reader = None
        if share is not None:
            share.inboxes.pop(self._fb_id, None)
            release_bus(share)

    def _send_frame(self, msg: can.Message) -> None:
        if self._bus is None:
            self.stats.send_errors += 1
            return
        try:
            self._bus.send(msg)
        except (can.CanError, OSError):
            self.stats.send_errors += 1

    def _recv_internal(self, deadline: float) -> Feedback | None:
        box = self._box
        if box:  # read off the shared bus by another node's driver
            return self._parse(box.popleft())
        q = self._rxq
        if q is not None:  # virtual bus: its queue directly (see virtual_rx_queue)
            frames = q.queue
            if frames:  # already there: take it without the queue's lock round trips
                msg = frames.popleft()
            else:
                remaining = deadline - _perf()
                if remaining <= 0.0:
                    return None
                try:
                    msg = q.get(True, remaining)
                except queue.Empty:
                    return None
            return self._parse(msg)
        bus = self._bus
        if bus is None:
            raise LinkDown("CAN bus closed")
        remaining = deadline - _perf()
        reader = self._reader
        if reader is not None:  # an interface that ignores the timeout: its reader
            msg = reader.get_message(remaining if remaining > 0.0 else 0.0)
            if msg is None:
                share = self._share
                if share is not None and share.notifier and share.notifier.exception:
                    self.stats.disconnects += 1
                    raise LinkDown("CAN bus reader stopped")
                return None
            return self._parse(msg)
        try:
            msg = bus.recv(remaining if remaining > 0.0 else 0.0)
        except (can.CanError, OSError):
            self.stats.disconnects += 1
            raise LinkDown("CAN bus read failed") from None
        return None if msg is None else self._parse(msg)


class CANDriver(SharedBusDriver):
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
    node : int
        CAN node of the controller (0–15): every identifier is offset by it (module docstring).
    """

    name: ClassVar[str] = "can"
    honours_deadline: ClassVar[bool] = True  # the virtual queue / SocketCAN / the Notifier
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        **BUS_KEYS,
        "dbc": Key(
            "str",
            None,
            doc="a DBC replacing the shipped one (same message and signal "
            "names; relative to the configuration file)",
        ),
        "node": Key(
            "int",
            0,
            lo=0,
            hi=MAX_NODE,
            doc="CAN node of the controller: every identifier is offset by it",
        ),
    }

    def __init__(
        self,
        interface: str = "virtual",
        channel: str = "rths-hil",
        bitrate: int | None = None,
        dbc: str | None = None,
        bus_options: dict[str, Any] | None = None,
        node: int = 0,
    ) -> None:
        super().__init__()
        self.node = int(node)
        self.codecs: ActuatorCodecs = load(dbc)
        cmd, fb = self.codecs.command, self.codecs.feedback
        # Command: Seq, Displacement, Control — shifts and masks precompiled from the DBC.
        self._c_seq_bits = cmd.lengths[0]
        self._c_seq_mask = (1 << cmd.lengths[0]) - 1
        self._c_d_shift, self._c_d_mask = cmd.field(1)
        self._c_ctl_shift = cmd.starts[2]
        self._c_scale, self._c_offset = cmd.scales[1], cmd.offsets[1]
        self._c_lo, self._c_hi = cmd.raw_range(1)
        self._c_len = cmd.length
        self._init_bus(interface, channel, bitrate, bus_options, fb.frame_id + node)
        self._f_len = fb.length
        # Feedback: Seq, Status, Displacement, Force — bit positions, masks, sign bits, scales
        # and INVALID values as one tuple: _handle unpacks it once per frame.
        self._f_layout = (
            *fb.field(0),
            *fb.field(1),
            *fb.field(2),
            fb.sign_bit(2),
            *fb.field(3),
            fb.sign_bit(3),
            fb.scales[2],
            fb.offsets[2],
            fb.scales[3],
            fb.offsets[3],
            fb.invalid[2],
            fb.invalid[3],
        )
        # one command frame, reused: its payload is rewritten in place by send()
        self._cmd_msg = Frame.blank(cmd.frame_id + node, cmd.length)
        self._cmd_data = self._cmd_msg.data
        self._estop_id = self.codecs.estop.frame_id + node
        self._hb_id = self.codecs.heartbeat.frame_id + node
        self._hb = 0

    def _holder(self) -> str:
        return f"node {self.node}"

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
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
        self._cmd_data[:] = value.to_bytes(self._c_len, "little")
        self._send_frame(self._cmd_msg)

    def estop(self) -> None:
        c = self.codecs.estop
        self.stats.estops += 1
        data = c.pack(self.codecs.estop_key)
        self._send_frame(Frame(arbitration_id=self._estop_id, data=data, is_extended_id=False))

    def heartbeat(self) -> None:
        c = self.codecs.heartbeat
        self._hb = (self._hb + 1) & 0xFF
        self._send_frame(
            Frame(arbitration_id=self._hb_id, data=c.pack(self._hb), is_extended_id=False)
        )

    def _handle(self, msg: can.Message) -> Feedback | None:
        """Decode ``msg`` and apply the sequence rules and counters (as :meth:`receive`)."""
        return self._accept(self._parse(msg))

    def _parse(self, msg: can.Message) -> Feedback | None:
        """The feedback in ``msg`` (sequence number extended), or None (counted)."""
        stats = self.stats
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            stats.count_malformed("bad_frame")
            return None
        if msg.arbitration_id != self._fb_id:
            other = self._routes.get(msg.arbitration_id)
            if other is not None:  # another node's feedback on the shared bus
                other.append(msg)
                return None
            stats.count_malformed("unknown_id")
            return None
        data = msg.data
        if len(data) != self._f_len:
            stats.count_malformed("bad_length")
            return None
        (s_sh, s_m, st_sh, st_m, d_sh, d_m, d_sign, f_sh, f_m, f_sign, d_sc, d_off, f_sc, f_off,
         d_bad, f_bad) = self._f_layout  # fmt: skip
        v = int.from_bytes(data, "little")
        last = self._last_sent  # extend_seq, inline: the echo at or just below the last sent
        seq = last - ((last - ((v >> s_sh) & s_m)) & s_m)
        rd = (v >> d_sh) & d_m
        if rd & d_sign:
            rd -= d_sign << 1
        rf = (v >> f_sh) & f_m
        if rf & f_sign:
            rf -= f_sign << 1
        disp = math.nan if rd == d_bad else rd * d_sc + d_off
        force = math.nan if rf == f_bad else rf * f_sc + f_off
        return Feedback(seq, disp, force, (v >> st_sh) & st_m)


def _profile_driver() -> type[Driver]:
    """A lab's own DBC: :class:`~.profile.CANProfileDriver`."""
    from .profile import CANProfileDriver

    return CANProfileDriver


#: The CAN protocol's planning facts (:mod:`rths_hil.drivers.protocol`): the hooks of its link
#: model (:mod:`.linkbudget`) and what else differs from the defaults.
PROTOCOL = Protocol.from_hooks(
    "can",
    CANDriver,
    linkbudget,
    profile_protocol="can",
    profile_driver=_profile_driver,
    path_keys=("dbc",),
    serve_options=options.serve_options,
)

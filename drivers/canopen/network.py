"""The shared CANopen bus: one python-can bus and its :class:`canopen.Network` per interface and
channel, shared by every axis on it; the SYNC producer (one SYNC per step for all axes), the
bridge's heartbeat and the reading of frames (TPDOs to their axis, the rest to the library).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from typing import TYPE_CHECKING, Any, ClassVar

import can
import canopen

from rths_hil.errors import InputError

from ..can import TIMEOUT_HONOURED, virtual_rx_queue
from ..can.codec import Frame
from .od import (
    _BUS_ERRORS,
    SYNC_ID,
)

if TYPE_CHECKING:
    from .driver import CANopenDriver

log = logging.getLogger(__package__)


class _BusGone(can.Listener):
    """Takes the error that ends the library's notifier thread (python-can hands it to every
    listener with ``on_error``; without one the thread dies with a traceback): the bus is
    gone, said once in the log and counted as a disconnect of every axis on it."""

    def __init__(self, bus: CANopenBus) -> None:
        self.bus = bus

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        bus = self.bus
        if bus.gone is None:
            bus.gone = exc
            log.error("canopen: bus %s %s: the reader stopped: %s", *bus.key, exc)
            for drv in list(bus.axes.values()):
                drv.stats.disconnects += 1


class CANopenBus:
    """One CANopen bus of the bridge: a python-can bus and its :class:`canopen.Network`,
    shared by every axis (driver) on the same interface and channel.

    The bus is the SYNC producer: :meth:`sync` sends one SYNC for the RPDOs every axis has
    written since the last one, so several axes on one bus share one SYNC per step (each axis
    its own node id, RPDO and TPDOs). Frames are read once (:meth:`pump`, :meth:`drain`): a
    TPDO goes into the PDO map of the axis that mapped it, anything else to the library's
    dispatch (``Network.notify``: EMCY, heartbeats, SDO). The bridge's heartbeat is one per bus.
    The library's notifier thread runs only while an axis is in an SDO phase (open, arming,
    close) on buses read from the caller's thread (:data:`~..can.TIMEOUT_HONOURED`); on others
    it always runs.
    """

    _open: ClassVar[dict[tuple[str, str], CANopenBus]] = {}
    _registry_lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, key: tuple[str, str], network: canopen.Network, direct: bool) -> None:
        self.key = key
        self.network = network
        self.direct = direct
        self.rxq: queue.Queue | None = virtual_rx_queue(network.bus) if direct else None
        self.axes: dict[int, CANopenDriver] = {}
        #: TPDO COB-ID → (axis, the library's PDO map, slot, size, precompiled unpack)
        self.tpdo: dict[int, tuple[CANopenDriver, Any, int, int, Any]] = {}
        #: frames are read from the caller's thread (no notifier thread runs), see :meth:`listen`
        self.reading = direct
        self.sync_msg = Frame.blank(SYNC_ID, 0)
        #: SYNC frames sent on this bus
        self.syncs = 0
        self._listening = 0
        self._hb_last = -math.inf
        #: the error that stopped the library's notifier thread (the bus gone: a serial line
        #: closed, an adapter unplugged), taken by :class:`_BusGone`; None while it reads
        self.gone: BaseException | None = None
        # every notifier started on the network (python-can takes any can.Listener)
        network.listeners.append(_BusGone(self))  # type: ignore[arg-type]
        #: after an e-stop: the library's periodic heartbeat task (:meth:`hold_heartbeat`)
        self._hb_task: Any = None

    @classmethod
    def join(cls, drv: CANopenDriver) -> CANopenBus:
        """The bus of ``drv``'s interface and channel, opened by the first axis on it."""
        key = (drv.interface, drv.channel)
        with cls._registry_lock:
            bus = cls._open.get(key)
            if bus is None:
                net = canopen.Network()
                net.NOTIFIER_CYCLE = 0.05  # how long close() may wait for the notifier thread
                kwargs = dict(drv.bus_options)
                if drv.bitrate is not None:
                    kwargs["bitrate"] = drv.bitrate
                try:
                    net.connect(interface=drv.interface, channel=drv.channel, **kwargs)
                except _BUS_ERRORS as exc:
                    raise InputError(
                        f"canopen: cannot open interface {drv.interface!r} channel "
                        f"{drv.channel!r}: {exc}"
                    ) from None
                bus = cls(key, net, drv.interface in TIMEOUT_HONOURED)
                if bus.direct and net.notifier is not None:  # read from the caller's thread
                    notifier, net.notifier = net.notifier, None
                    notifier.stop(1.0)
                elif net.notifier is not None:  # started by connect(), before the listener
                    net.notifier.add_listener(net.listeners[-1])
                bus.reading = bus.direct and net.notifier is None
                cls._open[key] = bus
            elif drv.node_id in bus.axes:
                raise InputError(
                    f"canopen: node {drv.node_id} is already open on {drv.interface} "
                    f"{drv.channel} (each axis on a bus needs its own node_id)"
                )
            bus.axes[drv.node_id] = drv
        return bus

    def release(self, drv: CANopenDriver) -> None:
        """``drv`` leaves the bus; the last axis closes it."""
        with self._registry_lock:
            if self.axes.get(drv.node_id) is drv:
                del self.axes[drv.node_id]
            for cob in [c for c, t in self.tpdo.items() if t[0] is drv]:
                del self.tpdo[cob]
            if self.axes:
                return
            if self._open.get(self.key) is self:
                del self._open[self.key]
        self.release_heartbeat()
        self.rxq = None
        try:
            self.network.disconnect()
        except (*_BUS_ERRORS, RuntimeError):  # pragma: no cover - already gone
            pass

    def listen(self, on: bool) -> None:
        """Run the library's notifier thread (an SDO phase of an axis) or stop it when no axis
        needs it any more (frames are then read from the caller's thread)."""
        net = self.network
        if not self.direct or net.bus is None:
            return
        self._listening = max(0, self._listening + (1 if on else -1))
        if self._listening and net.notifier is None:
            self.reading = False
            net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        elif not self._listening and net.notifier is not None:
            notifier, net.notifier = net.notifier, None
            notifier.stop(1.0)
            self.reading = True

    def pump(self, timeout: float) -> bool:
        """Read one frame (waiting up to ``timeout``) and hand it on (:meth:`handle`); False if
        none came."""
        q = self.rxq
        if q is not None:  # python-can's virtual bus: its receive queue (rths_hil.drivers.can)
            frames = q.queue
            if frames:
                msg = frames.popleft()
            elif timeout <= 0:
                return False
            else:
                try:
                    msg = q.get(True, timeout)
                except queue.Empty:
                    return False
        else:
            bus = self.network.bus
            if bus is None:
                return False
            try:
                msg = bus.recv(timeout)
            except (can.CanError, OSError):
                for drv in list(self.axes.values()):
                    drv.stats.disconnects += 1
                return False
            if msg is None:
                return False
        self.handle(msg)
        return True

    def drain(self) -> None:
        """Hand on every frame already received, without waiting."""
        q = self.rxq
        if q is not None:
            frames = q.queue
            handle = self.handle
            while frames:
                handle(frames.popleft())
        else:
            while self.pump(0.0):
                pass

    def handle(self, msg: can.Message) -> None:
        """One frame: a TPDO into the PDO map of its axis (as ``PdoMap.on_message`` does) and
        its values, unpacked by the axis's precompiled layout, to the axis (``_tpdo_in``);
        anything else to the library's dispatch (EMCY, heartbeats, SDO)."""
        if msg.is_error_frame or msg.is_remote_frame:
            for drv in self.axes.values():
                drv.stats.count_malformed("bad_frame")
                break
            return
        owner = self.tpdo.get(msg.arbitration_id)
        if owner is not None:
            drv, m, slot, size, unpack = owner
            data = m.data = msg.data
            m.timestamp = msg.timestamp
            drv._tpdo_in(slot, unpack(data) if len(data) == size else None)
            return
        try:
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)
        except Exception as exc:  # a callback's error must not end the run (as MessageListener)
            log.error("canopen: frame 0x%03X: %s", msg.arbitration_id, exc)

    def send(self, msg: can.Message) -> bool:
        """Write one frame; False (nothing raised) when the bus is gone."""
        net = self.network
        bus = net.bus
        if bus is None:
            return False
        try:
            with net.send_lock:
                bus.send(msg)
        except (can.CanError, OSError):
            return False
        return True

    def sync(self) -> bool:
        """Send one SYNC: every axis whose RPDO waits for it takes it as its step's clock.

        The axes take the new step before the SYNC leaves: read by a notifier thread, a
        device's answer can arrive before this thread runs again, and must not be filed under
        the step before (where it would count as a duplicate and the step go unanswered)."""
        for drv in self.axes.values():
            if drv._awaiting is not None:
                drv._synced()
        if not self.send(self.sync_msg):
            return False
        self.syncs += 1
        return True

    def hold_heartbeat(self, msg: can.Message, period: float) -> None:
        """After an e-stop: the bridge's heartbeat every ``period`` from the library's periodic
        task (``Network.send_periodic``, python-can's cyclic send) until the bus closes or an
        axis is armed again (:meth:`release_heartbeat`).

        While the loop runs the heartbeat goes with its steps, so a device's consumer (0x1016)
        also notices a hung loop. After an e-stop the loop no longer steps, but the bridge is
        alive and keeps every node operational and latched until it closes them one after the
        other (each close: NMT stop); without a producer a device closed last would see its
        consumer time run out and add a heartbeat fault (EMCY 0x8130) the bridge did not have.
        """
        if self._hb_task is not None or period <= 0.0 or self.network.bus is None:
            return
        if self.gone is not None:  # nothing to keep alive (its thread would fail on the line)
            return
        try:
            self._hb_task = self.network.send_periodic(msg.arbitration_id, bytes(msg.data), period)
        except (*_BUS_ERRORS, RuntimeError) as exc:  # pragma: no cover - bus gone
            log.warning("canopen: cannot keep the bridge's heartbeat after the e-stop: %s", exc)

    def release_heartbeat(self) -> None:
        """Stop the heartbeat of :meth:`hold_heartbeat` (the loop's steps produce it again)."""
        task, self._hb_task = self._hb_task, None
        if task is not None:
            try:
                task.stop()
            except (*_BUS_ERRORS, RuntimeError):  # pragma: no cover - bus gone
                pass

    def heartbeat(self, msg: can.Message) -> bool:
        """The bridge's heartbeat: one per bus (a second axis asking within 1 ms is served by
        the same frame)."""
        now = time.monotonic()
        if now - self._hb_last < 1e-3:
            return True
        self._hb_last = now
        return self.send(msg)

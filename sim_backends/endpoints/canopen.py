"""CANopen twin endpoint: a CiA 402 servo drive or CiA 408 hydraulic axis, a ``canopen`` LocalNode.

The node's object dictionary is one of the EDS files shipped in ``sim_backends/eds``
(``cia402_twin.eds``, ``cia408_twin.eds``) or a lab's own. The ``canopen`` library serves SDO
(:class:`canopen.sdo.SdoServer`: the driver reads 0x1000/0x1018 and maps the PDOs by SDO into
the node's data store), NMT (:class:`canopen.nmt.NmtSlave`, which also produces the heartbeat
set in 0x1017), EMCY (:class:`canopen.emcy.EmcyProducer`) and the PDO maps; this module adds
what a device does with them:

* NMT start (pre-operational → operational): the PDO maps are read from the node's own object
  dictionary (what the driver wrote), the plant is put back at rest (a new run) and the SYNC
  count restarts at 0.
* RPDO1 (control word + set-point) is stored; on each SYNC the control word is applied to the
  device FSA (402: the transitions of CiA 402 incl. quick stop and fault reset; 408: D/H/M and
  the reset edge), then — in OPERATION ENABLED with mode 8 (402) or ACTIVE with device mode 1
  (408) — the plant is stepped once towards the set-point (:class:`TwinController`, step ``n`` =
  the SYNC count), else it holds; TPDO1 (status word + actual position) and TPDO2 (force) are
  sent. Frame faults (drop, delay, corrupt = one byte short, duplicate) apply to the TPDOs.
* Controller-side watchdog = heartbeat consumer (0x1016: the bridge's heartbeat, or
  ``heartbeat_timeout`` from the twin's configuration): while operating, a heartbeat of node
  ``bridge_node_id`` must come within the consumer time; when none does the twin holds, enters
  FAULT (402) / FAULT HOLD (408) and sends EMCY 0x8130 (heartbeat error), also kept in the
  pre-defined error field 0x1003 where the EDS has it; only a fault reset (arming) leaves it.
  A runaway fault (``runaway_from``) does the same with EMCY 0x8611 (following error).
* SDO reads of the status word, actual position, force, following error 0x60F4 and mode display
  0x6061 are answered from the device's live state.
* Modes of operation (402): the twin runs the mode of its plant — cyclic synchronous position
  (0x6060 = 8, the target position 0x607A in the RPDO) for a displacement plant, cyclic
  synchronous torque (0x6060 = 10, the target torque 0x6071 in the RPDO, per mille of the
  motor rated torque 0x6076, × ``force_per_torque`` = N) for a force-controlled one
  (``plant.control == "force"``, whose step takes the set-point in N unchanged); the
  supported drive modes 0x6502 answer that mode's bit (7 or 9) and a write of another mode
  to 0x6060 is aborted (SDO abort 0x06090030, value range exceeded). The torque actual 0x6077
  is the measured force in per mille of the rated torque. A CiA 408 twin with a
  force-controlled plant is refused (the driver speaks no 408 force control).
"""

from __future__ import annotations

import logging
import math
import os
import queue
import random
import struct
import threading
import time
from collections.abc import Mapping
from importlib import resources
from typing import Any, ClassVar

import can
import canopen
from canopen.objectdictionary import ObjectDictionaryError
from canopen.sdo import SdoAbortedError
from rths_hil.drivers.base import INVALID_S32, Status
from rths_hil.drivers.can import virtual_rx_queue
from rths_hil.drivers.can.codec import Frame
from rths_hil.drivers.canopen import BRIDGE_NODE_ID, Layout, load_od, parse_object
from rths_hil.drivers.canopen.device import CONNECTION_KEYS
from rths_hil.drivers.canopen.profiles import PROFILES, SW408

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..registry import TwinEntry
from .base import TwinController, TwinEndpoint
from .nullmodem import CANLine, can_line_from_args

__all__ = ["EMCY_FOLLOWING_ERROR", "EMCY_HEARTBEAT", "CANopenTwin", "default_eds"]

log = logging.getLogger(__name__)

#: EMCY error codes the twin sends (CiA 301 / CiA 402).
EMCY_HEARTBEAT = 0x8130
EMCY_FOLLOWING_ERROR = 0x8611
_S32 = (-(2**31) + 1, 2**31 - 1)
_S16 = (-(2**15) + 1, 2**15 - 1)
#: SDO abort code: value range of parameter exceeded (CiA 301)
SDO_VALUE_RANGE = 0x06090030
#: CiA 402 modes of operation and their bit in the supported drive modes 0x6502
MODE_CSP, MODE_CST = 8, 10
_MODE_BIT = {MODE_CSP: 7, MODE_CST: 9}
# CiA 402 status words of the states (State402.SW_MASK values, + voltage enabled / remote)
_SW402 = {
    "NOT READY TO SWITCH ON": 0x0000,
    "SWITCH ON DISABLED": 0x0240,
    "READY TO SWITCH ON": 0x0231,
    "SWITCHED ON": 0x0233,
    "OPERATION ENABLED": 0x0237,
    "QUICK STOP ACTIVE": 0x0217,
    "FAULT REACTION ACTIVE": 0x020F,
    "FAULT": 0x0208,
}


def default_eds(profile: str) -> str:
    """Path of the shipped EDS of the twin of ``profile`` (``cia402`` or ``cia408``)."""
    return str(resources.files("rths_hil.sim_backends") / "eds" / f"{profile}_twin.eds")


class CANopenTwin(CANLine, TwinEndpoint):
    """A CANopen device (CiA 402 or 408) around a :class:`TwinController` (module docstring).

    Parameters
    ----------
    controller : TwinController
    interface, channel, bitrate, bus_options
        The python-can bus (``virtual`` by default).
    eds : str, optional
        EDS of the node (default: the shipped one of ``device_profile``).
    node_id, device_profile, counts_per_m, force_object, newtons_per_count, bridge_node_id
        As the driver's keys (:mod:`rths_hil.drivers.canopen`).
    **driver_keys
        Other driver settings, handed on in :attr:`connection`.
    """

    name = "canopen"
    #: The driver's keys (the twin hands on those it does not use), with the twin's defaults.
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        **CONNECTION_KEYS,
        "eds": Key("str", None, doc="twin: EDS of the node (none: the shipped one of the profile)"),
        "force_object": Key(
            "str|int", "0x2100", doc='twin: object of the measured force ("": none)'
        ),
        "newtons_per_count": Key(
            "float", 0.01, unit="N/count", lo=0, lo_open=True, doc="twin: scale of the force object"
        ),
    }
    #: inline: the endpoint's thread serves again when no pump came for this long (s); while
    #: standing by it wakes once per ``handover`` (fewer hand-offs of the interpreter lock
    #: inside the loop's steps), so it takes over within two
    handover = 0.05

    @classmethod
    def connection_from_args(cls, args: Any) -> dict[str, Any]:
        """``--interface`` (not ``virtual``: it cannot leave the process), ``--channel`` and
        ``--bitrate`` (:func:`~.nullmodem.can_line_from_args`); the shipped CiA 402 EDS,
        node 1."""
        return can_line_from_args(args, "canopen twin")

    def __init__(
        self,
        controller: TwinController,
        interface: str = "virtual",
        channel: str = "rths-canopen",
        bitrate: int | None = None,
        bus_options: dict[str, Any] | None = None,
        eds: str | None = None,
        node_id: int = 1,
        device_profile: str = "cia402",
        counts_per_m: float = 1e7,
        force_object: str = "0x2100",
        newtons_per_count: float = 0.01,
        bridge_node_id: int = BRIDGE_NODE_ID,
        force_per_torque: float = 1.0,
        **driver_keys: Any,
    ) -> None:
        super().__init__(controller)
        if device_profile not in PROFILES:
            raise InputError(
                f"canopen: device_profile {device_profile!r} is not known (known: "
                f"{', '.join(PROFILES)})"
            )
        self.profile = PROFILES[device_profile]
        prof = self.profile.for_control(self.control)
        if prof is None:
            raise InputError(
                f"canopen twin: device_profile {device_profile!r} has no force control the "
                "driver speaks: a force-controlled plant needs cia402 (cyclic synchronous "
                "torque)"
            )
        #: the set-point object of the RPDO and the mode of operation the twin runs (402)
        self._sp_obj = prof.setpoint
        self._run_mode = prof.mode[2] if prof.mode is not None else 0
        if (
            isinstance(force_per_torque, bool)
            or not isinstance(force_per_torque, int | float)
            or not (math.isfinite(force_per_torque) and force_per_torque > 0)
        ):
            raise InputError(
                f"canopen: force_per_torque must be a positive number, got {force_per_torque!r}"
            )
        self.force_per_torque = float(force_per_torque)
        self.interface, self.channel, self.bitrate = str(interface), str(channel), bitrate
        self.bus_options = dict(bus_options or {})
        self.eds = os.fspath(eds) if eds else default_eds(device_profile)
        for key, v in (("node_id", node_id), ("bridge_node_id", bridge_node_id)):
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 127:
                raise InputError(f"canopen: {key} must be an integer 1..127, got {v!r}")
        self.node_id = int(node_id)
        self.od = load_od(self.eds, self.node_id)
        self.counts_per_m = float(counts_per_m)
        self.newtons_per_count = float(newtons_per_count)
        self.force_object = (
            parse_object(force_object, "force_object") if str(force_object).strip() else None
        )
        self.bridge_node_id = int(bridge_node_id)
        self.driver_keys = dict(driver_keys)
        self.connection_keys = {
            "interface": self.interface, "channel": self.channel, "eds": self.eds,
            "node_id": self.node_id, "device_profile": device_profile, "counts_per_m": counts_per_m,
            "force_object": force_object, "newtons_per_count": newtons_per_count,
            "bridge_node_id": self.bridge_node_id, **self.driver_keys,
        }  # fmt: skip
        if force_per_torque != 1.0:
            self.connection_keys["force_per_torque"] = force_per_torque
        if self.control == "force" and 0x6076 not in self.od:
            raise InputError(
                f"canopen twin: eds {self.eds!r} has no object 0x6076 (motor rated torque) to "
                "scale the target torque 0x6071 of a force-controlled plant"
            )
        if bitrate is not None:
            self.connection_keys["bitrate"] = bitrate
        if self.bus_options:
            self.connection_keys["bus_options"] = dict(self.bus_options)
        self.bus: can.BusABC | None = None
        self.network: canopen.Network | None = None
        self.node: canopen.LocalNode | None = None
        self.state = "SWITCH ON DISABLED" if self.profile.number == 402 else "INIT"
        #: every FSA state entered, in order (for tests and logs)
        self.history: list[str] = [self.state]
        self.mode = 0
        self.n = 0
        self.target = 0
        self._cw = 0
        self._rpdo: Any = None
        self._tpdo: list[Any] = []
        self._rx: dict[tuple[int, int], Any] = {}  # the RPDO's PDO variables by object
        # the maps packed and unpacked by precompiled structs checked against the library's
        # encoding (Layout.check) when the node starts; None: through the library's variables
        self._fast: tuple[Any, ...] | None = None
        self._rxq: queue.Queue | None = None
        self._nmt_state = ""
        self._hb_watch = False
        #: inline: frames are handled under this lock, by the thread or the bridge's pump
        self._serving = threading.Lock()
        self._pumped_at = -math.inf
        self._newtons = math.nan  # N per count of 0x6071/0x6077 (0x6076), read at NMT start

    # -- transport ------------------------------------------------------------------------------
    def _setup(self) -> None:
        channel, bridge_channel, kwargs, options = self._open_line("canopen twin")
        try:
            self.bus = can.Bus(interface=self.interface, channel=channel, **kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            self._close_cable()
            raise InputError(
                f"canopen twin: cannot open {self.interface!r} {self.channel!r}: {exc}"
            ) from None
        self._rxq = virtual_rx_queue(self.bus)
        net = self.network = canopen.Network(self.bus)
        node = self.node = canopen.LocalNode(self.node_id, self.od)
        net.add_node(node)
        node.add_write_callback(self._on_write)
        node.add_read_callback(self._on_read)
        net.subscribe(0, self._on_nmt)
        net.subscribe(0x80, self._on_sync)
        net.subscribe(0x700 + self.bridge_node_id, self._on_bridge_heartbeat)
        node.nmt.state = "PRE-OPERATIONAL"
        self._nmt_state = node.nmt.state
        self.connection = self._bridge_end(
            {**self.connection_keys, "channel": bridge_channel}, options
        )
        self.where = (
            f"CANopen {self.profile.name} node {self.node_id} on {self.interface} {bridge_channel}"
            + self._line_note
        )

    def _teardown(self) -> None:
        node, self.node = self.node, None
        if node is not None:
            node.nmt.stop_heartbeat()
        bus, self.bus = self.bus, None
        self._rxq = None
        self.network = None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError):  # pragma: no cover
                pass
        self._close_cable()

    # -- serving: from the endpoint's thread, or inline from the bridge's ---------------------
    @property
    def supports_inline(self) -> bool:  # type: ignore[override]
        """Only python-can's in-process ``virtual`` bus delivers frames synchronously."""
        return self.interface == "virtual"

    def start(self, threaded: bool = True) -> CANopenTwin:
        """Open the bus and serve it (:meth:`TwinEndpoint.start`).

        Inline (``threaded=False``, the ``virtual`` bus) the endpoint's thread runs all the
        same: the driver's SDO exchanges (start-up, arming, the disable sequence at close) wait
        for answers while the loop does not step. The thread stands by while the bridge's
        thread serves the steps (:meth:`pump`) and serves again once no pump came for
        :attr:`handover` seconds — an SDO phase, or a bridge that stalled or stopped (the
        heartbeat consumer then trips as on a thread).
        """
        if threaded or not self.supports_inline:
            return super().start(threaded)  # type: ignore[return-value]
        super().start(True)
        self.inline = True
        return self

    def pump(self) -> int:
        """Serve every frame already on the bus from the caller's thread (inline mode); the
        endpoint's thread stands by for :attr:`handover` seconds. Return how many."""
        self._pumped_at = time.monotonic()
        return self._drain()

    def _drain(self) -> int:
        """Handle every frame waiting in the virtual bus's queue, in order; 0 while a delayed
        reply is held (a stalled controller). Under :attr:`_serving`: the thread and the
        bridge's thread never handle frames at the same time, and only take them under it."""
        q = self._rxq
        if q is None:
            return 0
        frames = q.queue  # the queue's deque: taken only under the lock, so in order
        n = 0
        with self._serving:
            if self._paused():
                return 0
            while frames and self._held is None:
                self._handle(frames.popleft())
                n += 1
        return n

    def _serve_once(self, timeout: float) -> None:
        if self.inline:
            held = self._held
            if time.monotonic() - self._pumped_at < self.handover:
                # the bridge's thread serves the steps: stand by, the consumer still watched
                self._stop.wait(self.handover)
                with self._serving:
                    self._check_faults()
                return
            q = self._rxq
            assert q is not None
            if held is not None:  # a delayed reply: until its time, the controller stalls
                self._stop.wait(min(timeout, max(0.0, held[0] - time.monotonic())))
            else:
                with q.not_empty:  # wait for a frame without taking it (the pump may)
                    if not q.queue:
                        q.not_empty.wait(timeout)
            with self._serving:
                self._check_faults()
            self._drain()
            return
        self._check_faults()
        bus = self.bus
        if bus is None:
            return
        q = self._rxq
        if q is not None:  # python-can's virtual bus: its receive queue (virtual_rx_queue)
            try:
                msg = q.get(True, timeout) if timeout > 0 else q.get_nowait()
            except queue.Empty:
                return
        else:
            msg = bus.recv(timeout)
        if msg is not None:
            self._handle(msg)

    def _handle(self, msg: can.Message) -> None:
        """One frame: SYNC and the RPDO directly (precompiled layouts), anything else through
        the library's dispatch (``Network.notify``: NMT, SDO, heartbeats)."""
        if self._gone:
            return
        if msg.is_error_frame or msg.is_remote_frame:
            self.controller.stats.malformed += 1
            return
        fast = self._fast
        if fast is not None:  # the step's own frames without the library's dispatch
            cob = msg.arbitration_id
            if cob == 0x80 and not msg.is_extended_id:
                self._on_sync(cob, msg.data, msg.timestamp)
                return
            if cob == fast[0] and not msg.is_extended_id:  # as PdoMap.on_message stores it
                rp = self._rpdo
                rp.data = msg.data
                rp.timestamp = msg.timestamp
                rp.is_received = True
                return
        assert self.network is not None
        self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)

    def _go_away(self) -> None:
        self._gone = True
        if self.node is not None:
            self.node.nmt.stop_heartbeat()

    # -- NMT, heartbeat, SDO -------------------------------------------------------------------
    def _on_nmt(self, can_id: int, data: bytes, ts: float) -> None:
        node = self.node
        assert node is not None
        state = node.nmt.state
        if state == "OPERATIONAL" and self._nmt_state != "OPERATIONAL":
            node.rpdo.read(from_od=False)
            node.tpdo.read(from_od=False)
            self._rpdo = node.rpdo[1]
            self._tpdo = [m for m in (node.tpdo[1], node.tpdo[2]) if m.enabled and m.map]
            self._rx = {(v.index, v.subindex): v for v in self._rpdo.map}
            self._fast = self._compile()
            self._newtons = self.torque_newtons if 0x6076 in self.od else math.nan
            ctl = self.controller
            with ctl.lock:
                ctl._arm()  # a new session: plant at rest, sequence count restarted
            self.n = 0
            self._hb_watch = True
        elif state != "OPERATIONAL":
            self._hb_watch = False
        self._nmt_state = state

    def _compile(self) -> tuple[Any, ...] | None:
        """The RPDO's unpacking and each TPDO's packing as one ``struct`` each (the driver's
        :class:`~rths_hil.drivers.canopen.Layout`), checked against the library's encoding and
        decoding of the maps; ``None`` (the library's variables each step) for a map that has
        no such layout (bit fields, more than 8 bytes) or lacks the control word or set-point."""
        rp = self._rpdo
        p = self.profile
        rng = random.Random(0x7A1 + self.node_id)
        try:
            keys = [(v.index, v.subindex) for v in rp.map]
            if p.control not in keys or self._sp_obj not in keys:
                return None
            rx = Layout.of([v.od for v in rp.map], "RPDO1")
            rx.check(rp, "RPDO1", rng)
            tx = []
            for m in self._tpdo:
                layout = Layout.of([v.od for v in m.map], f"TPDO 0x{m.cob_id:03X}")
                layout.check(m, f"TPDO 0x{m.cob_id:03X}", rng)
                tx.append((m.cob_id, layout.fmt.size, layout.fmt.pack,
                           tuple((v.index, v.subindex) for v in m.map)))  # fmt: skip
        except (InputError, ValueError, KeyError) as exc:
            log.info("canopen twin node %d: PDOs through the library's variables: %s",
                     self.node_id, exc)  # fmt: skip
            return None
        return (rp.cob_id, rx.fmt.size, rx.fmt.unpack, keys.index(p.control),
                keys.index(self._sp_obj), tx)  # fmt: skip

    def _on_bridge_heartbeat(self, can_id: int, data: bytes, ts: float) -> None:
        self.controller.heartbeat()

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == self.profile.control[0]:
            self._apply(int.from_bytes(data, "little"))
        elif index == 0x6060:
            mode = int.from_bytes(data, "little", signed=True)
            if self.profile.number == 402 and mode != self._run_mode:
                # a mode the twin's plant cannot run (CSP: a displacement plant, CST: a force
                # plant; 0x6502 says which): refused as a device refuses an unsupported value
                raise SdoAbortedError(SDO_VALUE_RANGE)
            self.mode = mode
        elif index == 0x6042 and self.profile.number == 408:
            self.mode = int.from_bytes(data, "little", signed=True)
        elif index == 0x1016 and subindex == 1:
            v = int.from_bytes(data, "little")
            node_id, ms = (v >> 16) & 0x7F, v & 0xFFFF
            net = self.network
            if net is not None and node_id and node_id != self.bridge_node_id:
                net.unsubscribe(0x700 + self.bridge_node_id, self._on_bridge_heartbeat)
                self.bridge_node_id = node_id
                net.subscribe(0x700 + node_id, self._on_bridge_heartbeat)
            self.controller.heartbeat_timeout = ms / 1000.0 if ms else None

    def _on_read(self, index: int, subindex: int, od: Any) -> int | None:
        p = self.profile
        ctl = self.controller
        if (index, subindex) == p.status:
            return self.statusword()
        if (index, subindex) == p.actual:
            return self._counts(ctl.displacement)
        if self.force_object is not None and (index, subindex) == self.force_object:
            return self._force_counts(ctl.force)
        if index == 0x60F4 and p.number == 402:
            return self.target - self._counts(ctl.displacement)
        if index == 0x6061 and p.number == 402:
            return self.mode
        if index == 0x6502 and p.number == 402:
            return 1 << _MODE_BIT.get(self._run_mode, 7)
        if index == 0x6077 and p.number == 402 and 0x6076 in self.od:
            return self._torque_counts(ctl.force)
        return None

    @property
    def torque_newtons(self) -> float:
        """N per count of the target torque 0x6071 and the torque actual 0x6077: the motor
        rated torque 0x6076 (mN·m, a linear motor's rated force in mN; as written by SDO, else
        the EDS's) / 10⁶ × ``force_per_torque``."""
        node = self.node
        if node is None:
            raw = self.od[0x6076].default
        else:
            rated = node.sdo[0x6076]
            # 0x6076 is a VAR (CiA 402); the SDO client returns the matching Variable
            assert isinstance(rated, canopen.sdo.Variable)
            raw = rated.raw
        return float(raw) / 1e6 * self.force_per_torque

    def _torque_counts(self, force: float) -> int:
        if force != force:
            return 0  # an INTEGER16 has no reserved "invalid" value
        per = self._newtons
        c = round(force / (per if per == per else self.torque_newtons))
        return min(max(c, _S16[0]), _S16[1])

    # -- device FSA --------------------------------------------------------------------------
    def statusword(self) -> int:
        """The status word of the current state."""
        if self.profile.number == 402:
            return _SW402[self.state]
        return SW408[self.state]

    def _enter(self, state: str) -> None:
        if state != self.state:
            log.debug("canopen twin node %d: %s → %s", self.node_id, self.state, state)
            self.state = state
            self.history.append(state)
        ctl = self.controller
        with ctl.lock:
            if state not in ("OPERATION ENABLED", "ACTIVE"):
                ctl.enabled = False

    def _fault(self, code: int) -> None:
        if self.profile.is_fault(self.state):
            return
        self._enter("FAULT" if self.profile.number == 402 else (
            "FAULT DISABLED" if self.state in ("DISABLED", "INIT") else "FAULT HOLD"))  # fmt: skip
        if self.node is not None:
            if 0x1003 in self.od:  # the pre-defined error field (CiA 301): the newest error
                self.node.set_data(0x1003, 1, code.to_bytes(4, "little"), check_writable=False)
                self.node.set_data(0x1003, 0, b"\x01", check_writable=False)
            try:
                self.node.emcy.send(code, 0x01 | (0x10 if code == EMCY_HEARTBEAT else 0x80))
            except (can.CanError, OSError, RuntimeError):  # pragma: no cover - bus gone
                pass

    def _clear_latches(self) -> None:
        ctl = self.controller
        with ctl.lock:
            ctl.estop_latched = False
            ctl.watchdog_tripped = False
            ctl._last_heartbeat = time.monotonic()
        if self.node is not None:
            try:
                self.node.emcy.reset()
            except (can.CanError, OSError, RuntimeError):  # pragma: no cover
                pass

    def _apply(self, cw: int) -> None:
        """Apply control word ``cw`` to the device FSA."""
        prev, self._cw = self._cw, cw
        if self.profile.number == 408:
            self._apply408(cw, prev)
        else:
            self._apply402(cw, prev)

    def _apply402(self, cw: int, prev: int) -> None:
        """Control word ``cw`` (the previous one ``prev``) on the CiA 402 power drive FSA."""
        s = self.state
        if s in ("FAULT", "FAULT REACTION ACTIVE"):
            if cw & 0x80 and not prev & 0x80:  # fault reset, rising edge (transition 15)
                self._clear_latches()
                self._enter("SWITCH ON DISABLED")
            return
        if not cw & 0x02:  # disable voltage (7, 9, 10, 12)
            if s == "QUICK STOP ACTIVE":
                self._clear_latches()
            self._enter("SWITCH ON DISABLED")
        elif cw & 0x06 == 0x02:  # quick stop (11; 7, 10 from the not-operating states)
            if s == "OPERATION ENABLED":
                self.controller.estop()
                self._enter("QUICK STOP ACTIVE")
            elif s in ("READY TO SWITCH ON", "SWITCHED ON"):
                self._enter("SWITCH ON DISABLED")
        elif cw & 0x87 == 0x06:  # shutdown (2, 6, 8)
            if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self._enter("READY TO SWITCH ON")
        elif cw & 0x8F == 0x07:  # switch on (3) / disable operation (5)
            if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self._enter("SWITCHED ON")
        elif cw & 0x8F == 0x0F:  # enable operation (4; 3+4; 16 with quick stop option 5..8)
            if s in ("SWITCHED ON", "READY TO SWITCH ON"):
                self._enter("OPERATION ENABLED")
            elif s == "QUICK STOP ACTIVE":
                self._clear_latches()
                self._enter("OPERATION ENABLED")

    def _apply408(self, cw: int, prev: int) -> None:
        s = self.state
        want = {0: "INIT", 1: "DISABLED", 3: "HOLD", 7: "ACTIVE"}.get(cw & 0x07, "DISABLED")
        if s.startswith("FAULT"):
            if cw & 0x08 and not prev & 0x08:  # reset fault, rising edge (TR10/TR11)
                self._clear_latches()
                self._enter(want)
            return
        self._enter(want)

    def _check_faults(self) -> None:
        ctl = self.controller
        if not self._hb_watch or ctl.heartbeat_timeout is None:
            return
        if ctl.watchdog_tripped and not self.profile.is_fault(self.state):
            log.warning(
                "canopen twin node %d: bridge heartbeat lost → fault, EMCY 0x8130", self.node_id
            )
            self._fault(EMCY_HEARTBEAT)

    # -- the step ------------------------------------------------------------------------------
    def _following(self) -> bool:
        if self.profile.number == 402:
            return self.state == "OPERATION ENABLED" and self.mode == self._run_mode
        return self.state == "ACTIVE" and self.mode == 1

    def _on_sync(self, can_id: int, data: bytes, ts: float) -> None:
        if self._nmt_state != "OPERATIONAL" or self._rpdo is None or self._gone:
            return
        self._check_faults()
        rp = self._rpdo
        if rp.is_received:
            rp.is_received = False
            fast = self._fast
            if fast is not None:  # the layout checked against the library's decoding
                _, size, unpack, i_cw, i_sp, _ = fast
                data = rp.data
                if len(data) == size:
                    values = unpack(data)
                    cw = values[i_cw]
                    self.target = values[i_sp]
                else:
                    self.controller.stats.malformed += 1
                    cw = self._cw
            else:
                try:  # the RPDO as the library mapped it (rp.map), decoded by its PDO variables
                    cw = self._rx[self.profile.control].raw
                    self.target = self._rx[self._sp_obj].raw
                except (KeyError, ObjectDictionaryError, struct.error):
                    self.controller.stats.malformed += 1
                    cw = self._cw
            self._apply(cw)
        n = self.n
        self.n += 1
        ctl = self.controller
        if self._following():
            hb = ctl._last_heartbeat  # the consumer watches heartbeats only (CiA 301)
            if self._run_mode == MODE_CST:  # the target torque, in N to the force plant
                value = self.target * self._newtons
            else:
                value = self.target / self.counts_per_m
            reply = ctl.command(n, value, True)
            if hb is not None:
                ctl._last_heartbeat = hb
            if reply is not None and reply[3] & Status.FAULT:
                self._fault(EMCY_FOLLOWING_ERROR)
        else:
            ctl.stats.commands += 1
            reply = (n, ctl.displacement, ctl.force, 0)
        self.emit(reply)

    def _counts(self, disp: float) -> int:
        if disp != disp:
            return INVALID_S32
        c = round(disp * self.counts_per_m)
        return min(max(c, _S32[0]), _S32[1])

    def _force_counts(self, force: float) -> int:
        if force != force:
            return INVALID_S32
        c = round(force / self.newtons_per_count)
        return min(max(c, _S32[0]), _S32[1])

    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        frames = []
        p = self.profile
        values = {
            p.status: self.statusword(),
            p.actual: self._counts(displacement),
        }
        if self.force_object is not None:
            values[self.force_object] = self._force_counts(force)
        fast = self._fast
        if fast is not None:  # each TPDO by the layout checked against the library's encoding
            for cob, size, pack, keys in fast[5]:
                row = []
                for key in keys:
                    v = values.get(key)
                    if v is None:
                        v = self._on_read(key[0], key[1], None)
                    row.append(0 if v is None else v)
                frames.append(Frame(arbitration_id=cob, data=bytearray(pack(*row)),
                                    is_extended_id=False, dlc=size))  # fmt: skip
            return frames
        for m in self._tpdo:  # each TPDO through the library's map: Variable.raw, map.data
            for var in m.map:
                key = (var.index, var.subindex)
                v = values.get(key)
                if v is None:
                    v = self._on_read(key[0], key[1], None)
                var.raw = 0 if v is None else v
            frames.append(Frame(arbitration_id=m.cob_id, data=bytearray(m.data),
                                is_extended_id=False, dlc=len(m.data)))  # fmt: skip
        return frames

    def _corrupt(self, frame: can.Message) -> can.Message:
        return can.Message(
            arbitration_id=frame.arbitration_id, data=frame.data[:-1], is_extended_id=False
        )

    def _write(self, frame: can.Message) -> None:
        self._send(self.bus, frame)


#: This endpoint in the twins' registry (the twin of the driver of this module's name,
#: :func:`rths_hil.sim_backends.registry.builtin_entry`).
TWIN = TwinEntry(
    "rths_hil.sim_backends.endpoints.canopen:CANopenTwin",
    seq_bits=None,
    fresh_channel=True,
)

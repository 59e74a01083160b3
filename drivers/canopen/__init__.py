"""CANopen driver: a CiA 402 servo drive or a CiA 408 hydraulic axis, through ``canopen``.

The bridge is the CANopen NMT master and SYNC producer; the controller is node ``node_id``.
Everything of CiA 301 — SDO, NMT, PDO mapping, SYNC, heartbeat, EMCY — goes through the
``canopen`` library (:class:`canopen.Network`, :class:`canopen.RemoteNode`) over a python-can bus
(``virtual`` in tests, ``socketcan``/``pcan``/``kvaser`` … on a real bus).

**Start-up** (:meth:`CANopenDriver.open`): read the device type 0x1000 and the identity 0x1018
by SDO and check them against the profile (the low 16 bits of 0x1000 must be 402 or 408;
``vendor_id`` / ``product_code`` when given); NMT pre-operational; write the profile's mode
object (402: 0x6060 = 8, cyclic synchronous position; 408: 0x6042 = 1, set-point via bus), the
device's heartbeat producer time 0x1017 (``controller_heartbeat``) and, when given, its heartbeat
consumer 0x1016 (``device_watchdog``: the bridge's heartbeat, node ``bridge_node_id``); the PDO
mapping (:meth:`CANopenDriver._map_pdos`): with ``configure_pdo = true`` (the default) the
driver's own is written by SDO —

* RPDO1 (COB-ID 0x200 + node, synchronous): control word 0x6040 + position set-point
  (402: target position 0x607A; 408: axis position set-point 0x6600:01), 6 bytes;
* TPDO1 (0x180 + node, every SYNC): status word 0x6041 + actual position (402: 0x6064;
  408: 0x6601:01), 6 bytes;
* TPDO2 (0x280 + node, every SYNC): the measured force (``force_object``: 0x2100, the
  manufacturer-specific INTEGER32 of the project's twins, where the EDS has it, else the torque
  actual 0x6077; ``""`` for none) —

unless the EDS has the mapping objects read-only (a fixed mapping) or the device refuses the
writes with an SDO abort; then, and with ``configure_pdo = false``, the device's own mapping is
used. Either way the mapping is read back from the device by SDO and the objects are taken from
whichever PDO carries them; the torque actual (per mille of the rated torque 0x6076, read by
SDO) is scaled to N by ``force_per_torque``; a device that maps no force gives NaN. Then NMT
operational. A PDO longer than 8 bytes, an EDS without one of the objects, a device mapping no
control word / set-point / status word / actual position, a wrong device type or identity is
refused with one line (:class:`~rths_hil.errors.InputError`, exit 2).

**Each step** (the base class's contract: :meth:`~..base.Driver.send` →
:meth:`CANopenDriver._send_raw`, :meth:`~..base.Driver.receive` →
:meth:`CANopenDriver._recv_internal`): RPDO1 with the control word and the set-point, then one
SYNC, sent by the bus (:class:`CANopenBus`) as soon as every axis on it has written its RPDO
(or when the first axis waits for its step's feedback, if one did not send), so several axes on
one bus share one SYNC per step. The
SYNC is the step clock: the devices apply the RPDO received before it and answer with their
TPDOs. The feedback of step ``k`` is the TPDO set received after SYNC ``k`` (TPDOs carry no
sequence number: a TPDO that comes after the next SYNC is taken for the next step's, see
``docs/canopen.md``). The RPDO is packed and the TPDOs unpacked by one precompiled ``struct``
each (:class:`Layout`), checked at start-up against the library's encoding and decoding of its
PDO maps (:meth:`Layout.check`; the library stays the authority on the mapping).
Positions are counts on the wire (``counts_per_m``), forces counts of ``newtons_per_count``.
The base class owns the receive deadline, the timeouts, the sequence rules and the counters.

**State machine.** The control word of each step follows the device's last reported state one
transition at a time (402: shutdown → switch on → enable operation; 408: active), so the run's
first ``enable=True`` steps bring the drive into operation without a jump (the first set-point
must be within ``start_tolerance`` of the actual position read at arming). :meth:`estop` sends
the profile's e-stop word at once (402 quick stop 0x0002 → QUICK STOP ACTIVE; 408 hold 0x0003,
latched by the driver since the 408 FSA has no quick-stop state) with its own SYNC, and repeats
it every step until a command with ``enable=False`` acknowledges it (402: disable voltage →
SWITCH ON DISABLED). :meth:`arm` resets a fault (402 fault reset 0x0080, 408 bit 3, each a
rising edge) and brings the device to holding (402 SWITCHED ON, 408 HOLD) by SDO. At a normal
end :meth:`close` hands the device back disabled by its own sequence (402 shutdown → disable
voltage: SWITCH ON DISABLED; 408 DISABLED), after an e-stop it leaves the latch; it clears the
device's heartbeat consumer 0x1016:01 when it set it (the bridge's heartbeat stops), and always
ends with NMT stop.

**Status.** 402 OPERATION ENABLED → ``ENABLED``, QUICK STOP ACTIVE → ``ESTOP_ACTIVE``, FAULT
(REACTION ACTIVE) → ``FAULT``; 408 ACTIVE → ``ENABLED``, HOLD after the e-stop →
``ESTOP_ACTIVE``, FAULT * → ``FAULT``. An EMCY with a non-zero error code sets ``FAULT`` (and
``WATCHDOG`` for 0x8130, heartbeat / life-guard error) until the next arming; the code is logged,
counted in the driver's stats (``emcy``) and named by :meth:`fault_text`, which the loop adds to
its controller trip. The controller's heartbeat (``controller_heartbeat``): when none came for
``controller_heartbeat_timeout`` (1 s), :meth:`_recv_internal` raises
:class:`~..base.LinkDown` (counted ``heartbeat_lost``): the receive returns nothing, so the loop's
watchdog — which counts time — trips.

Connection keys: ``eds`` (required: the controller's EDS file), ``node_id`` (1–127),
``device_profile`` (``cia402`` / ``cia408``), ``interface``, ``channel``, ``bitrate``,
``bus_options``, ``counts_per_m``, ``force_object``, ``newtons_per_count``, ``force_per_torque``,
``bridge_node_id``,
``heartbeat_period``, ``controller_heartbeat``, ``controller_heartbeat_timeout``,
``device_watchdog``, ``start_tolerance``, ``sdo_timeout``, ``vendor_id``, ``product_code``,
``configure_pdo`` (documented in ``docs/canopen.md``).
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
from collections import deque
from dataclasses import dataclass, field
from typing import Any, ClassVar

import can
import canopen
from canopen.emcy import EmcyError
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.objectdictionary.datatypes import INTEGER32
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from rths_hil.errors import InputError
from rths_hil.units import parse_length, parse_time

from ..base import Driver, DriverStats, Feedback, LinkDown, Status
from ..can import TIMEOUT_HONOURED, virtual_rx_queue
from ..can.codec import Frame
from .profiles import PROFILES, Profile

__all__ = [
    "BRIDGE_NODE_ID",
    "CANopenDriver",
    "CANopenStats",
    "Layout",
    "axes_that_fit",
    "link_load",
    "load_od",
    "parse_object",
    "step_frames",
]

log = logging.getLogger(__name__)

#: Default node id of the bridge (its heartbeat is 0x700 + this).
BRIDGE_NODE_ID = 127
#: SYNC COB-ID (CiA 301).
SYNC_ID = 0x80
#: Heartbeat NMT state byte of an operational node.
NMT_OPERATIONAL = 0x05
#: EMCY error code of a heartbeat / life-guard event (CiA 301).
EMCY_HEARTBEAT = 0x8130
#: longest wait after an e-stop for the device to report it before the next command (s)
ESTOP_SETTLE = 0.1
#: the measured force of the project's twins (manufacturer-specific INTEGER32)
FORCE_OBJECT = (0x2100, 0)
#: CiA 402 torque actual value (INTEGER16, per mille of the motor rated torque 0x6076)
TORQUE_ACTUAL = (0x6077, 0)
#: CiA 402 motor rated torque (UNSIGNED32, mN·m; mN for a linear motor)
RATED_TORQUE = (0x6076, 0)
_WATCHDOG = int(Status.WATCHDOG)
_ESTOP = int(Status.ESTOP_ACTIVE)
_FAULT = int(Status.FAULT)
_S32 = (-(2**31), 2**31 - 1)
_BUS_ERRORS = (can.CanError, OSError, ValueError, ImportError, NotImplementedError)
_SDO_ERRORS = (SdoAbortedError, SdoCommunicationError)
_perf = time.perf_counter
#: a TPDO of the current SYNC that has not come yet
_MISSING = object()


@dataclass(slots=True)
class CANopenStats(DriverStats):
    """:class:`DriverStats` plus the CANopen counters.

    Attributes
    ----------
    syncs : int
        SYNC frames sent.
    emcy : list of str
        Every EMCY received, as ``"0x8130 Monitoring"``.
    heartbeat_lost : int
        Receives that returned nothing because the controller's heartbeat had stopped.
    """

    syncs: int = 0
    emcy: list[str] = field(default_factory=list)
    heartbeat_lost: int = 0


def parse_object(text: Any, what: str) -> tuple[int, int]:
    """``"0x6064"`` or ``"0x6600:1"`` (or an int) → (index, sub-index)."""
    if isinstance(text, int) and not isinstance(text, bool):
        return int(text), 0
    s = str(text).strip()
    idx, _, sub = s.partition(":")
    try:
        return int(idx, 0), int(sub, 0) if sub else 0
    except ValueError:
        raise InputError(
            f"canopen: {what}: {text!r} is not an object index like 0x2100 or 0x6600:1"
        ) from None


def _quantity(key: str, value: Any, unit: str) -> Any:
    """A time (s) or length (m) key given as a string with its unit (``"0.1 s"``, ``"1mm"``)
    read to SI; anything else as it is (checked by the caller)."""
    if isinstance(value, str):
        return (parse_time if unit == "s" else parse_length)(value, f"canopen: {key}")
    return value


def _identity(key: str, value: Any) -> int | None:
    """``vendor_id`` / ``product_code``: an integer, or a string such as ``"0x0000A3C7"``."""
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 0xFFFFFFFF:
        return value
    if isinstance(value, str):
        try:
            v = int(value.strip(), 0)
        except ValueError:
            v = -1
        if 0 <= v <= 0xFFFFFFFF:
            return v
    raise InputError(
        f"canopen: {key} must be an UNSIGNED32 like 0x0000A3C7 (0x1018), got {value!r}"
    )


def _check_bitrate(bitrate: Any) -> None:
    """``bitrate``: None (the interface's) or a positive whole number of bit/s."""
    if bitrate is None:
        return
    if (
        isinstance(bitrate, bool)
        or not isinstance(bitrate, int | float)
        or not (math.isfinite(bitrate) and bitrate > 0 and float(bitrate).is_integer())
    ):
        raise InputError(f"canopen: bitrate must be a positive integer (bit/s), got {bitrate!r}")


def load_od(eds: str | os.PathLike[str], node_id: int) -> canopen.ObjectDictionary:
    """The object dictionary of an EDS file; one line when it cannot be read."""
    path = os.fspath(eds)
    if not os.path.exists(path):
        raise InputError(f"canopen: eds: no such file {path!r}")
    if not os.path.isfile(path):
        raise InputError(f"canopen: eds {path!r} is not a regular file (an EDS text file)")
    try:
        return canopen.import_od(path, node_id)
    except Exception as exc:  # the EDS parser raises anything from configparser to KeyError
        raise InputError(f"canopen: eds {path!r} cannot be read: {exc}") from None


def _variable(
    od: canopen.ObjectDictionary, obj: tuple[int, int], path: str, what: str
) -> ODVariable:
    index, sub = obj
    try:
        entry = od[index]
        if isinstance(entry, ODRecord | ODArray):
            entry = entry[sub]
        elif sub:  # a VAR has only sub-index 0
            raise KeyError(sub)
    except KeyError:
        raise InputError(
            f"canopen: eds {path!r} has no object 0x{index:04X}:{sub:02X} ({what})"
        ) from None
    if not isinstance(entry, ODVariable):  # pragma: no cover - defensive
        raise InputError(f"canopen: eds {path!r}: 0x{index:04X}:{sub:02X} ({what}) is not a value")
    return entry


@dataclass(frozen=True)
class Layout:
    """Byte layout of one PDO: ``struct`` format and the bits it takes (checked ≤ 64)."""

    fmt: struct.Struct
    bits: int

    @classmethod
    def of(cls, variables: list[ODVariable], name: str) -> Layout:
        """The little-endian layout of ``variables`` in order (CiA 301 PDO mapping)."""
        bits = sum(len(v) for v in variables)
        if bits > 64:
            objs = " + ".join(
                f"0x{v.index:04X}:{v.subindex:02X} ({len(v)} bits)" for v in variables
            )
            raise InputError(f"canopen: {name} does not fit in 8 bytes: {objs} = {bits} bits")
        fmt = "<"
        for v in variables:
            st = v.STRUCT_TYPES.get(v.data_type)
            if st is None or 8 * st.size != len(v):
                raise InputError(
                    f"canopen: {name}: object 0x{v.index:04X}:{v.subindex:02X} is not a "
                    "whole-byte integer"
                )
            fmt += st.format.lstrip("<")
        return cls(struct.Struct(fmt), bits)

    def check(self, pdo_map: Any, name: str, rng: random.Random, rounds: int = 8) -> None:
        """Refuse (one line) unless this layout packs and unpacks exactly as the library does.

        ``pdo_map`` is the library's PDO map (``canopen.pdo.PdoMap``) of the objects this
        layout was built from. For ``rounds`` sets of values (each object's extremes, 0, 1 and
        random values of its type) the bytes of :attr:`fmt` must equal the map's data after
        ``PdoVariable.raw = value`` for each mapped object (``ODVariable.encode_raw`` at the
        library's offsets), and for as many random payloads :attr:`fmt` must unpack the values
        ``PdoVariable.raw`` decodes. The map's data is restored afterwards. This is what lets
        the step pack and unpack a PDO with one precompiled ``struct`` call while the library
        stays the authority on the mapping and the encoding.
        """
        variables = list(pdo_map.map)
        size = self.fmt.size
        if sum(v.length for v in variables) != 8 * size:
            raise InputError(f"canopen: {name}: the library maps {len(variables)} objects that "
                             f"are not the {size} bytes the driver packs")  # fmt: skip
        samples = [_sample_values(v.od, rng, rounds) for v in variables]
        saved = pdo_map.data
        try:
            for j in range(rounds):
                values = [col[j] for col in samples]
                pdo_map.data = bytearray(size)
                for var, value in zip(variables, values, strict=True):
                    var.raw = value
                try:
                    ours = self.fmt.pack(*values)
                except struct.error as exc:
                    raise InputError(
                        f"canopen: {name}: the driver cannot pack {values} ({exc}), the canopen "
                        f"library's encoding is {bytes(pdo_map.data).hex()}"
                    ) from None
                if bytes(pdo_map.data) != ours:
                    raise InputError(
                        f"canopen: {name}: the driver's packing of {values} is {ours.hex()}, "
                        f"the canopen library's is {bytes(pdo_map.data).hex()}"
                    )
                payload = bytes(rng.getrandbits(8) for _ in range(size))
                pdo_map.data = bytearray(payload)
                lib = [var.raw for var in variables]
                mine = list(self.fmt.unpack(payload))
                if any(a != b and (a == a or b == b) for a, b in zip(lib, mine, strict=True)):
                    raise InputError(
                        f"canopen: {name}: the driver unpacks {payload.hex()} as {mine}, the "
                        f"canopen library as {lib}"
                    )
        finally:
            pdo_map.data = saved


def _sample_values(var: ODVariable, rng: random.Random, n: int) -> list[Any]:
    """``n`` values of ``var``'s type: its extremes, 0, 1, then random ones (floats for REAL)."""
    st = var.STRUCT_TYPES[var.data_type]
    code = st.format[-1]
    if code in "fd":
        base = [0.0, 1.5, -2.25]
        draw = lambda: st.unpack(st.pack(rng.uniform(-1e9, 1e9)))[0]  # noqa: E731
    elif code == "?":
        base = [False, True]
        draw = lambda: rng.random() < 0.5  # noqa: E731
    else:
        bits = 8 * st.size
        lo, hi = ((-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if code.islower()
                  else (0, (1 << bits) - 1))  # fmt: skip
        base = [lo, hi, 0, 1]
        draw = lambda: rng.randint(lo, hi)  # noqa: E731
    out = base[:n]
    while len(out) < n:
        out.append(draw())
    return out


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
        network.listeners.append(_BusGone(self))  # every notifier started on the network
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


class CANopenDriver(Driver):
    """Lockstep actuator driver over CANopen (see the module docstring)."""

    name: ClassVar[str] = "canopen"
    #: the bus is read with the time left (virtual queue / SocketCAN) or waited for on an event
    #: the library's notifier thread sets
    honours_deadline: ClassVar[bool] = True
    #: the feedback carries the step of its SYNC (a TPDO set belongs to the SYNC before it)
    echoes_seq: ClassVar[bool] = True
    #: positions are INTEGER32 counts of ``counts_per_m``, checked in :meth:`_send_raw`
    command_lsb: ClassVar[float | None] = None
    #: force: CiA 402 cyclic synchronous torque (:meth:`set_control`); CiA 408 refuses it
    control_modes: ClassVar[tuple[str, ...]] = ("displacement", "force")
    stats: CANopenStats

    def __init__(  # noqa: C901 - the connection keys, checked one by one
        self,
        eds: str | None = None,
        node_id: int = 1,
        device_profile: str = "cia402",
        interface: str = "virtual",
        channel: str = "rths-canopen",
        bitrate: int | None = None,
        bus_options: dict[str, Any] | None = None,
        counts_per_m: float = 1e7,
        force_object: str | None = None,
        newtons_per_count: float | None = None,
        force_per_torque: float = 1.0,
        bridge_node_id: int = BRIDGE_NODE_ID,
        heartbeat_period: float = 0.1,
        controller_heartbeat: float = 0.1,
        controller_heartbeat_timeout: float = 1.0,
        device_watchdog: float | None = None,
        start_tolerance: float = 1e-3,
        sdo_timeout: float = 0.5,
        vendor_id: int | None = None,
        product_code: int | None = None,
        configure_pdo: bool = True,
    ) -> None:
        super().__init__()
        self.stats = CANopenStats()
        if device_profile not in PROFILES:
            raise InputError(
                f"canopen: device_profile {device_profile!r} is not known (known: "
                f"{', '.join(PROFILES)})"
            )
        self.profile: Profile = PROFILES[device_profile]
        for key, v, lo in (("node_id", node_id, 1), ("bridge_node_id", bridge_node_id, 1)):
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= 127:
                raise InputError(f"canopen: {key} must be an integer 1..127, got {v!r}")
        if node_id == bridge_node_id:
            raise InputError(f"canopen: node_id and bridge_node_id are both {node_id}")
        for key, v in (
            ("counts_per_m", counts_per_m),
            ("newtons_per_count", 0.01 if newtons_per_count is None else newtons_per_count),
            ("force_per_torque", force_per_torque),
        ):
            if (
                isinstance(v, bool)
                or not isinstance(v, int | float)
                or not (math.isfinite(v) and v > 0)
            ):
                raise InputError(f"canopen: {key} must be a positive number, got {v!r}")
        if counts_per_m is not None and isinstance(counts_per_m, int | float):
            if not isinstance(counts_per_m, bool) and counts_per_m > 1e12:
                raise InputError(
                    f"canopen: counts_per_m must be ≤ 1e12 (1 pm per count; INTEGER32 then "
                    f"spans ±2.1 mm), got {counts_per_m!r}"
                )
        heartbeat_period = _quantity("heartbeat_period", heartbeat_period, "s")
        controller_heartbeat = _quantity("controller_heartbeat", controller_heartbeat, "s")
        controller_heartbeat_timeout = _quantity(
            "controller_heartbeat_timeout", controller_heartbeat_timeout, "s"
        )
        start_tolerance = _quantity("start_tolerance", start_tolerance, "m")
        sdo_timeout = _quantity("sdo_timeout", sdo_timeout, "s")
        device_watchdog = _quantity("device_watchdog", device_watchdog, "s")
        for key, v in (
            ("heartbeat_period", heartbeat_period),
            ("controller_heartbeat", controller_heartbeat),
            ("controller_heartbeat_timeout", controller_heartbeat_timeout),
            ("start_tolerance", start_tolerance),
            ("sdo_timeout", sdo_timeout),
            ("device_watchdog", 0.0 if device_watchdog is None else device_watchdog),
        ):
            if (
                isinstance(v, bool)
                or not isinstance(v, int | float)
                or not (math.isfinite(v) and v >= 0)
            ):
                raise InputError(f"canopen: {key} must be a number ≥ 0 (s), got {v!r}")
        if controller_heartbeat * 1000 > 65535:
            raise InputError("canopen: controller_heartbeat must be ≤ 65.535 s (0x1017 in ms)")
        if device_watchdog is not None and device_watchdog * 1000 > 65535:
            raise InputError(
                f"canopen: device_watchdog must be ≤ 65.535 s (0x1016 holds 16 bits of ms), "
                f"got {device_watchdog!r}"
            )
        _check_bitrate(bitrate)
        if eds is None:
            raise InputError("canopen: eds: give the controller's EDS file (driver.connection.eds)")
        self.eds = os.fspath(eds)
        self.node_id = node_id
        self.bridge_node_id = bridge_node_id
        self.interface, self.channel = str(interface), str(channel)
        self.bitrate = None if bitrate is None else int(bitrate)
        self.bus_options = dict(bus_options or {})
        self.counts_per_m = float(counts_per_m)
        #: the force scale given (None: 0.01 N per count, or from 0x6076 for the torque actual)
        self._newtons_given = None if newtons_per_count is None else float(newtons_per_count)
        self.newtons_per_count = 0.01 if newtons_per_count is None else float(newtons_per_count)
        self.force_per_torque = float(force_per_torque)
        self.heartbeat_period = float(heartbeat_period)
        self.controller_heartbeat = float(controller_heartbeat)
        self.controller_heartbeat_timeout = float(controller_heartbeat_timeout)
        self.device_watchdog = None if not device_watchdog else float(device_watchdog)
        self.start_tolerance = float(start_tolerance)
        self.sdo_timeout = float(sdo_timeout) or 0.5
        self.vendor_id = _identity("vendor_id", vendor_id)
        self.product_code = _identity("product_code", product_code)
        if not isinstance(configure_pdo, bool):
            raise InputError(
                f"canopen: configure_pdo must be true or false (a TOML boolean), got "
                f"{configure_pdo!r}"
            )
        self.configure_pdo = configure_pdo
        self.od = load_od(self.eds, node_id)
        p = self.profile
        if force_object is None:  # the twins' 0x2100 where the EDS has it, else torque actual
            cands = [o for o in (FORCE_OBJECT, TORQUE_ACTUAL) if o[0] in self.od]
        elif str(force_object).strip():
            cands = [parse_object(force_object, "force_object")]
        else:
            cands = []
        #: objects that may carry the measured force, in order of preference (``force_object``)
        self._force_candidates = cands
        f_obj = cands[0] if cands else None
        #: the force object of the driver's own mapping; after start-up the one a TPDO carries
        self.force_object = f_obj
        self._force_nan: int | None = _S32[0]  # the "no valid value" of an INTEGER32 force
        #: force mode: N per count of the target torque (0x6076 / 10⁶ × force_per_torque, read
        #: at start-up) and the measured force read at arming (the first set-point's reference)
        self._torque_newtons = math.nan
        self._force_at_arm: float | None = None
        v = {
            "control": _variable(self.od, p.control, self.eds, "control word"),
            "status": _variable(self.od, p.status, self.eds, "status word"),
            "setpoint": _variable(self.od, p.setpoint, self.eds, "position set-point"),
            "actual": _variable(self.od, p.actual, self.eds, "actual position"),
        }
        for obj, what, needed in (
            (0x1000, "device type", True),
            (0x1018, "identity", True),
            (0x1017, "producer heartbeat time, for controller_heartbeat", controller_heartbeat),
            (0x1016, "consumer heartbeat time, for device_watchdog", self.device_watchdog),
        ):
            if needed and obj not in self.od:
                raise InputError(f"canopen: eds {self.eds!r} has no object 0x{obj:04X} ({what})")
        if p.mode is not None:
            _variable(self.od, p.mode[:2], self.eds, "mode")
        for key in ("control", "setpoint"):  # written by SDO (arming, hand-back) and by RPDO
            if not v[key].writable:
                raise InputError(
                    f"canopen: eds {self.eds!r}: 0x{v[key].index:04X}:{v[key].subindex:02X} "
                    f"({v[key].name}, the {key.replace('setpoint', 'position set-point')}"
                    f"{' word' if key == 'control' else ''}) is read-only: the bridge cannot "
                    "command the device"
                )
        self._rpdo_vars = [v["control"], v["setpoint"]]
        self._tpdo1_vars = [v["status"], v["actual"]]
        self._tpdo2_vars = (
            [_variable(self.od, f_obj, self.eds, "force_object")] if f_obj is not None else []
        )
        for obj in cands:
            fv = _variable(self.od, obj, self.eds, "force_object")
            own = {p.control: "control word", p.status: "status word",
                   p.setpoint: "position set-point", p.actual: "actual position"}  # fmt: skip
            code = (
                fv.STRUCT_TYPES[fv.data_type].format[-1] if fv.data_type in fv.STRUCT_TYPES else ""
            )
            if obj in own or not code or not code.islower() or code in "fd?":
                why = f"the profile's {own[obj]}" if obj in own else "not a signed integer"
                raise InputError(
                    f"canopen: force_object 0x{obj[0]:04X}:{obj[1]:02X} ({fv.name}) is {why}: "
                    "give the object that carries the measured force"
                )
        for var in (*self._rpdo_vars, *self._tpdo1_vars, *self._tpdo2_vars):
            if not var.pdo_mappable and self.configure_pdo:
                raise InputError(
                    f"canopen: eds {self.eds!r}: 0x{var.index:04X}:{var.subindex:02X} "
                    f"({var.name}) is not PDO-mappable (PDOMapping=0), the driver cannot map it "
                    "(configure_pdo = false takes the mapping the device has)"
                )
        self.rpdo_layout = Layout.of(self._rpdo_vars, "RPDO1")
        self.tpdo1_layout = Layout.of(self._tpdo1_vars, "TPDO1")
        self.tpdo2_layout = Layout.of(self._tpdo2_vars, "TPDO2") if self._tpdo2_vars else None
        self._rpdo_id = 0x200 + node_id
        self._tpdo_ids = (0x180 + node_id, 0x280 + node_id)
        self._hb_id = 0x700 + bridge_node_id
        self.network: canopen.Network | None = None
        self.node: canopen.RemoteNode | None = None
        self._q: deque[Feedback] = deque()  # decoded feedback (appended by _on_tpdo)
        self._wake = threading.Event()  # set by _on_tpdo (the notifier thread's hand-off)
        self._lock = threading.Lock()
        # the TPDO values of the current SYNC: one slot per TPDO used (in PDO number order),
        # _MISSING until it came, None when malformed; reset at every SYNC. Until _map_pdos
        # reads the device's mapping: the driver's own (TPDO1 = status word + position,
        # TPDO2 = force)
        self._n_tpdo = 2 if f_obj is not None else 1
        self._blank: tuple[Any, ...] = (_MISSING,) * self._n_tpdo
        self._part: list[Any] = list(self._blank)
        self._have = 0  # TPDOs of the current SYNC received
        #: (slot, position) in the TPDO values of the status word, the actual position and
        #: the force (None: not mapped)
        self._at: tuple[tuple[int, int] | None, ...] = (
            (0, 0),
            (0, 1),
            (1, 0) if f_obj is not None else None,
        )
        #: the PDOs used, as the device maps them (``"TPDO1": "COB-ID 0x185: 0x6041:00 + …"``)
        self.mapping: dict[str, str] = {}
        self._states: dict[int, str] = {}
        self._flags: dict[tuple[str, bool], int] = {}
        self._words: dict[tuple[str, bool, bool], int] = {}
        # the library's PDO maps and the precompiled packing checked against them (_map_pdos)
        self._rpdo_map: Any = None
        self._tpdo_maps: dict[int, Any] = {}
        self._tpdo_decode: dict[int, tuple[int, int, Any]] = {}  # cob → (slot, size, unpack)
        self._step = -1  # the step the last SYNC belongs to
        self._delivered_sync = -2
        self._state = "NOT READY TO SWITCH ON" if p.number == 402 else "NOT READY"
        self._latched = False
        self._estop_seen = False  # the device reported the e-stop state since the e-stop
        self._emcy_code = 0
        self._emcy_text = ""
        self._hb_seen: float | None = None
        self._hb_last_sent = 0.0
        self._last_counts = 0
        self._actual_at_arm: float | None = None
        self._first_enable = True
        self._opened = False
        self._bus: CANopenBus | None = None
        self._awaiting: int | None = None  # the step of an RPDO sent and not yet SYNCed
        # the RPDO of every step, built once and rewritten in place (Frame: a can.Message that
        # the virtual bus copies cheaply, drivers.can.codec); the SYNC is the bus's
        self._rpdo_msg = Frame.blank(self._rpdo_id, self.rpdo_layout.fmt.size)
        self._rpdo_data = self._rpdo_msg.data
        #: each RPDO of a step: its frame and ``pack(word, counts)`` (set by _map_pdos)
        self._rpdo_out: list[tuple[Frame, Any]] = []
        #: the bridge wrote the device's heartbeat consumer 0x1016:01 (cleared at close)
        self._consumer_set = False
        self._hb_msg = Frame(
            arbitration_id=self._hb_id, is_extended_id=False, dlc=1, data=bytes((NMT_OPERATIONAL,))
        )

    # ------------------------------------------------------------------------------------------
    # what the class knows: its link and who may share it
    @classmethod
    def inline_twin(cls, connection: dict[str, Any]) -> bool:
        """The twin on python-can's in-process ``virtual`` bus serves the steps from the loop's
        thread (its own thread answers the SDO exchanges, see
        :meth:`rths_hil.sim_backends.endpoints.canopen_twin.CANopenTwin.start`)."""
        return str((connection or {}).get("interface", "virtual")) == "virtual"

    @classmethod
    def link_key(cls, connection: dict[str, Any]) -> str:
        """CANopen: the python-can interface and channel of the bus."""
        c = connection or {}
        return f"canopen {c.get('interface', 'virtual')}:{c.get('channel', 'rths-canopen')}"

    @classmethod
    def link_load(
        cls,
        connection: dict[str, Any],
        channels_on_link: int,
        fs: float,
        *,
        heartbeat_hz: float = 0.0,
    ):
        """SYNC, PDOs and heartbeats on the bus (:func:`link_load` of this module)."""
        return link_load(connection, int(channels_on_link), float(fs), heartbeat_hz=heartbeat_hz)

    @classmethod
    def check_sharing(cls, channels: list[tuple[int, str, dict[str, Any], bool]]) -> None:
        """Several axes may share a bus (one SYNC per step for all, :class:`CANopenBus`), each
        with its own node id and the bus's settings (bit rate, the bridge's node id)."""
        seen: dict[str, dict[str, Any]] = {}
        for _, name, conn, twin in channels:
            c = conn or {}
            if twin and not c.get("channel"):
                continue  # each twin gets a bus of its own
            key = cls.link_key(c)
            where = key.split(" ", 1)[1]
            first = seen.setdefault(key, {"name": name, "nodes": {}, "conn": c})
            node = c.get("node_id", 1)
            other = first["nodes"].get(node)
            if other is not None:
                raise InputError(
                    f"actuators: channels {other!r} and {name!r} are both CANopen node {node} on "
                    f"bus {where}: give each axis its own driver.connection.node_id"
                )
            first["nodes"][node] = name
            for k, default in (("bitrate", None), ("bridge_node_id", BRIDGE_NODE_ID)):
                if c.get(k, default) != first["conn"].get(k, default):
                    raise InputError(
                        f"actuators: channels {first['name']!r} and {name!r} share CANopen bus "
                        f"{where} but differ in driver.connection.{k} "
                        f"({first['conn'].get(k, default)} vs {c.get(k, default)})"
                    )

    # ------------------------------------------------------------------------------------------
    # the wire mode
    def set_control(self, mode: str) -> None:
        """Select the wire mode before :meth:`open` (:meth:`Driver.set_control`).

        ``"force"``: CiA 402 cyclic synchronous torque — modes of operation 0x6060 = 10, the
        target torque 0x6071 (per mille of the motor rated torque 0x6076, scaled to N by
        ``force_per_torque``) in the RPDO instead of the target position; the measured force
        as before (the torque actual 0x6077 or ``force_object``). Refused with one line: a
        profile without force control (CiA 408), an EDS without 0x6071 (writable, mappable)
        or 0x6076, a channel with no measured force; at start-up a drive whose supported
        drive modes 0x6502 lack CST, or whose mode display 0x6061 does not show it.
        """
        super().set_control(mode)
        try:
            self._use_control(mode)
        except InputError:
            self.control = "displacement"
            raise

    def _use_control(self, mode: str) -> None:
        base = PROFILES[self.profile.name]
        prof = base.for_control(mode)
        if prof is None:
            raise InputError(
                f"canopen: device_profile {base.name!r} has no force control the driver "
                "speaks (CiA 402 cyclic synchronous torque can): a force-controlled channel "
                "needs another controller"
            )
        if prof is self.profile:
            return
        if mode == "force":
            if not self._force_candidates:
                raise InputError(
                    "canopen: a force-controlled channel needs the measured force: give "
                    'driver.connection.force_object (force_object = "" maps none)'
                )
            if RATED_TORQUE[0] not in self.od:
                raise InputError(
                    f"canopen: eds {self.eds!r} has no object 0x6076 (motor rated torque) to "
                    f"scale the {prof.setpoint_name} 0x{prof.setpoint[0]:04X}"
                )
        sp = _variable(self.od, prof.setpoint, self.eds, prof.setpoint_name)
        if not sp.writable:
            raise InputError(
                f"canopen: eds {self.eds!r}: 0x{sp.index:04X}:{sp.subindex:02X} ({sp.name}, the "
                f"{prof.setpoint_name}) is read-only: the bridge cannot command the device"
            )
        if not sp.pdo_mappable and self.configure_pdo:
            raise InputError(
                f"canopen: eds {self.eds!r}: 0x{sp.index:04X}:{sp.subindex:02X} ({sp.name}) is "
                "not PDO-mappable (PDOMapping=0), the driver cannot map it (configure_pdo = "
                "false takes the mapping the device has)"
            )
        self.profile = prof
        self._rpdo_vars = [self._rpdo_vars[0], sp]
        self.rpdo_layout = Layout.of(self._rpdo_vars, "RPDO1")
        self._rpdo_msg = Frame.blank(self._rpdo_id, self.rpdo_layout.fmt.size)
        self._rpdo_data = self._rpdo_msg.data

    def _check_force_mode(self) -> None:
        """Start-up in force mode (pre-operational): the drive must support the mode (0x6502,
        when the EDS has it) before it is written; the rated torque scales the set-point."""
        p = self.profile
        bit = p.mode_bit
        if bit is not None and 0x6502 in self.od:
            modes = self._sdo_read(0x6502)
            if not modes >> bit & 1:
                raise InputError(
                    f"canopen: node {self.node_id} does not support cyclic synchronous torque "
                    f"(supported drive modes 0x6502 = 0x{modes:08X}, bit {bit} clear): it "
                    "cannot run a force-controlled channel"
                )
        rated = self._sdo_read(*RATED_TORQUE)
        if rated <= 0:
            raise InputError(
                f"canopen: node {self.node_id}: motor rated torque 0x6076 is {rated}: the "
                f"{p.setpoint_name} 0x{p.setpoint[0]:04X} cannot be scaled"
            )
        self._torque_newtons = rated / 1e6 * self.force_per_torque

    def _check_mode_display(self) -> None:
        """Force mode: the modes of operation display 0x6061 (where the EDS has it) shows the
        mode written, within ``sdo_timeout`` (a drive switches modes in its own time)."""
        p = self.profile
        if p.mode is None or p.number != 402 or 0x6061 not in self.od:
            return
        want = p.mode[2]
        end = time.monotonic() + self.sdo_timeout
        while True:
            shown = self._sdo_read(0x6061)
            if shown == want:
                return
            if time.monotonic() > end:
                raise InputError(
                    f"canopen: node {self.node_id} shows modes of operation {shown} (0x6061) "
                    f"after 0x6060 = {want} was written: it did not switch to "
                    f"{'cyclic synchronous torque' if want == 10 else f'mode {want}'}"
                )
            time.sleep(0.005)

    # ------------------------------------------------------------------------------------------
    # start-up
    def _sdo_read(self, index: int, sub: int = 0) -> int:
        assert self.node is not None
        try:
            var = self.node.sdo[index]
            if not isinstance(var.od, ODVariable):
                var = var[sub]
            return int(var.raw)
        except _SDO_ERRORS as exc:
            raise InputError(
                f"canopen: node {self.node_id}: SDO read of 0x{index:04X}:{sub:02X} failed: {exc}"
            ) from None

    def _sdo_write(self, index: int, sub: int, value: int) -> None:
        assert self.node is not None
        try:
            var = self.node.sdo[index]
            if not isinstance(var.od, ODVariable):
                var = var[sub]
            var.raw = value
        except _SDO_ERRORS as exc:
            raise InputError(
                f"canopen: node {self.node_id}: SDO write of 0x{index:04X}:{sub:02X} = {value} "
                f"failed: {exc}"
            ) from None

    def open(self) -> None:
        if self._opened:
            return
        bus = self._bus = CANopenBus.join(self)
        net = self.network = bus.network
        node = canopen.RemoteNode(self.node_id, self.od)
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
        net.add_node(node)
        self.node = node
        self._opened = True
        bus.listen(True)
        try:
            self._start_up()
        except BaseException:
            bus.listen(False)
            self._shutdown_network()
            raise
        bus.listen(False)

    def _listen(self, on: bool) -> None:
        """Run the library's notifier thread (SDO phases) or read from the caller's thread."""
        if self._bus is not None:
            self._bus.listen(on)

    def _start_up(self) -> None:
        node = self.node
        assert node is not None
        p = self.profile
        dev = self._sdo_read(0x1000)
        if dev & 0xFFFF != p.number:
            raise InputError(
                f"canopen: node {self.node_id} reports device type 0x{dev:08X} (profile "
                f"{dev & 0xFFFF}), not CiA {p.number} (driver.connection.device_profile = "
                f"{p.name!r})"
            )
        vendor, product = self._sdo_read(0x1018, 1), self._sdo_read(0x1018, 2)
        self.identity = {
            "device_type": dev,
            "vendor_id": vendor,
            "product_code": product,
            "revision": self._sdo_read(0x1018, 3),
        }
        for key, want, got in (
            ("vendor_id", self.vendor_id, vendor),
            ("product_code", self.product_code, product),
        ):
            if want is not None and int(want) != got:
                raise InputError(
                    f"canopen: node {self.node_id} identity 0x1018: {key} is 0x{got:08X}, the "
                    f"configuration expects 0x{int(want):08X}"
                )
        log.info("canopen: node %d identity %s", self.node_id, self.identity)
        node.nmt.send_command(0x80)  # pre-operational
        force = p.control_mode == "force"
        if force:
            self._check_force_mode()
        if p.mode is not None:
            self._sdo_write(*p.mode)
        if force:
            self._check_mode_display()
        self._sdo_write(0x1017, 0, round(self.controller_heartbeat * 1000))
        if self.device_watchdog is not None:
            ms = max(1, round(self.device_watchdog * 1000))
            self._sdo_write(0x1016, 1, (self.bridge_node_id << 16) | min(ms, 0xFFFF))
            self._consumer_set = True
        try:
            self._map_pdos()
        except _SDO_ERRORS as exc:
            raise InputError(f"canopen: node {self.node_id}: PDO mapping failed: {exc}") from None
        node.emcy.add_callback(self._on_emcy)
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        node.nmt.send_command(0x01)  # operational
        self._hb_seen = time.monotonic()
        self.heartbeat()  # the device's consumer counts from here (and the other axes' on the bus)

    def _map_pdos(self) -> None:  # noqa: C901 - one pass over the mapping, in order
        """Set the driver's PDO mapping (``configure_pdo``) or take the device's, read it back,
        find the objects in it and precompile the packing.

        With ``configure_pdo = true`` the driver's own mapping is written by SDO (RPDO1 =
        control word + set-point; TPDO1 = status word + actual position; TPDO2 = the force, or
        the force at the end of TPDO1 when the device has no TPDO2), unless the EDS has the
        mapping objects read-only (a fixed mapping); a device that refuses a write with an SDO
        abort keeps its own mapping (the COB-ID of the PDO being written is restored). Either
        way the mapping is then **read back from the device** (0x1400…, 0x1600…, 0x1800…,
        0x1A00… by SDO): what the device holds is what the bridge packs and unpacks. The
        control word and the set-point must be in RPDOs, the status word and the actual
        position in TPDOs; the force comes from whichever TPDO carries one of the force objects
        (``force_object``), else it is NaN. What is missing is refused in one line.
        """
        node = self.node
        assert node is not None
        fixed = ""
        if self.configure_pdo:
            fixed = self._fixed_in_eds() or self._write_mapping()
            if fixed:
                log.warning(
                    "canopen: node %d keeps its own PDO mapping (%s): the bridge uses it",
                    self.node_id, fixed,
                )  # fmt: skip
        maps = {"RPDO": dict(node.rpdo.map), "TPDO": dict(node.tpdo.map)}
        for kind, pdos in maps.items():
            for no, pdo in list(pdos.items()):
                try:
                    pdo.read()  # the device's mapping, by SDO
                except SdoAbortedError as exc:  # listed in the EDS, not in the device
                    log.info("canopen: node %d: %s%d not read: %s", self.node_id, kind, no, exc)
                    del pdos[no]
        p = self.profile
        where = {
            "control": self._locate(maps["RPDO"], p.control),
            "setpoint": self._locate(maps["RPDO"], p.setpoint),
            "status": self._locate(maps["TPDO"], p.status),
            "actual": self._locate(maps["TPDO"], p.actual),
        }
        names = {"control": "control word", "setpoint": p.setpoint_name,
                 "status": "status word", "actual": "actual position"}  # fmt: skip
        for key, at in where.items():
            if at is None:
                kind = "RPDO" if key in ("control", "setpoint") else "TPDO"
                obj = getattr(p, key)
                held = "; ".join(
                    f"{kind}{no} maps {self._describe(m)}"
                    for no, m in sorted(maps[kind].items()) if m.enabled and len(m.map)
                ) or f"no {kind} is enabled"  # fmt: skip
                raise InputError(
                    f"canopen: node {self.node_id}: no {kind} carries the {names[key]} "
                    f"0x{obj[0]:04X}:{obj[1]:02X} ({held}"
                    + (f"; the mapping is the device's own: {fixed}" if fixed else "")
                    + ")"
                )
        force_at = None
        for obj in self._force_candidates:
            force_at = self._locate(maps["TPDO"], obj)
            if force_at is not None:
                self.force_object = obj
                break
        else:
            if self._force_candidates:
                log.warning(
                    "canopen: node %d maps no force object (%s) in a TPDO: no force (NaN)",
                    self.node_id,
                    ", ".join(f"0x{i:04X}:{s:02X}" for i, s in self._force_candidates),
                )
            self.force_object = None
        if self.force_object is not None:
            self._force_scale_from_device()
        elif p.control_mode == "force":
            raise InputError(
                f"canopen: node {self.node_id} maps no measured force in a TPDO ("
                + ", ".join(f"0x{i:04X}:{s:02X}" for i, s in self._force_candidates)
                + "): a force-controlled channel tracks it"
            )
        # the PDOs used: sent on every SYNC (TPDO) and enabled, set so when the driver may
        used_r = sorted({where["control"][0], where["setpoint"][0]})
        used_t = sorted({where["status"][0], where["actual"][0]}
                        | ({force_at[0]} if force_at else set()))  # fmt: skip
        for kind, nos in (("RPDO", used_r), ("TPDO", used_t)):
            for no in nos:
                self._make_usable(kind, no, maps[kind][no], fixed)
        # each step packs the RPDOs and unpacks the TPDOs with one precompiled struct of their
        # mapped objects (Layout), checked here against the library's own encoding and
        # decoding of its maps
        rng = random.Random(0x1A0 + self.node_id)
        self._rpdo_out = []
        for no in used_r:
            pdo = maps["RPDO"][no]
            self._rpdo_out.append(self._rpdo_packer(no, pdo, rng))
        self._rpdo_msg, self._rpdo_map = self._rpdo_out[0][0], maps["RPDO"][used_r[0]]
        self._rpdo_data = self._rpdo_msg.data
        self._rpdo_id = self._rpdo_msg.arbitration_id
        self._tpdo_maps, self._tpdo_decode = {}, {}
        slots = {no: slot for slot, no in enumerate(used_t)}
        self._at = tuple(
            (slots[at[0]], at[1]) if at else None
            for at in (where["status"], where["actual"], force_at)
        )
        self._tpdo_ids = tuple(maps["TPDO"][no].cob_id for no in used_t)
        for no in used_t:
            pdo = maps["TPDO"][no]
            layout = Layout.of([v.od for v in pdo.map], f"TPDO{no}")
            layout.check(pdo, f"TPDO{no}", rng)
            unpack = layout.fmt.unpack
            self._tpdo_decode[pdo.cob_id] = (slots[no], layout.fmt.size, unpack)
            self._tpdo_maps[pdo.cob_id] = pdo
            if self._bus is not None:
                self._bus.tpdo[pdo.cob_id] = (self, pdo, slots[no], layout.fmt.size, unpack)
            pdo.add_callback(self._on_tpdo)
        self._n_tpdo = len(used_t)
        self._blank = (_MISSING,) * self._n_tpdo
        self._part = list(self._blank)
        self._have = 0
        self.mapping = {
            **{f"RPDO{no}": self._describe(maps["RPDO"][no]) for no in used_r},
            **{f"TPDO{no}": self._describe(maps["TPDO"][no]) for no in used_t},
        }
        log.info("canopen: node %d PDOs %s", self.node_id, self.mapping)

    @staticmethod
    def _describe(pdo: Any) -> str:
        objs = " + ".join(f"0x{v.index:04X}:{v.subindex:02X}" for v in pdo.map)
        return f"COB-ID 0x{pdo.cob_id:03X}: {objs}"

    @staticmethod
    def _locate(pdos: dict[int, Any], obj: tuple[int, int]) -> tuple[int, int] | None:
        """(PDO number, position in it) of ``obj``: an enabled PDO first, else a disabled one."""
        for no, pdo in sorted(pdos.items(), key=lambda kv: (not kv[1].enabled, kv[0])):
            for i, var in enumerate(pdo.map):
                if (var.index, var.subindex) == obj:
                    return no, i
        return None

    def _wanted(self) -> list[tuple[str, Any, int, list[ODVariable]]]:
        """The driver's own mapping: (name, the library's PDO map, COB-ID, objects)."""
        node = self.node
        assert node is not None
        r, t = node.rpdo.map, node.tpdo.map
        for kind, maps in (("RPDO1", r), ("TPDO1", t)):
            if 1 not in maps:
                com = 0x1400 if kind[0] == "R" else 0x1800
                raise InputError(
                    f"canopen: eds {self.eds!r} has no {kind} (0x{com:04X}): the driver cannot "
                    "map its PDOs (configure_pdo = false takes the device's)"
                )
        t1 = list(self._tpdo1_vars)
        out = [("RPDO1", r[1], self._rpdo_id, self._rpdo_vars)]
        if 2 in t:
            out += [("TPDO1", t[1], 0x180 + self.node_id, t1),
                    ("TPDO2", t[2], 0x280 + self.node_id, self._tpdo2_vars)]  # fmt: skip
        else:  # no TPDO2: the force at the end of TPDO1 when it fits
            if sum(len(v) for v in t1 + self._tpdo2_vars) <= 64:
                t1 += self._tpdo2_vars
            out.append(("TPDO1", t[1], 0x180 + self.node_id, t1))
        return out

    def _fixed_in_eds(self) -> str:
        """Why the EDS says the mapping cannot be written (its entries read-only), or ``""``."""
        for name, pdo, _, variables in self._wanted():
            od = pdo.map_array.od
            entries = [od[i] for i in range(len(variables) + 1) if i in od.subindices]
            if len(entries) < len(variables) + 1 or not all(e.writable for e in entries):
                return f"0x{od.index:04X} ({name} mapping) is read-only in the EDS"
        return ""

    def _write_mapping(self) -> str:
        """Write the driver's mapping by SDO; ``""``, or the refusal that stopped it (the PDO
        being written keeps its COB-ID)."""
        for name, pdo, cob, variables in self._wanted():
            orig: int | None = None
            try:
                orig = int(pdo.com_record[1].raw)
                pdo.clear()
                for var in variables:
                    pdo.add_variable(var.index, var.subindex)
                pdo.cob_id = cob
                pdo.trans_type = 1  # RPDO: applied at the next SYNC; TPDO: sent on every SYNC
                pdo.enabled = bool(variables)
                pdo.rtr_allowed = False
                pdo.save()
            except SdoAbortedError as exc:
                if orig is not None:
                    try:
                        pdo.com_record[1].raw = orig
                    except _SDO_ERRORS as again:
                        log.warning("canopen: node %d: %s COB-ID not restored: %s",
                                    self.node_id, name, again)  # fmt: skip
                return f"the device refused the {name} mapping by SDO: {exc}"
        return ""

    def _make_usable(self, kind: str, no: int, pdo: Any, fixed: str) -> None:
        """A PDO the bridge needs: enabled, and a TPDO sent on every SYNC (transmission type
        1); set so by SDO when ``configure_pdo``, else refused in one line."""
        ok_type = pdo.trans_type == 1 if kind == "TPDO" else (pdo.trans_type or 0) <= 240 or (
            pdo.trans_type >= 254)  # fmt: skip
        if pdo.enabled and ok_type:
            return
        what = (f"{kind}{no} of node {self.node_id} (COB-ID 0x{pdo.cob_id:03X}, transmission "
                f"type {pdo.trans_type}{', disabled' if not pdo.enabled else ''})")  # fmt: skip
        if not self.configure_pdo:
            raise InputError(
                f"canopen: {what} is not usable: the bridge needs it enabled"
                + (" and sent on every SYNC (type 1)" if kind == "TPDO" else "")
                + " (configure_pdo = true lets the driver set it)"
            )
        try:
            if not ok_type:
                pdo.com_record[2].raw = 1
                pdo.trans_type = 1
            if not pdo.enabled:
                pdo.com_record[1].raw = pdo.cob_id | (0 if pdo.rtr_allowed else 1 << 30)
                pdo.enabled = True
                pdo.subscribe()
        except SdoAbortedError as exc:
            raise InputError(
                f"canopen: {what}: setting it to enabled, type 1 failed: {exc}"
            ) from None

    def _rpdo_packer(self, no: int, pdo: Any, rng: random.Random) -> tuple[Frame, Any]:
        """The frame of RPDO ``no`` and ``pack(word, counts)`` filling it: the control word and
        the set-point where the device maps them, any other mapped object with the value read
        from the device at start-up (so it holds)."""
        layout = Layout.of([v.od for v in pdo.map], f"RPDO{no}")
        layout.check(pdo, f"RPDO{no}", rng)
        msg = Frame.blank(pdo.cob_id, layout.fmt.size)
        data, pack_into = msg.data, layout.fmt.pack_into
        keys = [(v.index, v.subindex) for v in pdo.map]
        p = self.profile
        if keys == [p.control, p.setpoint]:
            return msg, lambda w, c: pack_into(data, 0, w, c)
        values: list[Any] = []
        for index, sub in keys:
            if (index, sub) in (p.control, p.setpoint) or index < 0x1000:  # dummy entries: 0
                values.append(0)
            else:
                values.append(self._sdo_read(index, sub))
        i_w = keys.index(p.control) if p.control in keys else None
        i_c = keys.index(p.setpoint) if p.setpoint in keys else None

        def pack(w: int, c: int) -> None:
            if i_w is not None:
                values[i_w] = w
            if i_c is not None:
                values[i_c] = c
            pack_into(data, 0, *values)

        return msg, pack

    def _force_scale_from_device(self) -> None:
        """The force scale: ``newtons_per_count`` as given (0.01), or for the torque actual
        0x6077 (per mille of the rated torque) the rated torque 0x6076 read by SDO (mN·m; a
        linear motor's rated force in mN) × ``force_per_torque`` (N per N·m) / 10⁶."""
        assert self.force_object is not None
        var = _variable(self.od, self.force_object, self.eds, "force_object")
        self._force_nan = _S32[0] if var.data_type == INTEGER32 else None
        if self.force_object != TORQUE_ACTUAL or self._newtons_given is not None:
            return
        if RATED_TORQUE[0] not in self.od:
            raise InputError(
                f"canopen: node {self.node_id} maps the torque actual 0x6077 but its EDS has no "
                "0x6076 (rated torque) to scale it: give driver.connection.newtons_per_count"
            )
        rated = self._sdo_read(*RATED_TORQUE)
        if rated <= 0:
            raise InputError(
                f"canopen: node {self.node_id}: rated torque 0x6076 is {rated}: the torque "
                "actual 0x6077 cannot be scaled; give driver.connection.newtons_per_count"
            )
        self.newtons_per_count = rated / 1e6 * self.force_per_torque
        log.info(
            "canopen: node %d force from the torque actual 0x6077: %g N per per-mille "
            "(0x6076 = %d, force_per_torque %g)",
            self.node_id, self.newtons_per_count, rated, self.force_per_torque,
        )  # fmt: skip

    # ------------------------------------------------------------------------------------------
    # callbacks (the canopen library's notifier thread)
    def _on_tpdo(self, pdo_map: Any) -> None:
        """A TPDO arrived into the library's PDO map (``PdoMap.on_message`` of the notifier
        thread, or a test): its values to :meth:`_tpdo_in`."""
        slot, size, unpack = self._tpdo_decode[pdo_map.cob_id]
        data = pdo_map.data
        self._tpdo_in(slot, unpack(data) if len(data) == size else None)

    def _tpdo_in(self, slot: int, values: tuple[int, ...] | None) -> None:
        """The values of TPDO ``slot`` (0: TPDO1, 1: TPDO2; ``None`` when its length was wrong),
        unpacked by the layout checked against the library's decoding (:meth:`Layout.check`),
        are filed for the step of the last SYNC; the set complete, its feedback is queued."""
        with self._lock:
            step = self._step
            if step == self._delivered_sync:
                self.stats.duplicates += 1
                if self._latched and not self._estop_seen and values is not None:
                    self._note_estop(slot, values)
                return
            part = self._part
            if part[slot] is _MISSING:
                self._have += 1
            part[slot] = values
            if self._have < self._n_tpdo:
                return
            parts = tuple(part)
            part[:] = self._blank
            self._have = 0
            self._delivered_sync = step
        fb = self._decode(step, parts)
        if fb is not None:
            self._q.append(fb)
            bus = self._bus
            if bus is None or not bus.reading:  # a thread may wait for it
                self._wake.set()

    def _note_estop(self, slot: int, values: tuple[int, ...]) -> None:
        """After the e-stop: a TPDO of a step already delivered (the e-stop's own SYNC is sent
        for the last step) still tells whether the device reports the e-stop state."""
        at = self._at[0]
        if at is None or at[0] != slot:
            return
        state = self.profile.state(values[at[1]])
        if self.profile.flags(state, True) & _ESTOP:
            self._estop_seen = True

    def _decode(self, step: int, parts: tuple[Any, ...]) -> Feedback | None:
        """The feedback of one SYNC's TPDO values (``parts``: one tuple per TPDO used, in the
        order of :attr:`_at`'s slots; ``None`` for a TPDO of the wrong length)."""
        if None in parts:
            self.stats.count_malformed("bad_length")
            return None
        (s_sw, i_sw), (s_pos, i_pos), at_f = self._at  # type: ignore[misc]
        sw = parts[s_sw][i_sw]
        pos = parts[s_pos][i_pos]
        force = math.nan
        if at_f is not None:
            fc = parts[at_f[0]][at_f[1]]
            force = math.nan if fc == self._force_nan else fc * self.newtons_per_count
        state = self._states.get(sw)
        if state is None:  # the FSA state of a status word, looked up once
            state = self._states[sw] = self.profile.state(sw)
        self._state = state
        key = (state, self._latched)
        status = self._flags.get(key)
        if status is None:
            status = self._flags[key] = self.profile.flags(state, self._latched)
        if self._latched and status & _ESTOP:
            self._estop_seen = True  # the device reports the e-stop state (_settle_estop)
        code = self._emcy_code
        if code:
            status |= _FAULT | (_WATCHDOG if code == EMCY_HEARTBEAT else 0)
        disp = math.nan if pos == _S32[0] else pos / self.counts_per_m
        return Feedback(step, disp, force, status)

    def _on_emcy(self, entry: Any) -> None:
        code = int(entry.code)
        text = f"0x{code:04X} {entry.get_desc()}".strip()
        self.stats.emcy.append(text)
        if code & 0xFF00 == 0:  # error reset / no error
            log.info("canopen: node %d EMCY %s (error reset)", self.node_id, text)
            return
        log.warning("canopen: node %d EMCY %s", self.node_id, text)
        if not self._emcy_code:
            self._emcy_code, self._emcy_text = code, text

    def _on_heartbeat(self, state: int) -> None:
        self._hb_seen = time.monotonic()

    def fault_text(self) -> str:
        """The device's latest fault as one phrase (EMCY code, FSA state), or ``""``."""
        parts = []
        if self._emcy_code:
            parts.append(f"EMCY {self._emcy_text}")
        if self.profile.is_fault(self._state) or self.profile.device_latched(self._state):
            parts.append(f"CiA {self.profile.number} state {self._state}")
        return f"canopen node {self.node_id}: {', '.join(parts)}" if parts else ""

    # ------------------------------------------------------------------------------------------
    # per step
    def _rpdo(self, step: int, word: int, counts: int) -> None:
        """Write the RPDO of ``step``; the bus's next SYNC applies it (:meth:`_synced`)."""
        bus = self._bus
        if bus is None:
            self.stats.send_errors += 1
            return
        # the mapped objects (control word, set-point) packed by the precompiled layout that
        # _map_pdos checked against the library's encoding of its RPDO map (Layout.check)
        for msg, pack in self._rpdo_out:
            pack(word, counts)
            if not bus.send(msg):
                self.stats.send_errors += 1
                return
        self._awaiting = step
        for drv in bus.axes.values():  # the SYNC once every axis on the bus has its RPDO out
            if drv._awaiting is None:
                return
        bus.sync()

    def _synced(self) -> None:
        """The bus sent the SYNC after this axis's RPDO: the TPDOs that follow are its step's."""
        with self._lock:
            self._step = self._awaiting  # type: ignore[assignment]
            self._part[:] = self._blank
            self._have = 0
        self._awaiting = None
        self.stats.syncs += 1

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        if self.profile.control_mode == "force":
            counts = self._torque_counts(seq, displacement, enable)
        else:
            counts = self._position_counts(seq, displacement, enable)
        if enable:
            self._first_enable = False
        self._send_counts(seq, counts, enable)

    def _torque_counts(self, seq: int, force: float, enable: bool) -> int:
        """Force mode: the target torque (per mille of the rated torque) of ``force`` (N);
        the first enabled one within 1 % of the rated force of the force read at arming."""
        per = self._torque_newtons
        if not per > 0:  # not opened: nothing is scaled yet
            raise InputError(f"canopen: node {self.node_id}: force command before start-up")
        counts = round(force / per)
        if not -32768 < counts <= 32767:
            raise InputError(
                f"command force {force} N for step {seq} is out of the INTEGER16 range of the "
                f"{self.profile.setpoint_name} at {per:g} N per count (0x6076, force_per_torque)"
            )
        if enable and self._first_enable and self._force_at_arm is not None:
            gap = abs(force - self._force_at_arm)
            if gap > 10 * per:
                raise InputError(
                    f"canopen: the first force set-point {force:.6g} N is {gap:.6g} N from the "
                    f"force {self._force_at_arm:.6g} N read at arming (more than 1 % of the "
                    "rated force): the axis would jump"
                )
        return counts

    def _position_counts(self, seq: int, displacement: float, enable: bool) -> int:
        counts = round(displacement * self.counts_per_m)
        if not _S32[0] < counts <= _S32[1]:
            raise InputError(
                f"command displacement {displacement} m for step {seq} is out of the INTEGER32 "
                f"range at {self.counts_per_m:g} counts/m"
            )
        if enable and self._first_enable and self._actual_at_arm is not None:
            gap = abs(displacement - self._actual_at_arm)
            if gap > self.start_tolerance:
                raise InputError(
                    f"canopen: the first set-point {displacement:.6g} m is {gap:.6g} m from the "
                    f"actual position {self._actual_at_arm:.6g} m read at arming (start_tolerance "
                    f"{self.start_tolerance:g} m): the axis would jump"
                )
        return counts

    def _send_counts(self, seq: int, counts: int, enable: bool) -> None:
        if self._latched and not self._estop_seen and enable:
            self._settle_estop(ESTOP_SETTLE)
        if not enable and self._latched:
            self._latched = False  # acknowledged: the word below releases the device
            # 402: disable voltage, the acknowledgement of QUICK STOP ACTIVE (transition 12),
            # whatever state the last answer reported: on a link whose answers lag, that may be
            # the state before the quick stop (and from any other state it disables too)
            key = ("QUICK STOP ACTIVE" if self.profile.number == 402 else self._state, False, False)
        else:
            key = (self._state, enable, self._latched)
        word = self._words.get(key)
        if word is None:  # the FSA's control word for (state, enable, latched), once
            word = self._words[key] = self.profile.cyclic_word(*key)
        bus = self._bus
        if bus is not None:
            if self._awaiting is not None:  # the last RPDO was never SYNCed (no receive)
                bus.sync()
            if bus.reading:
                bus.drain()  # frames of older steps are theirs, not this step's
        q = self._q
        while q:  # a feedback left from an older step: it will never be delivered
            q.popleft()
            self.stats.late += 1
        self._last_counts = counts
        self._rpdo(seq, word, counts)
        now = time.monotonic()
        if self.heartbeat_period and now - self._hb_last_sent >= self.heartbeat_period:
            self.heartbeat()

    def _recv_internal(self, deadline: float) -> Feedback | None:
        """The TPDO set of the last SYNC, decoded by the library's dispatch (``_on_tpdo``).

        Frames are read from the bus in this thread and handed to ``Network.notify`` (virtual
        and SocketCAN buses; other interfaces are read by the library's notifier thread and
        waited for on :attr:`_wake`). Raises :class:`LinkDown` when the controller's heartbeat
        has stopped for ``controller_heartbeat_timeout`` (counted ``heartbeat_lost``).
        """
        bus = self._bus
        if bus is None:
            raise LinkDown(f"canopen node {self.node_id}: closed")
        if self._awaiting is not None:  # the step's SYNC: after every axis's RPDO on the bus
            if not bus.sync():
                self.stats.send_errors += 1
        q = self._q
        if q:
            return q.popleft()
        direct = bus.reading
        if direct:
            bus.drain()  # what already arrived, heartbeats included
            if q:
                return q.popleft()
        if self.controller_heartbeat and self._hb_seen is not None:
            if time.monotonic() - self._hb_seen > self.controller_heartbeat_timeout:
                self.stats.heartbeat_lost += 1
                raise LinkDown(f"canopen node {self.node_id}: controller heartbeat lost")
        remaining = deadline - _perf()
        if remaining <= 0.0:
            return None
        if direct:
            if bus.pump(remaining):
                bus.drain()  # the rest of the TPDO set, when it came together
        else:
            if bus.gone is not None:
                raise LinkDown(f"canopen node {self.node_id}: bus reader stopped: {bus.gone}")
            wake = self._wake
            wake.clear()
            if not q:
                wake.wait(remaining)
        return q.popleft() if q else None

    def estop(self) -> None:
        self.stats.estops += 1
        self._latched = True
        self._estop_seen = False
        step = max(self._last_sent, 0)
        self._rpdo(step, self.profile.estop_word(), self._last_counts)
        bus = self._bus
        if bus is not None:
            if self._awaiting is not None:  # at once: a synchronous RPDO acts at the next SYNC
                bus.sync()
            self.heartbeat()
            # the loop stops stepping: the heartbeat goes on until the nodes are closed
            bus.hold_heartbeat(self._hb_msg, self.heartbeat_period or 0.1)

    def _settle_estop(self, limit: float) -> None:
        """After the e-stop, before the next command (the loop's confirmation poll): wait up to
        ``limit`` for the device to report the e-stop state (402 QUICK STOP ACTIVE, 408 HOLD
        after the e-stop), then drop what came before it. TPDOs carry no step: on a link whose
        answers lag a few SYNCs behind (a serial line, a loaded adapter), the next answer may
        still be one the device sent before it applied the e-stop, and the poll would read
        that (OPERATION ENABLED) as "not confirmed"."""
        bus = self._bus
        end = _perf() + limit
        while bus is not None and not self._estop_seen:
            remaining = end - _perf()
            if remaining <= 0.0:
                break
            if bus.reading:
                if bus.pump(min(remaining, 0.01)):
                    bus.drain()
            else:
                self._wake.clear()
                if not self._estop_seen:
                    self._wake.wait(min(remaining, 0.01))
        if self._estop_seen:
            self._q.clear()
        else:
            log.warning(
                "canopen: node %d did not report the e-stop state within %.0f ms (state %s)",
                self.node_id, limit * 1e3, self._state,
            )  # fmt: skip

    def heartbeat(self) -> None:
        self._hb_last_sent = time.monotonic()
        bus = self._bus
        if bus is None or not bus.heartbeat(self._hb_msg):
            self.stats.send_errors += 1

    def _error_field(self) -> int:
        """The newest error of the device's pre-defined error field (0x1003:1, CiA 301; its
        low 16 bits, the EMCY error code), 0 when the EDS has none or none is recorded."""
        assert self.node is not None
        if 0x1003 not in self.node.object_dictionary:
            return 0
        try:
            if not self._sdo_read(0x1003, 0):
                return 0
            return self._sdo_read(0x1003, 1) & 0xFFFF
        except InputError as exc:
            log.info("canopen: node %d: no error field: %s", self.node_id, exc)
            return 0

    def arm(self, timeout: float, receive: Any = None) -> Feedback | None:
        """Reset a fault and bring the device to holding by SDO (see the module docstring).

        Returns the device's state before arming (status word, position and force read by
        SDO), or ``None`` when it does not answer within ``timeout``. A fault of the device's
        heartbeat consumer (EMCY 0x8130, seen by this bridge or read from the pre-defined error
        field 0x1003 where the EDS has it: the bridge before this one stopped) is reported as
        the controller's latched watchdog (``ESTOP_ACTIVE | WATCHDOG``) that arming
        acknowledges, as every controller's; any other fault stays ``FAULT`` (the loop refuses
        to start on it).
        """
        p = self.profile
        if self._bus is not None:
            self._bus.release_heartbeat()  # a new run: the loop's steps produce it
        self._listen(True)
        try:
            sw = self._sdo_read(*p.status)
            before = self._state = p.state(sw)
            pos = self._sdo_read(*p.actual) / self.counts_per_m
            force = math.nan
            if self.force_object is not None:
                fc = self._sdo_read(*self.force_object)
                force = math.nan if fc == self._force_nan else fc * self.newtons_per_count
            flags = p.flags(before, self._latched)
            code = self._emcy_code or (self._error_field() if flags & _FAULT else 0)
            if code == EMCY_HEARTBEAT:  # the device's consumer latched: a bridge that stopped
                flags = (flags & ~_FAULT) | _ESTOP | _WATCHDOG
            elif code:
                flags |= _FAULT
                desc = EmcyError(code, 0, b"", 0.0).get_desc()
                log.warning("canopen: node %d is in %s with error 0x%04X %s", self.node_id,
                            before, code, desc)  # fmt: skip
            deadline = time.monotonic() + max(timeout, 0.5)
            for word in p.arm_words(before):
                self._sdo_write(p.control[0], p.control[1], word)
            want = "SWITCHED ON" if p.number == 402 else "HOLD"
            while True:
                self._state = p.state(self._sdo_read(*p.status))
                if self._state == want:
                    break
                if time.monotonic() > deadline:
                    log.warning(
                        "canopen: node %d did not reach %s at arming (state %s)",
                        self.node_id, want, self._state,
                    )  # fmt: skip
                    break
                time.sleep(0.005)
            self._actual_at_arm = self._sdo_read(*p.actual) / self.counts_per_m
            if p.control_mode == "force" and self.force_object is not None:
                fc = self._sdo_read(*self.force_object)
                self._force_at_arm = None if fc == self._force_nan else fc * self.newtons_per_count
        except InputError as exc:
            log.warning("canopen: arming node %d failed: %s", self.node_id, exc)
            return None
        finally:
            self._listen(False)
        self._latched = False
        self._emcy_code, self._emcy_text = 0, ""
        self._first_enable = True
        self._last_counts = round(self._actual_at_arm * self.counts_per_m)
        if p.control_mode == "force":  # the held set-point: the force read at arming
            f0 = self._force_at_arm
            self._last_counts = round(f0 / self._torque_newtons) if f0 is not None else 0
        self._last_sent = -1
        self._last_delivered = -1
        with self._lock:
            self._step = -1
            self._delivered_sync = -2
            self._part[:] = self._blank
            self._have = 0
        self._awaiting = None
        self._q.clear()
        self.heartbeat()  # the device's heartbeat consumer counts from here
        return Feedback(0, pos, force, flags)

    # ------------------------------------------------------------------------------------------
    # end
    def close(self) -> None:
        if not self._opened:
            return
        p = self.profile
        self._listen(True)
        try:
            if self.node is not None:
                if not self._latched:
                    state = p.state(self._sdo_read(*p.status))
                    for word in p.disable_words(state):
                        self._sdo_write(p.control[0], p.control[1], word)
                    self._state = p.state(self._sdo_read(*p.status))
                if self._consumer_set:  # the bridge's heartbeat stops: its consumer too
                    self._sdo_write(0x1016, 1, 0)
                    self._consumer_set = False
                self.node.nmt.send_command(0x02)  # NMT stop
        except (InputError, *_BUS_ERRORS, RuntimeError) as exc:
            log.warning("canopen: handing node %d back disabled failed: %s", self.node_id, exc)
        self._shutdown_network()

    def _shutdown_network(self) -> None:
        bus, self._bus = self._bus, None
        net, self.network = self.network, None
        node, self.node = self.node, None
        self._opened = False
        self._awaiting = None
        if (
            net is not None
            and node is not None
            and bus is not None
            and bus.axes.keys() - {self.node_id}
        ):  # other axes stay on the network: this node leaves its dispatch
            for pdo in node.tpdo.map.values():
                for cb in [
                    cb for cb in net.subscribers.get(pdo.cob_id, ()) if cb == pdo.on_message
                ]:
                    net.unsubscribe(pdo.cob_id, cb)
            node.remove_network()
            net.nodes.pop(self.node_id, None)
        if bus is not None:
            bus.release(self)


# ---------------------------------------------------------------------------------------------
# link budget
def step_frames(connection: dict[str, Any] | None = None) -> dict[str, int]:
    """Data bytes of the frames of one axis per step, and of the SYNC (shared by the bus).

    RPDO1 (control word + set-point), TPDO1 (status word + actual position), TPDO2 (force, absent
    when ``force_object = ""``) and the SYNC without a counter (0 bytes); heartbeats are 1 byte.
    With an EDS whose PDO mapping is fixed (its mapping objects read-only, the mapping in their
    defaults) the frames are those of that mapping: the RPDO with the control word, the TPDO
    with the status word ("tpdo1") and any other TPDO with the position or the force ("tpdo2").
    """
    c = dict(connection or {})
    fixed = _fixed_eds_frames(c)
    if fixed is not None:
        return {**fixed, "sync": 0, "heartbeat": 1}
    f = c.get("force_object", "0x2100")
    return {"rpdo": 6, "tpdo1": 6, "tpdo2": _force_bytes(c) if str(f).strip() else 0, "sync": 0,
            "heartbeat": 1}  # fmt: skip


def _force_bytes(c: dict[str, Any]) -> int:
    """Bytes of the force object in the EDS (4, an INTEGER32, when it cannot be told)."""
    eds, f = c.get("eds"), c.get("force_object")
    if f is None or not isinstance(eds, str) or not os.path.isfile(eds):
        return 4
    try:
        od = canopen.import_od(eds, int(c.get("node_id", 1)))
        return len(_variable(od, parse_object(f, "force_object"), eds, "force_object")) // 8
    except Exception:  # refused by the driver with its own message
        return 4


def _fixed_eds_frames(c: dict[str, Any]) -> dict[str, int] | None:
    """Data bytes of the PDOs of a fixed mapping read from the EDS (:func:`step_frames`), or
    None (no EDS, a mapping the driver may write, or one that does not carry the profile's
    objects: the driver's own mapping is counted)."""
    eds = c.get("eds")
    profile = PROFILES.get(str(c.get("device_profile", "cia402")))
    if not isinstance(eds, str) or profile is None or not os.path.isfile(eds):
        return None
    try:
        od = canopen.import_od(eds, int(c.get("node_id", 1)))
        maps: dict[str, list[list[tuple[int, int, int]]]] = {"R": [], "T": []}
        for kind, base in (("R", 0x1600), ("T", 0x1A00)):
            for no in range(512):
                rec = od.get(base + no)
                if rec is None:
                    continue
                if not isinstance(rec, ODRecord | ODArray) or any(
                    rec[i].writable for i in rec.subindices
                ):
                    return None
                n = int(rec[0].default or 0)
                entries = [int(rec[i].default or 0) for i in range(1, n + 1)]
                maps[kind].append([(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in entries])
    except Exception:  # an EDS the driver will refuse with its own message
        return None
    f = c.get("force_object")
    forces = [(0x2100, 0), TORQUE_ACTUAL] if f is None else []
    if f is not None and str(f).strip():
        try:
            forces = [parse_object(f, "force_object")]
        except InputError:
            return None

    def size(objs: list[tuple[int, int, int]]) -> int:
        return sum(bits for _, _, bits in objs) // 8

    def carrying(kind: str, obj: tuple[int, int]) -> list[tuple[int, int, int]] | None:
        return next((m for m in maps[kind] if any((i, s) == obj for i, s, _ in m)), None)

    rpdo, tpdo1 = carrying("R", profile.control), carrying("T", profile.status)
    if rpdo is None or tpdo1 is None:
        return None
    others = [carrying("T", profile.actual), *(carrying("T", o) for o in forces)]
    extra = {id(m): m for m in others if m is not None and m is not tpdo1}
    return {"rpdo": size(rpdo), "tpdo1": size(tpdo1),
            "tpdo2": sum(size(m) for m in extra.values())}  # fmt: skip


def link_load(connection: dict[str, Any], channels: int, fs: float, *, heartbeat_hz: float = 0.0):
    """The CANopen link's load (:class:`rths_hil.linkbudget.LinkLoad`) of ``channels`` axes.

    Per step: one SYNC for the bus (shared by its axes, :class:`CANopenBus`) plus, per axis,
    RPDO1, TPDO1 and TPDO2; per second the bridge's heartbeat, one per bus (``heartbeat_hz``, at
    least ``1/heartbeat_period``), and each device's (``1/controller_heartbeat``). Frame bits
    with worst-case stuffing (:func:`rths_hil.linkbudget.can_frame_bits`).
    """
    from rths_hil.linkbudget import LinkLoad, can_frame_bits, link_key

    c = dict(connection or {})
    for key in ("heartbeat_period", "controller_heartbeat"):  # as the driver takes them
        if key in c:
            v = _quantity(key, c[key], "s")
            if isinstance(v, bool) or not isinstance(v, int | float) or not v >= 0:
                raise InputError(f"canopen: {key} must be a number ≥ 0 (s), got {c[key]!r}")
            c[key] = v
    bitrate = c.get("bitrate")
    _check_bitrate(bitrate)
    n = step_frames(c)
    per_axis = sum(can_frame_bits(n[k]) for k in ("rpdo", "tpdo1", "tpdo2") if n[k] or k != "tpdo2")
    b_sync = can_frame_bits(0)
    hb_bridge = max(heartbeat_hz, 1.0 / c["heartbeat_period"] if c.get("heartbeat_period") else 0.0)
    ctrl = c.get("controller_heartbeat", 0.1)
    hb_dev = 1.0 / ctrl if ctrl else 0.0
    b_hb = can_frame_bits(1)
    name = link_key("canopen", c)
    per_second_bits = b_hb * (hb_bridge + channels * hb_dev)  # the bridge's: one per bus
    detail = (
        f"SYNC {b_sync} + {channels} × (RPDO {can_frame_bits(n['rpdo'])} + TPDO "
        f"{can_frame_bits(n['tpdo1'])}"
        + (f" + TPDO {can_frame_bits(n['tpdo2'])}" if n["tpdo2"] else "")
        + f") bits at {fs:g} Hz + heartbeats of {b_hb} bits: the bridge's at {hb_bridge:g} Hz, "
        f"{channels} × the device's at {hb_dev:g} Hz"
    )
    base = {"channels": channels, "fs": fs}
    interface = str(c.get("interface", "virtual"))
    bits_s = (b_sync + channels * per_axis) * fs + per_second_bits
    if bitrate is None:
        why = "virtual bus" if interface == "virtual" else "bit rate set by the interface"
        return LinkLoad(name, None, f"{why}; {detail} = {bits_s:.0f} bit/s", kind="can", **base)
    rate = float(bitrate)
    return LinkLoad(
        name,
        bits_s / rate,
        f"{detail}, worst-case stuffing, of {rate / 1e6:g} Mbit/s"
        + ("; virtual bus" if interface == "virtual" else ""),
        enforced=interface != "virtual",
        kind="can",
        rate=rate,
        per_channel=per_axis / rate,
        per_second=(b_sync * fs + per_second_bits) / rate,
        **base,
    )


def axes_that_fit(
    fs: float, bitrate: float = 1e6, limit: float = 0.8, connection: dict[str, Any] | None = None
) -> int:
    """How many axes one CANopen bus carries at ``fs`` below ``limit`` (SYNC, PDOs, heartbeats)."""
    n = 0
    while (
        link_load(
            {**(connection or {}), "bitrate": bitrate, "interface": "socketcan"}, n + 1, fs
        ).load
        <= limit
    ):
        n += 1
        if n > 127:
            break
    return n

"""The driver's base: its counters, its connection keys (:data:`CONNECTION_KEYS`) and bringing the
device up by SDO: the wire mode (CiA 402 cyclic synchronous position or torque), the SDO reads
and writes, and the start-up checks and writes before NMT operational (the base of
:class:`~rths_hil.drivers.canopen.CANopenDriver`).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import canopen
from canopen.objectdictionary import ODVariable

from rths_hil.errors import InputError
from rths_hil.keys import REQUIRED, Key, seconds

from ..base import Driver, DriverStats, Feedback
from ..can.codec import Frame
from .network import CANopenBus
from .od import (
    _MISSING,
    _S32,
    _SDO_ERRORS,
    BRIDGE_NODE_ID,
    FORCE_OBJECT,
    NMT_OPERATIONAL,
    RATED_TORQUE,
    TORQUE_ACTUAL,
    _identity,
    _variable,
    load_od,
    parse_object,
)
from .pdo import Layout
from .profiles import PROFILES, Profile

log = logging.getLogger(__package__)


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


#: The CANopen driver's connection settings (``driver.connection``,
#: :attr:`Driver.CONNECTION <rths_hil.drivers.base.Driver.CONNECTION>`).
CONNECTION_KEYS: dict[str, Key] = {
    "eds": Key(
        "str",
        REQUIRED,
        doc="the controller's EDS file, relative to the configuration file (with a twin: the "
        "twin's by default)",
    ),
    "node_id": Key("int", 1, lo=1, hi=127, doc="the controller's node id"),
    "device_profile": Key(
        "choice",
        "cia402",
        choices=tuple(PROFILES),
        doc="the device profile (CiA 402 drive or CiA 408 hydraulic valve), not driver.profile",
    ),
    "interface": Key("str", "virtual", doc="python-can interface"),
    "channel": Key("str|int", "rths-canopen", doc="bus channel"),
    "bitrate": Key("int", None, unit="bit/s", lo=1, doc="bit rate, for interfaces that set it"),
    "bus_options": Key("table", None, doc="further keyword arguments of python-can's can.Bus"),
    "counts_per_m": Key(
        "float",
        1e7,
        unit="counts/m",
        lo=0,
        lo_open=True,
        hi=1e12,
        doc="position scale, counts per m (above 1e12 INTEGER32 spans under ±2.1 mm)",
    ),
    "force_object": Key(
        "str|int",
        None,
        doc='object of the measured force ("0x6077", "0x2100:1"; "": none); none: 0x2100 '
        "where the EDS has it, else the torque actual 0x6077",
    ),
    "newtons_per_count": Key(
        "float",
        None,
        unit="N/count",
        lo=0,
        lo_open=True,
        doc="scale of the force object, N per count (none: 0.01; from 0x6076 for 0x6077)",
    ),
    "force_per_torque": Key(
        "float",
        1.0,
        unit="N/(N·m)",
        lo=0,
        lo_open=True,
        doc="N per N·m of the torque objects (1: a linear motor; a ball screw of lead L: 2π/L)",
    ),
    "bridge_node_id": Key(
        "int", BRIDGE_NODE_ID, lo=1, hi=127, doc="the bridge's node id (its heartbeat 0x700 + id)"
    ),
    "heartbeat_period": seconds(
        0.1, "the bridge's heartbeat producer period (0: only loop.heartbeat)"
    ),
    "controller_heartbeat": seconds(
        0.1, "device heartbeat period written to 0x1017 in ms (0: none)", hi=65.535
    ),
    "controller_heartbeat_timeout": seconds(
        1.0, "how long the bridge waits for the device's heartbeat"
    ),
    "device_watchdog": Key(
        "float",
        None,
        unit="s",
        lo=0,
        hi=65.535,
        doc="written in ms to 0x1016, the device's consumer of the bridge's heartbeat (none "
        "or 0: not written)",
    ),
    "start_tolerance": Key(
        "float", 1e-3, unit="m", lo=0, doc="largest first set-point − actual position at enabling"
    ),
    "sdo_timeout": seconds(0.5, "SDO response timeout (0: 0.5 s)"),
    "vendor_id": Key(
        "str|int", None, doc='identity 0x1018:1 to insist on (an integer or "0x0000A3C7")'
    ),
    "product_code": Key(
        "str|int", None, doc='identity 0x1018:2 to insist on (an integer or "0x0000A3C7")'
    ),
    "configure_pdo": Key(
        "bool",
        True,
        doc="write the driver's PDO mapping by SDO where the device lets it (false: take the "
        "device's as it is)",
    ),
}


class DeviceStartUp(Driver):
    """The connection keys and the device's start-up by SDO (the base of
    :class:`~rths_hil.drivers.canopen.CANopenDriver`)."""

    stats: CANopenStats
    CONNECTION: ClassVar[Mapping[str, Key]] = CONNECTION_KEYS

    def __init__(
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
        if device_profile not in PROFILES:  # (a driver built without check_connection)
            raise InputError(
                f"canopen: device_profile {device_profile!r} is not known (known: "
                f"{', '.join(PROFILES)})"
            )
        self.profile: Profile = PROFILES[device_profile]
        if node_id == bridge_node_id:
            raise InputError(f"canopen: node_id and bridge_node_id are both {node_id}")
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
        obj: Any  # an index, then an (index, sub-index)
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

    if TYPE_CHECKING:  # defined by the subclasses

        def _map_pdos(self) -> None: ...

        def _on_emcy(self, entry: Any) -> None: ...

        def _on_heartbeat(self, state: int) -> None: ...

        def heartbeat(self) -> None: ...

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

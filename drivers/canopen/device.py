"""Bringing the device up by SDO: the wire mode (CiA 402 cyclic synchronous position or
torque), the SDO reads and writes, and the start-up checks and writes before NMT operational
(a part of :class:`~rths_hil.drivers.canopen.CANopenDriver`).
"""

from __future__ import annotations

import logging
import time

from canopen.objectdictionary import ODVariable

from rths_hil.errors import InputError

from ..can.codec import Frame
from .od import (
    _SDO_ERRORS,
    RATED_TORQUE,
    _variable,
)
from .pdo import Layout
from .profiles import PROFILES

log = logging.getLogger(__package__)


class DeviceStartUp:
    """The device's start-up by SDO (a part of
    :class:`~rths_hil.drivers.canopen.CANopenDriver`)."""

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

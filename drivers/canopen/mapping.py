"""The driver's PDO mapping at start-up: :class:`PdoMapping` sets the driver's mapping or
takes the device's, reads it back by SDO, finds the objects in it and precompiles the packing
with :class:`~rths_hil.drivers.canopen.pdo.Layout` (a part of
:class:`~rths_hil.drivers.canopen.CANopenDriver`).
"""

from __future__ import annotations

import logging
import random
from typing import TYPE_CHECKING, Any

from canopen.objectdictionary import ODVariable
from canopen.objectdictionary.datatypes import INTEGER32
from canopen.sdo import SdoAbortedError

from rths_hil.errors import InputError

from ..can.codec import Frame
from .device import DeviceStartUp
from .od import (
    _MISSING,
    _S32,
    _SDO_ERRORS,
    RATED_TORQUE,
    TORQUE_ACTUAL,
    _variable,
)
from .pdo import Layout

log = logging.getLogger(__package__)


class PdoMapping(DeviceStartUp):
    """The driver's PDO mapping at start-up (a part of
    :class:`~rths_hil.drivers.canopen.CANopenDriver`)."""

    if TYPE_CHECKING:  # defined by the subclass

        def _on_tpdo(self, pdo_map: Any) -> None: ...

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
        assert node.rpdo.map is not None and node.tpdo.map is not None
        maps: dict[str, dict[int, Any]] = {"RPDO": dict(node.rpdo.map), "TPDO": dict(node.tpdo.map)}
        for kind, pdos in maps.items():
            for no, pdo in list(pdos.items()):
                try:
                    pdo.read()  # the device's mapping, by SDO
                except SdoAbortedError as exc:  # listed in the EDS, not in the device
                    log.info("canopen: node %d: %s%d not read: %s", self.node_id, kind, no, exc)
                    del pdos[no]
        p = self.profile
        where: dict[str, Any] = {
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
                self._bus.tpdo[pdo.cob_id] = (self, pdo, slots[no], layout.fmt.size, unpack)  # type: ignore[assignment]
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
        assert r is not None and t is not None
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

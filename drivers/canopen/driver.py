"""The CANopen driver: :class:`CANopenDriver` (the connection keys, open, the lockstep step over
RPDO + SYNC + TPDOs, the callbacks of the library, e-stop, arming, close) and its counters.
The protocol is described in the package docstring (:mod:`rths_hil.drivers.canopen`).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, ClassVar

import canopen
from canopen.emcy import EmcyError

from rths_hil.errors import InputError

from ..base import Feedback, LinkDown
from .mapping import PdoMapping
from .network import CANopenBus
from .od import (
    _BUS_ERRORS,
    _ESTOP,
    _FAULT,
    _MISSING,
    _S32,
    _WATCHDOG,
    EMCY_HEARTBEAT,
    ESTOP_SETTLE,
    _perf,
)

log = logging.getLogger(__package__)


class CANopenDriver(PdoMapping):
    """Lockstep actuator driver over CANopen (see :mod:`rths_hil.drivers.canopen`)."""

    name: ClassVar[str] = "canopen"
    #: the bus is read with the time left (virtual queue / SocketCAN) or waited for on an event
    #: the library's notifier thread sets
    honours_deadline: ClassVar[bool] = True
    # the axes on one bus read it for each other (each frame to its axis): a late receive is
    # counted, never moved to a reader thread (Driver.reader_fallback)
    reader_fallback: ClassVar[bool] = False
    #: the feedback carries the step of its SYNC (a TPDO set belongs to the SYNC before it)
    echoes_seq: ClassVar[bool] = True
    #: positions are INTEGER32 counts of ``counts_per_m``, checked in :meth:`_send_raw`
    command_lsb: ClassVar[float | None] = None
    #: force: CiA 402 cyclic synchronous torque (:meth:`set_control`); CiA 408 refuses it
    control_modes: ClassVar[tuple[str, ...]] = ("displacement", "force")

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
        """Reset a fault and bring the device to holding by SDO (see the package).

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
            for pdo in node.tpdo.map.values():  # type: ignore[union-attr]
                for cb in [
                    cb for cb in net.subscribers.get(pdo.cob_id, ()) if cb == pdo.on_message
                ]:
                    net.unsubscribe(pdo.cob_id, cb)
            node.remove_network()
            net.nodes.pop(self.node_id, None)
        if bus is not None:
            bus.release(self)

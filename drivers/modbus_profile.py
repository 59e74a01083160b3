"""Modbus TCP driver for a lab's own register map, declared in a profile (:mod:`.profile`).

Per step the driver writes the set-point and reads the measured values in the requests the map
allows: one Read/Write Multiple Registers (FC 23) when the set-point and every read role are
holding registers within one read block, else a Write Multiple Registers (FC 16) followed by
one read per table (FC 3 holding, FC 4 input, FC 1 coils, FC 2 discrete inputs), all
pipelined in one TCP write. A controller answers Modbus TCP requests with the request's
transaction id, so the step travels in it: ``tid = (seq mod 4096) · 16 + slot`` (slot 0 the
write or FC 23, 1… the reads, 13 the start-up check, 14 the heartbeat, 15 the actions), and a
feedback is delivered once every read of its step has come back. Actions (enable, disable,
acknowledge) are written when the bridge's enable flag changes; the e-stop action is written at
once.

Requests are built and responses decoded by pymodbus (``FramerSocket`` and its PDU classes);
values are converted by pymodbus's ``convert_to_registers`` / ``convert_from_registers``.
At :meth:`ModbusProfileDriver.open` every mapped read block and the set-point registers are
read once: a controller that refuses one (a Modbus exception, e.g. illegal data address) is
refused with one line naming the role.
"""

from __future__ import annotations

import os
import select
import socket
import time
from typing import Any, ClassVar

from pymodbus.framer import FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadDiscreteInputsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    ReadWriteMultipleRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

from rths_hil.errors import InputError

from .base import Driver, Feedback, LinkDown, extend_seq
from .profile import ModbusAction, ModbusProfile, load_profile, status_from_word

__all__ = ["ModbusProfileDriver"]

_READS = {
    "holding": ReadHoldingRegistersRequest,
    "input": ReadInputRegistersRequest,
    "coil": ReadCoilsRequest,
    "discrete": ReadDiscreteInputsRequest,
}
SLOT_CHECK = 13  # the start-up reads
SLOT_HEARTBEAT = 14
SLOT_ACTION = 15
_EXC = {1: "illegal function", 2: "illegal data address", 3: "illegal data value"}


class ModbusProfileDriver(Driver):
    """Lockstep driver for a Modbus TCP controller described by a profile.

    Parameters
    ----------
    profile : str
        Path of the profile file (``protocol = "modbus"``).
    transport : str
        ``tcp`` (a profile over RTU is not supported).
    host, port : str, int
        The controller's Modbus TCP server.
    device_id : int, optional
        Unit id; the profile's ``[modbus] unit`` by default.
    connect_timeout : float
        TCP connect and start-up check timeout (s).
    """

    name: ClassVar[str] = "modbus"
    honours_deadline: ClassVar[bool] = True  # select() with the time left
    command_lsb: ClassVar[float | None] = None  # the profile's point type checks the range

    def __init__(
        self,
        profile: str,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        device_id: int | None = None,
        connect_timeout: float = 1.0,
    ) -> None:
        super().__init__()
        prof = load_profile(profile)
        if not isinstance(prof, ModbusProfile):
            raise InputError(f"modbus driver: profile {profile} is not a Modbus profile")
        if transport != "tcp":
            raise InputError(
                f"modbus driver: a profile runs over Modbus TCP; transport {transport!r} is "
                "not supported with a profile"
            )
        self.profile = prof
        self.host, self.port = str(host), int(port)
        self.unit = prof.unit if device_id is None else int(device_id)
        self.connect_timeout = float(connect_timeout)
        self._framer = FramerSocket(DecodePDU(False))
        self._sock: socket.socket | None = None
        self._fd: int | None = None
        self._buf = b""
        self._enabled: bool | None = None
        self._hb = 0
        self._sp = prof.points["setpoint"]
        self._reads = prof.reads
        self._n_reads = 1 if prof.fc23 else len(prof.reads)
        self._parts: dict[int, Any] = {}
        self._read_frames: list[bytes] | None = None
        self._parts_seq = -1
        self._pos, self._force, self._status = (
            prof.points["position"],
            prof.points["force"],
            prof.points["status"],
        )
        self._masks = prof.masks

    # -- transport ------------------------------------------------------------------------------
    def open(self) -> None:
        if self._sock is not None:
            return
        try:
            sock = socket.create_connection((self.host, self.port), self.connect_timeout)
        except OSError as exc:
            raise InputError(
                f"modbus driver: cannot connect to {self.host}:{self.port}: {exc}"
            ) from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self._sock, self._fd, self._buf = sock, sock.fileno(), b""
        try:
            self._check_map()
        except InputError:
            self.close()
            raise

    def close(self) -> None:
        sock, self._sock = self._sock, None
        self._fd = None
        self._enabled = None
        if sock is not None:
            sock.close()

    def _frame(self, pdu: Any, tid: int) -> bytes:
        pdu.dev_id, pdu.transaction_id = self.unit, tid
        return self._framer.buildFrame(pdu)

    def _write(self, data: bytes) -> None:
        fd = self._fd
        if fd is None:
            self.stats.send_errors += 1
            return
        try:
            os.write(fd, data)
        except OSError:
            self.stats.send_errors += 1
            self.stats.disconnects += 1
            self.close()

    def _check_map(self) -> None:
        """Read every mapped block once; refuse a map the controller does not have."""
        prof = self.profile
        checks = [
            (b.table, b.address, b.count, ", ".join(p.role for p in b.points)) for b in prof.reads
        ]
        checks.append(("holding", self._sp.address, self._sp.count, "setpoint"))
        deadline = time.perf_counter() + self.connect_timeout
        for i, (table, address, count, roles) in enumerate(checks):
            self._write(
                self._frame(_READS[table](address=address, count=count), (i << 4) | SLOT_CHECK)
            )
            while True:
                pdu = self._next_pdu(deadline)
                if pdu is None:
                    raise InputError(
                        f"modbus driver: profile {prof.source}: no answer from unit {self.unit} "
                        f"at {self.host}:{self.port} to a read of {table} {address}–"
                        f"{address + count - 1} (roles.{roles})"
                    )
                tid, resp = pdu
                if tid != (i << 4) | SLOT_CHECK:
                    continue
                if resp.function_code & 0x80:
                    code = getattr(resp, "exception_code", 0)
                    raise InputError(
                        f"modbus driver: profile {prof.source}: roles.{roles}: the controller "
                        f"refuses a read of {table} {address}–{address + count - 1} (Modbus "
                        f"exception {code}: {_EXC.get(code, 'error')})"
                    )
                break

    def _next_pdu(self, deadline: float) -> tuple[int, Any] | None:
        """The next response off the connection before ``deadline`` (blocking helper)."""
        while True:
            got = self._parse_one()
            if got is not None:
                return got
            remaining = deadline - time.perf_counter()
            if remaining <= 0 or self._fd is None:
                return None
            if select.select((self._fd,), (), (), remaining)[0]:
                data = os.read(self._fd, 4096)
                if not data:
                    return None
                self._buf += data

    def _parse_one(self) -> tuple[int, Any] | None:
        buf = self._buf
        if len(buf) < 8:
            return None
        used, dev_id, tid, pdu_bytes = self._framer.decode(buf)
        if not used:
            if len(buf) > 512:
                self.stats.count_malformed("bad_header")
                self._buf = b""
            return None
        self._buf = buf[used:]
        if dev_id != self.unit or not pdu_bytes:
            self.stats.count_malformed("unknown_id")
            return (-1, None)
        if pdu_bytes[0] < 0x80 and self._is_echo(tid):
            return (-1, None)  # a write's echo: nothing to decode
        pdu = self._framer.decoder.decode(pdu_bytes)
        if pdu is None:
            self.stats.count_malformed("bad_frame")
            return (-1, None)
        return tid, pdu

    def _is_echo(self, tid: int) -> bool:
        slot = tid & 15
        return (
            slot == SLOT_ACTION or slot == SLOT_HEARTBEAT or (slot == 0 and not self.profile.fc23)
        )

    # -- commands -------------------------------------------------------------------------------
    def _action(self, action: ModbusAction | None) -> bytes:
        if action is None:
            return b""
        if action.table == "coil":
            pdu: Any = WriteSingleCoilRequest(address=action.address, bits=[bool(action.value)])
        else:
            pdu = WriteSingleRegisterRequest(address=action.address, registers=[action.value])
        return self._frame(pdu, SLOT_ACTION)

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        regs = self._sp.to_registers(displacement)  # InputError: out of the point's range
        acts = self.profile.actions
        out = b""
        if enable != self._enabled:
            if enable:
                out += self._action(acts.get("enable"))
            else:
                out += self._action(acts.get("disable")) + self._action(acts.get("acknowledge"))
            self._enabled = enable
        base = (seq & 0x0FFF) << 4
        sp = self._sp
        reads = self._read_frames
        if reads is None:  # built by pymodbus once; per step only the transaction id changes
            reads = self._read_frames = [
                self._frame(_READS[b.table](address=b.address, count=b.count), i)
                for i, b in enumerate(self._reads, start=1)
            ]
        if self.profile.fc23:
            b = self._reads[0]
            out += self._frame(
                ReadWriteMultipleRegistersRequest(
                    read_address=b.address,
                    read_count=b.count,
                    write_address=sp.address,
                    write_registers=regs,
                ),
                base,
            )
        else:
            out += self._frame(
                WriteMultipleRegistersRequest(address=sp.address, registers=regs), base
            )
            for i, frame in enumerate(reads, start=1):
                out += (base | i).to_bytes(2, "big") + frame[2:]
        self._write(out)

    def estop(self) -> None:
        self.stats.estops += 1
        self._write(self._action(self.profile.actions["estop"]))

    def heartbeat(self) -> None:
        hb = self.profile.heartbeat
        if hb is None:
            return
        self._hb = (self._hb + 1) & 0x7FFF
        pdu = WriteSingleRegisterRequest(address=hb.address, registers=hb.to_registers(self._hb))
        self._write(self._frame(pdu, SLOT_HEARTBEAT))

    # -- feedback -------------------------------------------------------------------------------
    def _take(self, tid: int, pdu: Any) -> Feedback | None:
        """File one response; the feedback when its step's last read came back."""
        if tid < 0:
            return None
        fc = pdu.function_code
        if fc & 0x80:
            self.stats.count_malformed("modbus_exception")
            return None
        slot = tid & 15
        if slot >= SLOT_CHECK or (slot == 0 and not self.profile.fc23):
            return None  # a write's echo
        seq12 = tid >> 4
        if seq12 != self._parts_seq:
            self._parts_seq = seq12
            self._parts = {}
        n = self._n_reads
        index = 0 if self.profile.fc23 else slot - 1
        if not 0 <= index < n:
            self.stats.count_malformed("bad_frame")
            return None
        block = self._reads[index]
        data = pdu.registers if block.table in ("holding", "input") else pdu.bits
        if len(data) < block.count:
            self.stats.count_malformed("bad_length")
            return None
        parts = self._parts
        for p in block.points:
            parts[p.role] = data[p.address - block.address : p.end - block.address]
        if len(parts) < 3:
            return None
        seq = extend_seq(seq12, self._last_sent, 12)
        try:
            word = self._status.raw_from_registers(parts["status"])
            fb = Feedback(
                seq,
                self._pos.from_registers(parts["position"]),
                self._force.from_registers(parts["force"]),
                status_from_word(word, self._masks),
            )
        except (ValueError, TypeError, IndexError):
            self.stats.count_malformed("bad_frame")
            return None
        self._parts = {}
        return fb

    def _recv_internal(self, deadline: float) -> Feedback | None:
        while True:
            got = self._parse_one()
            if got is None:
                break
            fb = self._take(*got)
            if fb is not None:
                return fb
        fd = self._fd
        if fd is None:
            raise LinkDown("modbus connection closed")
        remaining = deadline - time.perf_counter()
        try:
            ready = select.select((fd,), (), (), remaining if remaining > 0.0 else 0.0)[0]
            data = os.read(fd, 4096) if ready else b""
            if ready and not data:
                raise ConnectionResetError("peer closed the connection")
        except (OSError, ValueError):
            self.stats.disconnects += 1
            self.close()
            raise LinkDown("modbus connection lost") from None
        if data:
            self._buf += data
        return None

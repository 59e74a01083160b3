"""Modbus driver (TCP and RTU) for a lab's own register map, declared in a profile.

Per step the driver writes the set-point and reads the measured values in the requests the map
allows: one Read/Write Multiple Registers (FC 23) when the set-point and every read role are
holding registers within one read block, else a Write Multiple Registers (FC 16) followed by
one read per table (FC 3 holding, FC 4 input, FC 1 coils, FC 2 discrete inputs). Actions
(enable, disable, acknowledge) are written when the bridge's enable flag changes; the e-stop
action is written at once.

**Modbus TCP.** A controller answers Modbus TCP requests with the request's transaction id, so
the step travels in it: ``tid = (seq mod 4096) · 16 + slot`` (slot 0 the write or FC 23, 1…
the reads, 13 the start-up check, 14 the heartbeat, 15 the actions), and a feedback is
delivered once every read of its step has come back. With the profile's ``[modbus] pipeline``
(the default) the step's requests go out in ONE socket write and the responses are matched by
their transaction ids: the MBAP header's transaction identifier pairs a response with its
request, so several transactions may be outstanding on one connection (MODBUS Messaging on
TCP/IP Implementation Guide V1.0b, the MBAP header; docs/references.md). Without it, one
request at a time as on RTU (the next written when the previous one is answered), for a server
that serves one transaction at a time.

**Modbus RTU** (a serial line: ``device``, ``baudrate``, ``parity``, ``stopbits``). RTU is
half-duplex and carries no transaction id: the driver keeps the step's requests in a queue,
writes the first, and writes the next one when the answer to the previous one has come (an
answer whose function code is not the one of the request at the head of the queue answers an
older request: counted ``late``, dropped). The step of a response is the step of its request.
A frame is cut by the size pymodbus's PDU class computes from its header and checked by its CRC
(``FramerRTU``); garbage is dropped when the line falls idle. An e-stop goes out at once (as
the built-in RTU driver's, :mod:`.modbus`), ahead of the queue.

Requests are built by pymodbus (its request classes and framers; the request objects of the
step are built once and only their transaction id and registers change), responses decoded by
pymodbus's response classes; values are converted by pymodbus's ``convert_to_registers`` /
``convert_from_registers`` (points of one type next to each other in one call). At
:meth:`ModbusProfileDriver.open` every mapped read block and the set-point registers are read
once: a controller that refuses one (a Modbus exception, e.g. illegal data address) is
refused with one line naming the role.
"""

from __future__ import annotations

import os
import select
import socket
import time
from collections import deque
from typing import Any, ClassVar

import serial
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    ReadDiscreteInputsRequest,
    ReadDiscreteInputsResponse,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
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
#: Response classes of the read function codes (decoded in place, one object per code).
_RESPONSES = {
    3: ReadHoldingRegistersResponse,
    4: ReadInputRegistersResponse,
    1: ReadCoilsResponse,
    2: ReadDiscreteInputsResponse,
    23: ReadWriteMultipleRegistersResponse,
}
_convert = ModbusClientMixin.convert_from_registers
SLOT_CHECK = 13  # the start-up reads
SLOT_HEARTBEAT = 14
SLOT_ACTION = 15
_EXC = {1: "illegal function", 2: "illegal data address", 3: "illegal data value"}


def _groups(block: Any) -> list[tuple[int, int, Any, str, tuple[Any, ...]]]:
    """The points of a read block as runs of one type and word order next to each other:
    (offset in the block, registers, pymodbus DATATYPE, word order, points), so that each run
    is converted by one ``convert_from_registers`` call."""
    out: list[tuple[int, int, Any, str, tuple[Any, ...]]] = []
    for p in sorted(block.points, key=lambda q: q.address):
        if p.type == "bool" or p.byte_order != "big" or p.role == "status":
            out.append((p.address - block.address, p.count, None, p.word_order, (p,)))
            continue
        if out:
            off, n, dt, wo, pts = out[-1]
            if dt is p.dtype and wo == p.word_order and block.address + off + n == p.address:
                out[-1] = (off, n + p.count, dt, wo, (*pts, p))
                continue
        out.append((p.address - block.address, p.count, p.dtype, p.word_order, (p,)))
    return out


class ModbusProfileDriver(Driver):
    """Lockstep driver for a Modbus TCP or RTU controller described by a profile.

    Parameters
    ----------
    profile : str
        Path of the profile file (``protocol = "modbus"``).
    transport : str
        ``tcp`` or ``rtu``.
    host, port : str, int
        TCP: the controller's Modbus TCP server.
    device, baudrate, parity, stopbits : str, int, str, int
        RTU: the serial line (a device or pyserial URL) and its settings (8 data bits).
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
        device: str | None = None,
        baudrate: int = 115200,
        parity: str = "E",
        stopbits: int = 1,
        device_id: int | None = None,
        connect_timeout: float = 1.0,
        estop_timeout: float = 0.1,
    ) -> None:
        super().__init__()
        prof = load_profile(profile)
        if not isinstance(prof, ModbusProfile):
            raise InputError(f"modbus driver: profile {profile} is not a Modbus profile")
        if transport not in ("tcp", "rtu"):
            raise InputError(f"modbus driver: transport must be 'tcp' or 'rtu', got {transport!r}")
        if transport == "rtu" and not device:
            raise InputError("modbus driver: transport 'rtu' needs device= (serial port or URL)")
        self.profile = prof
        self.transport = transport
        self._rtu = transport == "rtu"
        #: one request on the wire at a time (RTU always; TCP when the profile says so)
        self._serial = self._rtu or not prof.pipeline
        self.host, self.port = str(host), int(port)
        self.device = device
        self.baudrate, self.parity, self.stopbits = int(baudrate), str(parity), int(stopbits)
        self.unit = prof.unit if device_id is None else int(device_id)
        self.connect_timeout = float(connect_timeout)
        self.estop_timeout = float(estop_timeout)
        self._framer: Any = (FramerRTU if self._rtu else FramerSocket)(DecodePDU(False))
        self._sock: socket.socket | None = None
        self._ser: Any = None
        self._fd: int | None = None
        self._buf = b""
        self._enabled: bool | None = None
        self._estop_sent = False
        self._hb = 0
        self._sp = prof.points["setpoint"]
        self._reads = prof.reads
        self._n_reads = 1 if prof.fc23 else len(prof.reads)
        self._groups = [_groups(b) for b in prof.reads]
        self._parts: dict[int, Any] = {}
        self._parts_seq = -1
        self._masks = prof.masks
        self._flags: dict[int, int] = {}
        self._status = prof.points["status"]
        self._responses = {fc: cls() for fc, cls in _RESPONSES.items()}
        self._read_frames: list[bytes] = []
        self._pending: deque[tuple[int, int, bytes]] = deque()  # RTU: (tid, fc, frame)
        # the step's write request, built once; per step its registers and id change
        sp = self._sp
        if prof.fc23:
            b = self._reads[0]
            self._step_pdu: Any = ReadWriteMultipleRegistersRequest(
                read_address=b.address,
                read_count=b.count,
                write_address=sp.address,
                write_registers=[0] * sp.count,
            )
        else:
            self._step_pdu = WriteMultipleRegistersRequest(
                address=sp.address, registers=[0] * sp.count
            )
        self._step_pdu.dev_id = self.unit

    # -- transport ------------------------------------------------------------------------------
    def open(self) -> None:
        if self._fd is not None:
            return
        if self._rtu:
            try:
                ser = serial.serial_for_url(
                    self.device, baudrate=self.baudrate, parity=self.parity,
                    stopbits=self.stopbits, bytesize=8, timeout=0,
                )  # fmt: skip
            except (serial.SerialException, OSError, ValueError) as exc:
                raise InputError(f"modbus driver: cannot open {self.device!r}: {exc}") from None
            if not hasattr(ser, "fd"):
                ser.close()
                raise InputError(f"modbus driver: RTU needs a serial device, got {self.device!r}")
            self._ser, self._fd = ser, ser.fd
        else:
            try:
                sock = socket.create_connection((self.host, self.port), self.connect_timeout)
            except OSError as exc:
                raise InputError(
                    f"modbus driver: cannot connect to {self.host}:{self.port}: {exc}"
                ) from None
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)
            self._sock, self._fd = sock, sock.fileno()
        self._buf = b""
        self._read_frames = [
            self._frame(_READS[b.table](address=b.address, count=b.count), i)
            for i, b in enumerate(self._reads, start=1)
        ]  # built by pymodbus once; per step only the transaction id changes (TCP)
        try:
            self._check_map()
        except InputError:
            self.close()
            raise

    def close(self) -> None:
        sock, self._sock = self._sock, None
        ser, self._ser = self._ser, None
        self._fd = None
        self._enabled = None
        self._pending.clear()
        if sock is not None:
            sock.close()
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException):  # pragma: no cover
                pass

    def _where(self) -> str:
        return str(self.device) if self._rtu else f"{self.host}:{self.port}"

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

    def _submit(self, requests: list[tuple[int, int, bytes]]) -> None:
        """Send ``(tid, function code, frame)`` requests: TCP pipelined all at once in one
        write; RTU (and TCP with ``pipeline = false``) one at a time (the next when the
        previous one is answered)."""
        if not requests:
            return
        if not self._serial:
            self._write(b"".join(r[2] for r in requests))
            return
        idle = not self._pending
        self._pending.extend(requests)
        if idle:
            self._write(self._pending[0][2])

    def _check_map(self) -> None:
        """Read every mapped block once; refuse a map the controller does not have."""
        prof = self.profile
        checks = [
            (b.table, b.address, b.count, ", ".join(p.role for p in b.points)) for b in prof.reads
        ]
        checks.append(("holding", self._sp.address, self._sp.count, "setpoint"))
        deadline = time.perf_counter() + self.connect_timeout
        for i, (table, address, count, roles) in enumerate(checks):
            tid = (i << 4) | SLOT_CHECK
            req = _READS[table](address=address, count=count)
            self._submit([(tid, req.function_code, self._frame(req, tid))])
            while True:
                got = self._next_pdu(deadline)
                if got is None:
                    raise InputError(
                        f"modbus driver: profile {prof.source}: no answer from unit {self.unit} "
                        f"at {self._where()} to a read of {table} {address}–"
                        f"{address + count - 1} (roles.{roles})"
                    )
                rtid, pdu_bytes = got
                if rtid != tid:
                    continue
                if pdu_bytes[0] & 0x80:
                    code = pdu_bytes[1] if len(pdu_bytes) > 1 else 0
                    raise InputError(
                        f"modbus driver: profile {prof.source}: roles.{roles}: the controller "
                        f"refuses a read of {table} {address}–{address + count - 1} (Modbus "
                        f"exception {code}: {_EXC.get(code, 'error')})"
                    )
                break

    def _next_pdu(self, deadline: float) -> tuple[int, bytes] | None:
        """The next response off the line before ``deadline`` (blocking helper)."""
        while True:
            got = self._parse_one()
            if got is not None and got[0] >= 0:
                return got
            if got is not None:
                continue
            remaining = deadline - time.perf_counter()
            if remaining <= 0 or self._fd is None:
                return None
            if select.select((self._fd,), (), (), remaining)[0]:
                data = os.read(self._fd, 4096)
                if not data:
                    return None
                self._buf += data

    def _parse_one(self) -> tuple[int, bytes] | None:
        """The next response in the buffer as (transaction id, PDU bytes); (-1, b"") for one
        that is not ours or broken (counted); ``None`` when no complete frame is there."""
        buf = self._buf
        if self._rtu:
            if len(buf) < 5:
                return None
            if buf[0] != self.unit:
                self.stats.count_malformed("unknown_id")
                self._buf = b""
                return (-1, b"")
            cls = self._framer.decoder.lookupPduClass(buf)
            size = cls.calculateRtuFrameSize(buf) if cls is not None else 0
            if cls is None:
                self.stats.count_malformed("unknown_function")
                self._buf = b""
                return (-1, b"")
            if not size or len(buf) < size:
                return None
            frame, self._buf = buf[:size], buf[size:]
            _, _, _, pdu_bytes = self._framer.decode(frame)  # checks the CRC
            if not pdu_bytes:
                self.stats.count_malformed("bad_crc")
                self._buf = b""  # resynchronise on the next frame
                return (-1, b"")
            pending = self._pending
            want = pending[0][1] if pending else -1
            if pdu_bytes[0] & 0x7F != want:
                self.stats.late += 1  # the answer to an older request
                return (-1, b"")
            tid = pending.popleft()[0]
            if pending and pending[0][2]:  # (an e-stop went out already: b"")
                self._write(pending[0][2])
            return tid, pdu_bytes
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
            return (-1, b"")
        pending = self._pending
        if pending and pending[0][0] == tid:  # one at a time: the next request goes out
            pending.popleft()
            if pending:
                self._write(pending[0][2])
        return tid, pdu_bytes

    # -- commands -------------------------------------------------------------------------------
    def _action(self, action: ModbusAction | None) -> list[tuple[int, int, bytes]]:
        if action is None:
            return []
        if action.table == "coil":
            pdu: Any = WriteSingleCoilRequest(address=action.address, bits=[bool(action.value)])
        else:
            pdu = WriteSingleRegisterRequest(address=action.address, registers=[action.value])
        return [(SLOT_ACTION, pdu.function_code, self._frame(pdu, SLOT_ACTION))]

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        regs = self._sp.to_registers(displacement)  # InputError: out of the point's range
        out: list[tuple[int, int, bytes]] = []
        pending = self._pending
        if pending and any(r[0] & 15 < SLOT_CHECK for r in pending):
            # RTU: the last step's requests were not all answered (it timed out): drop them
            self.stats.late += len(pending)
            pending.clear()
            if self._rtu:  # (a TCP stream keeps its framing: a late answer is told by its id)
                self._buf = b""
        acts = self.profile.actions
        if not enable and (seq == 0 or self._estop_sent):
            # the arming command (a new run) or the first disable after our e-stop: acknowledge
            out += self._action(acts.get("disable")) + self._action(acts.get("acknowledge"))
            self._enabled, self._estop_sent = False, False
        elif enable != self._enabled:  # (the hand-back at a normal end only disables)
            out += self._action(acts.get("enable" if enable else "disable"))
            self._enabled = enable
        base = (seq & 0x0FFF) << 4
        pdu = self._step_pdu
        if self.profile.fc23:
            pdu.write_registers = regs
        else:
            pdu.registers = regs
        pdu.transaction_id = base
        out.append((base, pdu.function_code, self._framer.buildFrame(pdu)))
        if not self.profile.fc23:
            for i, frame in enumerate(self._read_frames, start=1):
                if self._rtu:
                    out.append((base | i, frame[1], frame))
                else:
                    out.append((base | i, frame[7], (base | i).to_bytes(2, "big") + frame[2:]))
        self._submit(out)

    def estop(self) -> None:
        self.stats.estops += 1
        self._estop_sent = True  # the next disable acknowledges it
        ((tid, fc, frame),) = self._action(self.profile.actions["estop"])
        if self._rtu:  # written now: answered after the request on the line, if any
            self._pending.insert(1 if self._pending else 0, (tid, fc, b""))
        self._write(frame)

    def heartbeat(self) -> None:
        hb = self.profile.heartbeat
        if hb is None:
            return
        self._hb = (self._hb + 1) & 0x7FFF
        pdu = WriteSingleRegisterRequest(address=hb.address, registers=hb.to_registers(self._hb))
        self._submit([(SLOT_HEARTBEAT, pdu.function_code, self._frame(pdu, SLOT_HEARTBEAT))])

    # -- feedback -------------------------------------------------------------------------------
    def _take(self, tid: int, pdu_bytes: bytes) -> Feedback | None:  # noqa: C901
        """File one response; the feedback when its step's last read came back."""
        if tid < 0:
            return None
        fc = pdu_bytes[0]
        if fc & 0x80:
            self.stats.count_malformed("modbus_exception")
            return None
        slot = tid & 15
        if slot >= SLOT_CHECK or (slot == 0 and not self.profile.fc23):
            return None  # a write's echo
        resp = self._responses.get(fc)
        if resp is None:
            self.stats.count_malformed("bad_frame")
            return None
        try:
            resp.decode(pdu_bytes[1:])  # pymodbus's response class
        except Exception:  # pymodbus raises its own and struct errors
            self.stats.count_malformed("bad_frame")
            return None
        index = 0 if self.profile.fc23 else slot - 1
        if not 0 <= index < self._n_reads:
            self.stats.count_malformed("bad_frame")
            return None
        block = self._reads[index]
        data = resp.registers if fc in (3, 4, 23) else resp.bits
        if len(data) < block.count:
            self.stats.count_malformed("bad_length")
            return None
        seq12 = tid >> 4
        if seq12 != self._parts_seq:
            self._parts_seq = seq12
            self._parts = {}
        parts = self._parts
        parts[index] = data
        if len(parts) < self._n_reads:
            return None
        values: dict[str, float] = {}
        word = 0
        try:
            for index, data in parts.items():
                for off, n, dtype, wo, pts in self._groups[index]:
                    regs = data[off : off + n]
                    if dtype is None:
                        p = pts[0]
                        if p.role == "status":
                            word = p.raw_from_registers(regs)
                        else:
                            values[p.role] = p.from_registers(regs)
                        continue
                    raw = _convert(regs, dtype, word_order=wo)
                    if len(pts) == 1:
                        values[pts[0].role] = pts[0].si(raw)
                    else:
                        for p, r in zip(pts, raw, strict=True):
                            values[p.role] = p.si(r)
            fb = Feedback(
                extend_seq(seq12, self._last_sent, 12),
                values["position"],
                values["force"],
                self._status_of(word),
            )
        except (ValueError, TypeError, IndexError, KeyError):
            self.stats.count_malformed("bad_frame")
            return None
        self._parts = {}
        return fb

    def _status_of(self, word: int) -> int:
        """The bridge's status flags of a status word (looked up once per word)."""
        flags = self._flags.get(word)
        if flags is None:
            flags = self._flags[word] = status_from_word(word, self._masks)
        return flags

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
        elif remaining <= 0 and self._rtu and self._buf:
            self.stats.count_malformed("bad_length")  # an idle line ends an RTU frame
            self._buf = b""
        return None

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

pymodbus is the authority for the frames and the conversions, and its generic work is done
once, at :meth:`ModbusProfileDriver.open` (:mod:`.modbus_layout`): the step's requests are built
by its request classes and framers, the set-point's value bytes located in them, and every
point's wire bytes turned into a ``struct`` format (word order, byte order, type), each checked
against pymodbus's ``convert_to_registers`` / ``convert_from_registers``, ``buildFrame`` and
response classes for test values (a disagreement refuses the profile with one line). Per step
the set-point's bytes, the transaction id (TCP) and the CRC (RTU, pymodbus's
``compute_CRC``) are patched into the request template, and a response is read by one
``struct.unpack_from`` at the precomputed offsets after its function code, byte count and
length are checked as pymodbus's response classes check them. The read requests are built once
(only their transaction id changes); the status word's flags are looked up once per word.
Also at open, every mapped read block and the set-point registers are read once: a controller
that refuses one (a Modbus exception, e.g. illegal data address) is refused with one line
naming the role.
"""

from __future__ import annotations

import os
import select
import socket
import time
from collections import deque
from typing import Any, ClassVar

import serial
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadDiscreteInputsRequest,
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
    WriteMultipleRegistersResponse,
    WriteSingleRegisterRequest,
)

from rths_hil.errors import InputError

from .base import Driver, Feedback, LinkDown, extend_seq
from .modbus_layout import BlockLayout, PointLayout, RequestTemplate, StepReply
from .profile import ModbusAction, ModbusProfile, load_profile, status_from_word

__all__ = ["ModbusProfileDriver"]

_READS = {
    "holding": ReadHoldingRegistersRequest,
    "input": ReadInputRegistersRequest,
    "coil": ReadCoilsRequest,
    "discrete": ReadDiscreteInputsRequest,
}
#: The function code of each table's read response (and FC 23's).
_READ_FC = {"holding": 3, "input": 4, "coil": 1, "discrete": 2}
SLOT_CHECK = 13  # the start-up reads
SLOT_HEARTBEAT = 14
SLOT_ACTION = 15
_EXC = {1: "illegal function", 2: "illegal data address", 3: "illegal data value"}


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
        #: precompiled at open (modbus_layout): the step's request and each block's decoder
        self._template: RequestTemplate | None = None
        self._blocks: list[BlockLayout] = []
        self._block_fc: list[int] = []  # the function code answering each block
        self._reply: StepReply | None = None  # pipelined TCP: the step's whole reply
        #: the step's decoded values so far (role → SI value, ``status`` → the status word),
        #: the blocks they came from and the step (mod 4096) they belong to
        self._parts: dict[str, float] = {}
        self._done: set[int] = set()
        self._parts_seq = -1
        self._masks = prof.masks
        self._flags: dict[int, int] = {}
        self._status = prof.points["status"]
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
        if self._template is None:
            self._compile()
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
        try:
            self._check_map()
        except InputError:
            self.close()
            raise

    def _compile(self) -> None:
        """pymodbus's generic work, once: the step's request template and the read blocks'
        decoders, each checked against pymodbus (:mod:`.modbus_layout`)."""
        prof, src = self.profile, self.profile.source
        self._blocks = [BlockLayout(b, src) for b in self._reads]
        if prof.fc23:
            self._block_fc = [23]
        else:
            self._block_fc = [_READ_FC[b.table] for b in self._reads]
            self._read_frames = [
                self._frame(_READS[b.table](address=b.address, count=b.count), i)
                for i, b in enumerate(self._reads, start=1)
            ]  # built by pymodbus once; per step only the transaction id changes (TCP)
        # pipelined TCP: the step's requests in one template (the reads follow the write)
        follow = [] if self._serial else self._read_frames
        sp = PointLayout(self._sp, src)
        self._template = RequestTemplate(self._framer, self._step_pdu, sp, src, follow)
        if self._serial or any(b.bits or b.other_points for b in self._blocks):
            return  # (the general path: one response at a time)
        # pipelined TCP: the step's whole reply, as pymodbus builds its response frames
        if prof.fc23:
            n = self._reads[0].count
            replies: list[tuple[Any, Any]] = [
                (ReadWriteMultipleRegistersResponse(registers=[0] * n), self._blocks[0])
            ]
        else:
            echo = WriteMultipleRegistersResponse(address=self._sp.address, count=self._sp.count)
            replies = [(echo, None)]
            for b, lay in zip(self._reads, self._blocks, strict=True):
                cls = (
                    ReadHoldingRegistersResponse
                    if b.table == "holding"
                    else ReadInputRegistersResponse
                )
                replies.append((cls(registers=[0] * b.count), lay))
        self._reply = StepReply(self._framer, self.unit, replies)

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
        raw = self._sp.raw_value(displacement)  # InputError: out of the point's range
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
        tpl = self._template
        if tpl is None:  # not opened: nothing goes out (counted as the closed link)
            self.stats.send_errors += 1
            return
        if self._reply is not None:  # pipelined TCP: FC 16 + reads (or FC 23) in one write
            frames = tpl.build(raw, base)  # transaction ids base, base + 1, …
            self._write(b"".join([r[2] for r in out]) + frames if out else frames)
            return
        out.append((base, tpl.function_code, tpl.build(raw, base)))  # FC 16 or FC 23
        if not self.profile.fc23 and self._serial:
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
    def _take(self, tid: int, pdu_bytes: bytes) -> Feedback | None:
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
        index = 0 if self.profile.fc23 else slot - 1
        if not 0 <= index < self._n_reads or fc != self._block_fc[index]:
            self.stats.count_malformed("bad_frame")
            return None
        seq12 = tid >> 4
        if seq12 != self._parts_seq:
            self._parts_seq = seq12
            self._parts = {}
            self._done = set()
        parts = self._parts
        try:
            why = self._blocks[index].decode(pdu_bytes, parts)  # role → SI value, status word
        except (ValueError, OverflowError):  # a NaN or ∞ in a float status point
            why = "bad_frame"
        if why is not None:
            self.stats.count_malformed(why)
            return None
        self._done.add(index)
        if len(self._done) < self._n_reads:
            return None
        self._done = set()
        self._parts = {}
        return Feedback(
            extend_seq(seq12, self._last_sent, 12),
            parts["position"],
            parts["force"],
            self._status_of(parts["status"]),
        )

    def _status_of(self, word: int) -> int:
        """The bridge's status flags of a status word (looked up once per word)."""
        flags = self._flags.get(word)
        if flags is None:
            flags = self._flags[word] = status_from_word(word, self._masks)
        return flags

    def _whole_reply(self) -> Feedback | None:
        """Pipelined TCP: the step's whole reply at the head of the buffer, in one pass
        (:class:`.modbus_layout.StepReply`); anything else is left to :meth:`_parse_one`."""
        reply = self._reply
        if reply is None or len(self._buf) < reply.size:
            return None
        last = self._last_sent
        try:
            got = reply.match(self._buf, (last & 0x0FFF) << 4)
        except (ValueError, OverflowError):  # a NaN or ∞ in a float status point
            return None  # (the general path counts it)
        if got is None:
            return None
        self._buf = self._buf[reply.size :]
        return Feedback(last, got[0], got[1], self._status_of(got[2]))

    def _recv_internal(self, deadline: float) -> Feedback | None:
        while True:
            fb = self._whole_reply()
            if fb is not None:
                return fb
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

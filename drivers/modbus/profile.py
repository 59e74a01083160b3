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
TCP/IP Implementation Guide V1.0b, the MBAP header; docs/references.md). A step sent before
the last step's read was answered writes its set-point alone and takes that read's answer as
its measurement (once per read, within ``HEAD_GIVEUP``; ``_read_outstanding``): a read of
its own would queue behind it at a controller with a request queue. Without it, one
request at a time as on RTU (the next written when the previous one is answered), for a server
that serves one transaction at a time. Whether the server answers pipelined requests is checked
when the driver opens (two reads in one write): a server that answers the first only (it
serves one transaction at a time and drops a request that arrives while another is in
progress) is sent one request at a time from then on, with a warning (:attr:`link_note`). One
at a time, a request is not written over an outstanding one (given up after ``HEAD_GIVEUP``).

**Arming and the enable edge.** Arming writes the loop of the channel's wire mode
(``actions.force_mode`` / ``actions.displacement_mode``, where the profile maps it), the disable
and acknowledge actions and reads the measured values, no set-point (a controller that follows
its set-point register once enabled would move to it); on the enable edge the set-point goes out
before the enable action, so the controller follows the command from the edge.

**E-stop** (Modbus TCP): over a second connection of its own, idle but for the e-stop (else on
the step's connection after the outstanding answer, at most ``ESTOP_DRAIN``), its answer
awaited, the status word read back, and written again until the status word shows the e-stop
or ``ESTOP_WINDOW`` has passed (:meth:`ModbusProfileDriver.estop`). Messages give the
controller's status register as it has it (:meth:`ModbusProfileDriver.fault_text`).

**Modbus RTU** (a serial line: ``device``, ``baudrate``, ``parity``, ``stopbits``). RTU is
half-duplex and carries no transaction id: the driver keeps the step's requests in a queue, writes
the first, and writes the next one when the answer to the previous one has come (an answer whose
function code is not the one of the request at the head of the queue answers an older request:
counted ``late``, dropped). The step of a response is the step of its request. A frame is cut by
the size pymodbus's PDU class computes from its header and checked by its CRC (``FramerRTU``,
:func:`.transport.rtu_frame_size`); garbage is dropped when the line falls idle. An e-stop goes out
at once (as the built-in RTU driver's, :mod:`.driver`), ahead of the queue.

pymodbus is the authority for the frames and the conversions, and its generic work is done
once, at :meth:`ModbusProfileDriver.open` (:mod:`.layout`): the step's requests are built
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

The requests on the connection (pipelined, or one at a time and its queue) are
:class:`.requests.RequestQueue`, the e-stop path :class:`.estop.EStopPath`: the driver's bases.
"""

from __future__ import annotations

import logging
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
    WriteMultipleRegistersRequest,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterRequest,
)

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..base import Feedback, LinkDown, extend_seq
from ..profile import MODE_ACTIONS, status_from_word
from ..profile_driver import ProfileDriver
from .estop import EStopPath
from .layout import BlockLayout, PointLayout, RequestTemplate, StepReply
from .profile_format import ModbusProfile
from .requests import _READS, HEAD_GIVEUP, SLOT_ACTION, SLOT_CHECK, SLOT_HEARTBEAT
from .transport import CONNECTION_KEYS, EXCEPTIONS, Link, framer, openers

__all__ = ["ModbusProfileDriver"]

log = logging.getLogger(__name__)

#: The function code of each table's read response (and FC 23's).
_READ_FC = {"holding": 3, "input": 4, "coil": 1, "discrete": 2}
#: How long the pipelining probe waits for the second answer once the first came (s).
PROBE_WAIT = 0.1
#: One request at a time over TCP: single reads timed at open (the driver's ``round_trip``).
ROUND_TRIPS = 24
#: The share of the loop period a step's one-at-a-time transactions may fill before
#: :meth:`ModbusProfileDriver.link_check` warns (the rest is the round trip's own spread).
LINK_FILL = 0.75


class ModbusProfileDriver(EStopPath, ProfileDriver):
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
    estop_timeout : float
        How long one e-stop write waits for its answer (s); the e-stop is written again and
        read back within 0.5 s (:meth:`estop`).
    estop_connection : bool
        Modbus TCP: open a second connection to the controller, idle but for the e-stop and
        its read-back, so that the e-stop never waits behind a request outstanding on the
        step's connection (a controller that serves one request at a time drops a request
        that arrives while another is in progress). Without it, or when the controller does
        not answer there, the e-stop waits for the outstanding answer (at most 50 ms).

    Attributes
    ----------
    link_note : str or None
        What the driver found out about the link when it opened (e.g. that the controller
        answers one request at a time), for the run's events; ``None`` when nothing.
    round_trip : tuple of float or None
        Modbus TCP one request at a time: the median and 90th percentile (s) of
        ``ROUND_TRIPS`` single reads timed when the link opened; ``None`` otherwise.
    """

    name: ClassVar[str] = "modbus"
    honours_deadline: ClassVar[bool] = True  # select() with the time left
    reader_fallback: ClassVar[bool] = False  # a late receive counted (Driver.reader_fallback)
    #: the built-in driver's, but the unit id is the profile's ``[modbus] unit`` by default
    #: (the profile is ``driver.profile``)
    CONNECTION: ClassVar[Mapping[str, Key]] = {
        **CONNECTION_KEYS,
        "device_id": Key(
            "int", None, lo=0, hi=255, doc="Modbus unit id (none: the profile's [modbus] unit)"
        ),
    }

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
        estop_connection: bool = True,
    ) -> None:
        super().__init__()
        prof = self._load_profile(profile, ModbusProfile, "Modbus")
        if transport == "rtu" and not device:
            raise InputError("modbus driver: transport 'rtu' needs device= (serial port or URL)")
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
        self.estop_connection = estop_connection
        self.link_note: str | None = None
        self.round_trip: tuple[float, float] | None = None
        self._probed = False  # the pipelining probe ran (TCP, pipeline = true)
        self._arming = False
        self._etid = 0
        self._word: int | None = None  # the controller's last status word
        self._head_t = 0.0  # when the request at the head of the queue was written
        self._lock = threading.RLock()
        self._given_up: deque[int] = deque(maxlen=8)  # ids of requests given up (TCP)
        #: the step (mod 4096) of the last step's reads, still outstanding when this step was
        #: sent, whose answer is this step's measurement (see _send_locked); -1: none
        self._adopted = -1
        #: pipelined TCP: the step whose reads were last written, and when (the one to adopt
        #: when the next step goes out before their answer, _send_locked)
        self._read_seq = -1
        self._read_t = 0.0
        self.estop_word: int | None = None  # its status word read back after the e-stop
        self._framer: Any = framer(self._rtu)
        #: the connection (:mod:`.transport`), and the e-stop's own (TCP): made at open
        self._link: Link | None = None
        self._enabled: bool | None = None
        self._estop_sent = False
        self._hb = 0
        self._reads = prof.reads
        #: precompiled at open (layout): the step's request and each block's decoder
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
        self._use_setpoint()

    def _use_setpoint(self) -> None:
        """The point written every step (``roles.setpoint``, or ``roles.force_setpoint`` in
        force mode) and the step's write request, built once (per step its registers and id
        change)."""
        prof = self.profile
        self._sp = sp = prof.points["setpoint"]
        self._n_reads = 1 if prof.fc23 else len(prof.reads)
        self._template = None  # compiled at open
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
        if self._link is None:
            self._link = Link(None, *openers(self))
        link = self._link
        link.connect()
        try:
            self._check_map()
        except InputError:
            self.close()
            raise
        if not self._rtu:
            if not self._serial and not self._probed:
                self._probe_pipeline()
            if self._serial and self.round_trip is None:
                self._time_round_trips()
            if self.estop_connection:
                self._link.open_estop()

    def _probe_pipeline(self) -> None:
        """Two reads in one write: does the controller answer both? A controller that serves
        one transaction at a time drops (or never answers) the second; then the driver sends
        one request at a time from now on, and says so (log, :attr:`link_note`)."""
        self._probed = True
        b = self._reads[0]
        req = _READS[b.table](address=b.address, count=b.count)
        deadline = time.perf_counter() + self.connect_timeout
        for attempt in range(3):
            tids = [((0x100 + 2 * attempt + i) << 4) | SLOT_CHECK for i in (0, 1)]
            self._write(b"".join(self._frame(req, t) for t in tids))
            got: set[int] = set()
            first = 0.0
            while len(got) < 2:
                until = deadline if not got else min(deadline, first + PROBE_WAIT)
                r = self._next_pdu(until)
                if r is None:
                    break
                if r[0] in tids:
                    got.add(r[0])
                    first = first or time.perf_counter()
            if not got:
                return  # no answer at all: arming will say so
            if len(got) < 2:
                self._serial = True
                self._reply = None
                self._compile()  # the step's requests one at a time
                self.link_note = (
                    f"the controller at {self._where()} (unit {self.unit}) answers one request "
                    "at a time: of two requests written together it answered the first only; "
                    "sending one request at a time (profile [modbus] pipeline = true)"
                )
                log.warning("modbus driver: %s", self.link_note)
                return

    def _time_round_trips(self) -> None:
        """One request at a time over TCP: time ``ROUND_TRIPS`` single reads of the step's
        first block, each written when the last was answered (:attr:`round_trip`). A read the
        controller drops (its own pauses) is given up after ``PROBE_WAIT`` and not counted."""
        b = self._reads[0]
        req = _READS[b.table](address=b.address, count=b.count)
        times: list[float] = []
        for i in range(ROUND_TRIPS):
            tid = ((0x200 + i) << 4) | SLOT_CHECK
            sent = time.perf_counter()
            self._submit([(tid, req.function_code, self._frame(req, tid))])
            got = self._next_pdu(sent + PROBE_WAIT)
            while got is not None and got[0] != tid:
                got = self._next_pdu(sent + PROBE_WAIT)
            if got is None:
                self._pending.clear()  # (given up: the next read goes out at once)
                continue
            times.append(time.perf_counter() - sent)
        if len(times) >= ROUND_TRIPS // 2:
            deciles = statistics.quantiles(times, n=10)
            self.round_trip = (statistics.median(times), deciles[8])

    def requests_per_step(self) -> int:
        """A steady step's requests: the set-point write and the reads (FC 23: one)."""
        return 1 if self.profile.fc23 else 1 + len(self._reads)

    def link_check(self, fs: float) -> str | None:
        """What the measured link means at loop rate ``fs`` (Hz): a warning when a step's
        one-at-a-time transactions fill more than ``LINK_FILL`` of the period, else ``None``.

        A controller that serves one request at a time answers a step's requests one after
        the other, so a step needs ``n·t_rt`` of link time (``n`` requests, round trip
        ``t_rt``, the median measured at open). Where that exceeds the period the link
        cannot carry every step: the replies that do not fit are missed (held measurements,
        counted in the summary), however fast the loop.
        """
        if self.round_trip is None or fs <= 0:
            return None
        n, (rt, rt90) = self.requests_per_step(), self.round_trip
        need = n * rt
        if need <= LINK_FILL / fs:
            return None
        fcs = " + ".join(f"FC {c}" for c in ([23] if self.profile.fc23 else [16, *self._block_fc]))
        return (
            f"the controller at {self._where()} (unit {self.unit}) answers one request at a "
            f"time in {rt * 1e3:.2f} ms (median of {ROUND_TRIPS} reads, 90th percentile "
            f"{rt90 * 1e3:.2f} ms): a step's {n} requests ({fcs}) take about "
            f"{need * 1e3:.2f} ms, {100 * need * fs:.0f} % of the {1e3 / fs:.3f} ms period at "
            f"{fs:g} Hz; expect missed replies (held measurements). At most "
            f"{LINK_FILL / need:.0f} Hz leaves a quarter of the period free"
        )

    def _compile(self) -> None:
        """pymodbus's generic work, once: the step's request template and the read blocks'
        decoders, each checked against pymodbus (:mod:`.layout`)."""
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
        link, self._link = self._link, None
        self._enabled = None
        self._pending.clear()
        if link is not None:
            link.close_estop()
            link.disconnect()

    def _check_map(self) -> None:
        """Read every mapped block once; refuse a map the controller does not have."""
        prof = self.profile
        checks = [
            (b.table, b.address, b.count, ", ".join(p.role for p in b.points)) for b in prof.reads
        ]
        checks.append(("holding", self._sp.address, self._sp.count, self._sp.role))
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
                        f"exception {code}: {EXCEPTIONS.get(code, 'error')})"
                    )
                break

    # -- commands -------------------------------------------------------------------------------
    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        with self._lock:
            self._send_locked(seq, displacement, enable)

    def _send_locked(self, seq: int, displacement: float, enable: bool) -> None:
        raw = self._sp.raw_value(displacement)  # InputError: out of the point's range
        out: list[tuple[int, int, bytes]] = []
        pending = self._pending
        if pending and any(r[0] & 15 < SLOT_CHECK for r in pending):
            # the last step's requests were not all answered (it timed out): drop them
            self._drop_pending()
        tpl = self._template
        if tpl is None:  # not opened: nothing goes out (counted as the closed link)
            self.stats.send_errors += 1
            return
        acts = self.profile.actions
        base = (seq & 0x0FFF) << 4
        if self._arming:
            # the arming command (a new run): disable, acknowledge, read where the actuator
            # is; no set-point (the controller would follow it once enabled). A controller
            # that selects its loop on command gets the channel's loop first, while disabled
            out += self._action(acts.get(MODE_ACTIONS[self.control]))
            out += self._action(acts.get("disable")) + self._action(acts.get("acknowledge"))
            self._enabled, self._estop_sent = False, False
            self._read_seq = -1
            self._submit(out + self._reads_only(base))
            return
        preload: list[tuple[int, int, bytes]] = []
        if not enable and (seq == 0 or self._estop_sent):
            # the first disable after our e-stop (or a step 0 disabled): acknowledge
            out += self._action(acts.get("disable")) + self._action(acts.get("acknowledge"))
            self._enabled, self._estop_sent = False, False
        elif enable != self._enabled:  # (the hand-back at a normal end only disables)
            if enable and "enable" in acts:
                # the enable edge: the set-point first, so that the controller follows this
                # command from the edge, not what its register held
                tid = (1 << 4) | SLOT_ACTION
                frame = tpl.build(raw, tid)
                if tpl.tids:  # (the pipelined template carries the reads after the write)
                    frame = frame[: tpl.tids[0]]
                preload = [(tid, tpl.function_code, frame)]
            out += self._action(acts.get("enable" if enable else "disable"))
            self._enabled = enable
        out = preload + out
        if self._reply is not None:  # pipelined TCP: FC 16 + reads (or FC 23) in one write
            frames = tpl.build(raw, base)  # transaction ids base, base + 1, …
            if not out and enable and self._read_outstanding():
                # the last step's reads not answered yet: the controller serves them before
                # this step's requests, so their answer, at the earliest now, is this step's
                # measurement; reads of its own would queue behind them and come a step late
                # again (a cascade of missed replies where the server needs most of the
                # period). The set-point goes out alone (FC 16); no action this step.
                self._adopted = self._read_seq & 0x0FFF
                self._read_seq = -1  # (adopted once: unanswered by the next step, read anew)
                self._write(frames[: tpl.tids[0]])
                return
            self._adopted = -1
            self._read_seq, self._read_t = seq, time.perf_counter()
            self._write(b"".join([r[2] for r in out]) + frames if out else frames)
            return
        out.append((base, tpl.function_code, tpl.build(raw, base)))  # FC 16 or FC 23
        if not self.profile.fc23 and self._serial:
            # the last step's read, outstanding or waiting behind an outstanding write
            old = -1 if self._rtu else next((r[0] for r in pending if r[0] & 15 == 1), -1)
            steady = enable and len(out) == 1  # no action this step: no status to confirm
            if steady and self._n_reads == 1 and old >= 0 and old >> 4 != base >> 4:
                # TCP one at a time, the last step's read not answered yet (its answer was
                # missed): the controller samples when it serves that read, at the earliest
                # now, so its answer is this step's measurement; a read of its own behind the
                # write would come a whole transaction later and miss this step too (a
                # cascade of missed replies at rates where the two transactions fill most of
                # the period). Not with an action (enable, disable, acknowledge): its effect
                # is read after it.
                self._adopted = old >> 4
            else:
                if old >= 0 and pending[0][0] != old:  # not on the wire: this step reads anew
                    pending.remove(next(r for r in pending if r[0] == old))
                    self.stats.late += 1
                self._adopted = -1
                out += self._reads_only(base)
        self._submit(out)

    def _read_outstanding(self) -> bool:
        """Pipelined TCP: whether the last step's read is still unanswered as this step goes
        out. What has come meanwhile is filed first (an answer of an older step is counted
        late, as the receive would). Not when it was written more than ``HEAD_GIVEUP`` ago (a
        reply the controller lost is not waited for twice, e.g. after a lockstep wait), nor
        for maps of several reads or FC 23 (their reads are not apart from the write)."""
        seq = self._read_seq
        if seq < 0 or self._n_reads != 1 or self.profile.fc23 or self._last_delivered == seq:
            return False
        if time.perf_counter() - self._read_t > HEAD_GIVEUP:
            return False
        link, fd = self._link, self._fd
        if link is None or fd is None:
            return False
        try:
            while link.ready(fd, 0.0):
                data = link.recv(fd)
                if not data:
                    break
                self._buf += data
        except (OSError, ValueError):
            return False  # (the receive finds the link down)
        answered = False
        while (fb := self._parse_buffer()) is not None:
            answered = answered or fb.seq == seq
            self._accept(fb)  # counted: late (or a duplicate)
        return not answered

    def _reads_only(self, base: int) -> list[tuple[int, int, bytes]]:
        """The step's reads alone (for FC 23 maps an FC 3 of the block) with the step's ids."""
        if self.profile.fc23:
            b = self._reads[0]
            req = ReadHoldingRegistersRequest(address=b.address, count=b.count)
            return [(base, req.function_code, self._frame(req, base))]
        out = []
        for i, frame in enumerate(self._read_frames, start=1):
            if self._rtu:
                out.append((base | i, frame[1], frame))
            else:
                out.append((base | i, frame[7], (base | i).to_bytes(2, "big") + frame[2:]))
        return out

    def arm(
        self, timeout: float, receive: Callable[[float], Feedback | None] | None = None
    ) -> Feedback | None:
        """Start a new run: disable, acknowledge a latch and read where the actuator is, with
        no set-point written (see :meth:`Driver.arm`); the run's first command writes the
        set-point ahead of the enable."""
        self._arming = True
        try:
            return super().arm(timeout, receive)
        finally:
            self._arming = False

    def heartbeat(self) -> None:
        hb = self.profile.heartbeat
        if hb is None:
            return
        self._hb = (self._hb + 1) & 0x7FFF
        pdu = WriteSingleRegisterRequest(address=hb.address, registers=hb.to_registers(self._hb))
        with self._lock:
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
        want = self._block_fc[index] if 0 <= index < self._n_reads else -1
        if fc != want and not (want == 23 and fc == 3):  # (FC 3: the arming read, FC 23 map)
            self.stats.count_malformed("bad_frame")
            return None
        seq12 = tid >> 4
        if seq12 == self._adopted:  # the last step's reads, this step's measurement (above)
            seq12 = self._last_sent & 0x0FFF
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
        self._adopted = -1  # (a copy of the adopted answer is the old step's)
        word = self._word = int(parts["status"])
        return Feedback(
            extend_seq(seq12, self._last_sent, 12),
            parts["position"],
            parts["force"],
            self._status_of(word),
        )

    def _status_of(self, word: int) -> int:
        """The bridge's status flags of a status word (looked up once per word)."""
        flags = self._flags.get(word)
        if flags is None:
            flags = self._flags[word] = status_from_word(word, self._masks)
        return flags

    def _whole_reply(self) -> Feedback | None:
        """Pipelined TCP: the step's whole reply at the head of the buffer, in one pass
        (:class:`.layout.StepReply`); anything else is left to :meth:`_parse_one`."""
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
        word = self._word = got[2]
        return Feedback(last, got[0], got[1], self._status_of(word))

    def _parse_buffer(self) -> Feedback | None:
        """The responses in the buffer, filed; the feedback once a step's last one came."""
        while True:
            fb = self._whole_reply()
            if fb is not None:
                return fb
            got = self._parse_one()
            if got is None:
                return None
            fb = self._take(*got)
            if fb is not None:
                return fb

    def _recv_internal(self, deadline: float) -> Feedback | None:
        # (the lock: a reader thread may call this while the loop's thread sends, see
        # Driver.receive; the step's queue and the buffer are shared). Waits until a feedback
        # is complete or the deadline: a step's answers come one at a time.
        while True:
            with self._lock:
                fb = self._parse_buffer()
                if fb is not None:
                    return fb
                link, fd = self._link, self._fd
            if link is None or fd is None:
                raise LinkDown("modbus connection closed")
            remaining = deadline - time.perf_counter()
            try:
                ready = link.ready(fd, remaining)
                with self._lock:
                    data = link.recv(fd) if ready else b""  # (b"": the other thread read it)
                    if data:
                        self._buf += data
                    elif remaining <= 0 and self._rtu and self._buf:
                        self.stats.count_malformed("bad_length")  # an idle line ends a frame
                        self._buf = b""
            except (OSError, ValueError):
                self.stats.disconnects += 1
                self._close_main()
                raise LinkDown("modbus connection lost") from None
            if remaining <= 0:
                with self._lock:
                    return self._parse_buffer()

"""The requests of :class:`~.profile.ModbusProfileDriver` on its connection: each framed with
its transaction id, written pipelined (a step's requests in one write) or one at a time (the
next written when the previous one is answered: RTU, and Modbus TCP with ``pipeline = false``),
the answers read back and matched, the last step's unanswered requests dropped or kept, and a
request the controller lost given up after ``HEAD_GIVEUP``.

:class:`RequestQueue` is a base of the driver; the attributes it uses are the driver's (set in
its ``__init__``, listed here for the type checker).
"""

from __future__ import annotations

import socket
import time
from collections import deque
from typing import Any

from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadDiscreteInputsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    WriteSingleRegisterRequest,
)

from ..base import DriverStats
from .profile_format import ModbusAction, ModbusProfile
from .transport import Link, rtu_frame_size

__all__ = ["HEAD_GIVEUP", "SLOT_ACTION", "SLOT_CHECK", "SLOT_HEARTBEAT", "RequestQueue"]

_READS = {
    "holding": ReadHoldingRegistersRequest,
    "input": ReadInputRegistersRequest,
    "coil": ReadCoilsRequest,
    "discrete": ReadDiscreteInputsRequest,
}
SLOT_CHECK = 13  # the start-up reads (and the pipelining probe)
SLOT_HEARTBEAT = 14
SLOT_ACTION = 15  # actions, the set-point written ahead of the enable, the e-stop and its poll
#: One request at a time over TCP: how long a request stays outstanding (the next ones wait
#: for its answer) before the driver gives it up and writes the next (s). Longer than a
#: controller's own pauses (20–40 ms), and well inside the loop's reply watchdog
#: (``safety.watchdog_timeout``, 0.1 s by default), so that one request the controller lost
#: costs a reply gap, not a trip.
HEAD_GIVEUP = 0.05


class RequestQueue:
    """The driver's requests on its connection (module docstring)."""

    stats: DriverStats
    profile: ModbusProfile
    unit: int
    device: str | None
    host: str
    port: int
    _rtu: bool
    _serial: bool
    _framer: Any
    _link: Link | None
    _enabled: bool | None
    _pending: deque[tuple[int, int, bytes]]
    _head_t: float
    _given_up: deque[int]
    _n_reads: int

    @property
    def _fd(self) -> int | None:
        """The step connection's descriptor (``None``: down or not open)."""
        link = self._link
        return None if link is None else link.fd

    @property
    def _buf(self) -> bytes:
        """Bytes read off the step's connection, not yet parsed."""
        link = self._link
        return b"" if link is None else link.buf

    @_buf.setter
    def _buf(self, value: bytes) -> None:
        if self._link is not None:
            self._link.buf = value

    @property
    def _esock(self) -> socket.socket | None:
        link = self._link
        return None if link is None else link.esock

    def _close_main(self) -> None:
        """Close the step's connection (a lost link; the e-stop's own stays open)."""
        self._enabled = None
        self._pending.clear()
        if self._link is not None:
            self._link.disconnect()

    def _where(self) -> str:
        return str(self.device) if self._rtu else f"{self.host}:{self.port}"

    def _frame(self, pdu: Any, tid: int) -> bytes:
        pdu.dev_id, pdu.transaction_id = self.unit, tid
        return self._framer.buildFrame(pdu)

    def _write(self, data: bytes) -> None:
        link = self._link
        if link is None:
            self.stats.send_errors += 1
            return
        was_up = link.fd is not None
        link.write(data, self.stats)
        if was_up and link.fd is None:  # the write lost the connection
            self._enabled = None
            self._pending.clear()

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
            self._head_t = time.perf_counter()

    def _next_pdu(self, deadline: float) -> tuple[int, bytes] | None:
        """The next response off the line before ``deadline`` (blocking helper)."""
        while True:
            got = self._parse_one()
            if got is not None and got[0] >= 0:
                return got
            if got is not None:
                continue
            remaining = deadline - time.perf_counter()
            link = self._link
            if remaining <= 0 or link is None or link.fd is None:
                return None
            try:
                data = link.read(remaining)
            except ConnectionResetError:
                return None
            link.buf += data

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
            size = rtu_frame_size(self._framer.decoder, buf)
            if size is None:
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
        self._answered(tid)
        return tid, pdu_bytes

    def _answered(self, tid: int) -> None:
        """TCP one at a time: the answer to ``tid`` came; the next request goes out."""
        pending = self._pending
        if pending and pending[0][0] == tid:
            pending.popleft()
        elif tid in self._given_up:
            # the late answer to a request given up: the controller was still serving it when
            # the one now outstanding arrived, and dropped that one: write it again
            self._given_up.remove(tid)
        else:
            return
        if pending:
            self._write(pending[0][2])
            self._head_t = time.perf_counter()

    def _action(self, action: ModbusAction | None) -> list[tuple[int, int, bytes]]:
        if action is None:
            return []
        if action.table == "coil":
            pdu: Any = WriteSingleCoilRequest(address=action.address, bits=[bool(action.value)])
        else:
            pdu = WriteSingleRegisterRequest(address=action.address, registers=[action.value])
        return [(SLOT_ACTION, pdu.function_code, self._frame(pdu, SLOT_ACTION))]

    def _drop_pending(self) -> None:
        """Drop the last step's unanswered requests before this step's go out.

        RTU: all of them (the line is resynchronised). Modbus TCP one at a time: the request
        on the wire stays outstanding unless it has been for ``HEAD_GIVEUP`` (a controller
        that serves one request at a time drops one written while another is in progress, so
        the next is written when its answer comes); of the ones not yet written the step's
        set-point writes are dropped (the next step writes a newer one), the heartbeats and
        actions stay, and the step's read stays when a write is on the wire.
        """
        pending = self._pending
        if self._rtu:  # the line is resynchronised: nothing of the last step is kept
            self.stats.late += len(pending)
            if any(r[0] & 15 == SLOT_ACTION and r[2] for r in list(pending)[1:]):
                self._enabled = None  # an action that never went out: the next step sends it
            pending.clear()
            self._buf = b""
            return
        head, rest = pending[0], list(pending)[1:]
        stale = time.perf_counter() - self._head_t > HEAD_GIVEUP
        # kept, in their order: heartbeats (the controller's watchdog counts on them),
        # actions (an enable, a disable, the set-point ahead of an enable: dropped and sent
        # again behind the next step's outstanding request, on a link slower than the period
        # they would never go out) and the step's read if a write is on the wire (it goes
        # before the next step's write and is that step's measurement, _send_locked)
        read_ok = self._n_reads == 1 and not self.profile.fc23 and head[0] & 15 != 1
        keep, dropped, has_read = [], [], False
        for r in rest:
            slot = r[0] & 15
            if slot == SLOT_HEARTBEAT or (slot == SLOT_ACTION and r[2]):
                keep.append(r)
            elif slot == 1 and read_ok and not has_read:
                keep.append(r)
                has_read = True
            else:
                dropped.append(r)
        self.stats.late += len(dropped) + (1 if stale else 0)
        pending.clear()
        if stale:
            self._given_up.append(head[0])
        else:
            pending.append(head)
        pending.extend(keep)
        if stale and pending:
            self._write(pending[0][2])
            self._head_t = time.perf_counter()

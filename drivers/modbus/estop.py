"""The e-stop path of :class:`~.profile.ModbusProfileDriver`: ``actions.estop`` written at once
(RTU) or on the e-stop's own connection, else on the step's once its outstanding answer came
(Modbus TCP), written again and the status word read back until it shows the e-stop or
``ESTOP_WINDOW`` has passed, the outcome logged in the controller's own terms.

:class:`EStopPath` is a base of the driver; the attributes it uses are the driver's (set in its
``__init__``, listed here for the type checker).
"""

from __future__ import annotations

import logging
import threading
import time

from ..base import Status
from .profile_format import ModbusPoint
from .requests import _READS, SLOT_ACTION, SLOT_CHECK, RequestQueue

__all__ = ["ESTOP_DRAIN", "ESTOP_WINDOW", "EStopPath"]

log = logging.getLogger(f"{__package__}.profile")  # the driver's logger

#: E-stop over Modbus TCP: how long it may wait for the answer outstanding on the link before
#: writing the e-stop there (s), and how long it keeps writing and reading back (s).
ESTOP_DRAIN = 0.05
ESTOP_WINDOW = 0.5
_FLAG_NAMES = {
    int(Status.ENABLED): "enabled",
    int(Status.ESTOP_ACTIVE): "e-stop",
    int(Status.FAULT): "fault",
    int(Status.WATCHDOG): "watchdog",
    int(Status.SENSOR_INVALID): "sensor invalid",
}


class EStopPath(RequestQueue):
    """The driver's e-stop (module docstring)."""

    estop_timeout: float
    estop_word: int | None
    _lock: threading.RLock
    _masks: dict[int, int]
    _status: ModbusPoint
    _word: int | None
    _etid: int
    _estop_sent: bool

    def estop(self) -> None:
        """Latch the controller's e-stop (``actions.estop``), whatever is outstanding.

        RTU: written at once, answered after the request on the line. Modbus TCP: written on
        the e-stop's own connection (``estop_connection``), else on the step's connection once
        the answer outstanding there has come (at most 50 ms: a controller that serves one
        request at a time drops a request that arrives while another is in progress); its
        answer awaited (``estop_timeout``) and the status word read back, and written again
        until the status word shows the e-stop or 0.5 s have passed. :attr:`estop_word` is
        the status word read back (``None``: no answer); the outcome is logged in the
        controller's own terms (its status register).
        """
        self.stats.estops += 1
        self._estop_sent = True  # the next disable acknowledges it
        ((tid, fc, frame),) = self._action(self.profile.actions["estop"])
        with self._lock:
            if self._rtu:  # written now: answered after the request on the line, if any
                self._pending.insert(1 if self._pending else 0, (tid, fc, b""))
                self._write(frame)
                return
            self._estop_tcp()

    def _estop_tcp(self) -> None:
        mask = self._masks[int(Status.ESTOP_ACTIVE)]
        t0 = time.perf_counter()
        end = t0 + ESTOP_WINDOW
        self.estop_word = None
        writes, answered, refused = 0, 0, None
        own_silent = False  # no answer on the e-stop's own connection: the step's next
        while True:
            own = self._esock is not None and not own_silent
            if not own and self._fd is None:
                if self._esock is None:
                    break  # no connection left to the controller
                own = True
            if not own:
                self._drain(min(end, time.perf_counter() + ESTOP_DRAIN))
            self._etid = (self._etid + 1) & 0xFF
            tid = ((0xE00 | self._etid) << 4) | SLOT_ACTION
            act = self.profile.actions["estop"]
            ((_, _, frame),) = self._action(act)
            frame = tid.to_bytes(2, "big") + frame[2:]
            writes += 1
            pdu = self._ask(frame, tid, min(end, time.perf_counter() + self.estop_timeout), own)
            own_silent = own and pdu is None
            if pdu is not None:
                answered += 1
                if pdu[0] & 0x80:
                    refused = pdu[1] if len(pdu) > 1 else 0
                word = self._read_status(end, own)
                if word is not None:
                    self.estop_word = word
                    if word & mask:
                        break
            if time.perf_counter() >= end:
                break
        if own:  # the step's connection: let its outstanding answer come (the confirmation poll)
            self._drain(min(end, time.perf_counter() + ESTOP_DRAIN))
        self._pending.clear()
        via = "its own connection" if own else "the step's connection"
        word = self.estop_word
        where = f"modbus driver: e-stop to the controller at {self._where()} over {via}"
        ms = (time.perf_counter() - t0) * 1e3
        if word is not None and word & mask:
            log.warning(
                "%s: latched, status register %s (%d write%s, %.0f ms)",
                where, self.describe_word(word), writes, "s" if writes > 1 else "", ms,
            )  # fmt: skip
        elif word is not None:
            why = f", the e-stop write refused (exception {refused})" if refused else ""
            log.error(
                "%s: NOT latched: status register %s after %d writes in %.0f ms%s",
                where, self.describe_word(word), writes, ms, why,
            )  # fmt: skip
        else:
            log.error(
                "%s: not confirmed: no status read back (%d writes, %d answered, in %.0f ms)",
                where, writes, answered, ms,
            )  # fmt: skip

    def _drain(self, deadline: float) -> None:
        """One request at a time: wait (until ``deadline``) for the answer outstanding on the
        step's connection, sending nothing more; the requests queued behind it are dropped."""
        pending = self._pending
        while len(pending) > 1:
            pending.pop()
        while pending and self._fd is not None:
            try:
                if self._next_pdu(deadline) is None:
                    break
            except OSError:
                self._close_main()
                break

    def _ask(self, frame: bytes, tid: int, deadline: float, own: bool) -> bytes | None:
        """Write one request on the e-stop's own connection (``own``) or the step's, and
        return the PDU of its answer (``None``: none before ``deadline``)."""
        if not own:
            if self._fd is None:
                return None
            self._pending.clear()
            self._write(frame)
            while True:
                try:
                    got = self._next_pdu(deadline)
                except OSError:
                    self._close_main()
                    return None
                if got is None:
                    return None
                if got[0] == tid:
                    return got[1]
        link = self._link
        if link is None:
            return None
        try:
            return link.ask(frame, tid, self.unit, deadline)
        except OSError:  # (closed: the next attempt goes over the step's connection)
            return None

    def _read_status(self, end: float, own: bool) -> int | None:
        """The controller's status word, read on its own (``None``: no answer)."""
        st = self._status
        req = _READS[st.table](address=st.address, count=st.count)
        self._etid = (self._etid + 1) & 0xFF
        tid = ((0xF00 | self._etid) << 4) | SLOT_CHECK
        pdu = self._ask(
            self._frame(req, tid), tid, min(end, time.perf_counter() + self.estop_timeout), own
        )
        if pdu is None or pdu[0] & 0x80 or len(pdu) < 3:
            return None
        if st.table in ("coil", "discrete"):
            return pdu[2] & 1
        n = pdu[1] // 2
        if n < st.count or len(pdu) < 2 + 2 * n:
            return None
        regs = [int.from_bytes(pdu[2 + 2 * i : 4 + 2 * i], "big") for i in range(st.count)]
        return st.raw_from_registers(regs)

    def describe_word(self, word: int) -> str:
        """A status word in the controller's terms: ``0x00A0 (e-stop, watchdog)``."""
        names = [_FLAG_NAMES[f] for f, m in self._masks.items() if word & m and f in _FLAG_NAMES]
        return f"0x{word:04X} ({', '.join(names) if names else 'none of the profile bits'})"

    def fault_text(self) -> str:
        """The controller's last status register, in its own terms (for a trip's reason)."""
        word = self._word
        return "" if word is None else f"status register {self.describe_word(word)}"

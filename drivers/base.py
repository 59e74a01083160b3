"""The one interface every bus driver implements, and what it returns.

A driver carries, once per integration step ``k``, one command (displacement in m, an enable
flag, the sequence number ``k``) to an actuator controller and brings back one
:class:`Feedback` (measured displacement in m, measured force in N, status flags, the echoed
sequence number). The real-time loop runs in lockstep: ``send(k, …)`` then ``receive(timeout)``.

Robustness contract (all drivers): :meth:`Driver.receive` never raises on what the bus brings
— a malformed frame (bad CRC/checksum, wrong length, unknown ID, undecodable), a sequence gap, a
duplicate, a late frame, a timeout or a lost connection — it counts it in :class:`DriverStats`
and returns the next good feedback for the last command sent, or ``None`` when the timeout
expires. Only programming or configuration errors raise
(:class:`~rths_hil.errors.InputError`: a NaN or out-of-range command, bad connection keys).

Sequence rules shared by all drivers (:meth:`Driver._classify`): feedback echoing the last sent
sequence number is delivered; an older one is counted as ``late`` (answering a command whose
feedback already timed out) or ``duplicates`` (already delivered) and skipped; one newer than any
command sent is malformed (``unexpected_seq``). When a delivered sequence number is more than one
above the previous delivered one, the missing ones are counted in ``seq_gaps``. A controller that
echoes no sequence number (:attr:`Driver.echoes_seq` false): the first feedback received after a
command was sent answers it (its age is recorded in :attr:`Feedback.age`); any further one before
the next command is a ``duplicate``.

The receive loop, the deadline and the counters belong to :class:`Driver`; a driver implements
``_send_raw`` and ``_recv_internal`` (see :class:`Driver` and ``docs/protocols.md``).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from enum import IntFlag
from types import TracebackType
from typing import TYPE_CHECKING, Any, ClassVar

from rths_hil.errors import InputError

if TYPE_CHECKING:
    from rths_hil.keys import Key

log = logging.getLogger(__name__)
_perf = time.perf_counter

#: How late past its deadline a driver that declares :attr:`Driver.honours_deadline` may
#: return before it is counted and moved to a reader thread (s).
DEADLINE_SLACK = 0.050
#: How long a reader thread waits in one ``_recv_internal`` call (s).
READER_POLL = 0.05
#: A reader thread stops after this long without a :meth:`Driver.receive` call (s).
READER_IDLE = 2.0

__all__ = [
    "DEADLINE_SLACK",
    "DISPLACEMENT",
    "DISPLACEMENT_LSB",
    "FORCE",
    "FORCE_LSB",
    "INVALID_S32",
    "Driver",
    "DriverStats",
    "Feedback",
    "LinkDown",
    "Status",
    "check_command",
    "extend_seq",
]

#: Fixed-point resolution of displacements on CAN and Modbus (m per count, signed 32 bit).
DISPLACEMENT_LSB = 1e-7
#: Fixed-point resolution of forces on CAN and Modbus (N per count, signed 32 bit).
FORCE_LSB = 1e-2
#: The wire control modes (:meth:`Driver.set_control`): the command is a displacement (m) or a
#: force set-point (N). A ``"load"`` channel is force-controlled on the wire.
DISPLACEMENT = "displacement"
FORCE = "force"
#: Signed 32-bit raw value reserved for "no valid measurement" (decoded as NaN).
INVALID_S32 = -(2**31)
_S32_MAX = 2**31 - 1


class Status(IntFlag):
    """Status bit flags carried in :attr:`Feedback.status` (same bits on every bus).

    ENABLED
        The controller follows commands (last command had ``enable`` set, no e-stop latched).
    ESTOP_ACTIVE
        The e-stop is latched: the actuator holds its last position and ignores commands until a
        command with ``enable=False`` acknowledges it (then ``enable=True`` re-enables).
    FAULT
        The controller reports a fault of its own (e.g. an injected runaway).
    SENSOR_INVALID
        At least one measured value in this feedback is not valid (sent as NaN / the reserved
        raw value, or a controller's own sensor bit): :meth:`Driver.receive` delivers the
        displacement of such a sample as NaN whatever number came with it.
    WATCHDOG
        The heartbeat watchdog expired and tripped the e-stop.
    SEQ_GAP
        The controller saw a gap in the command sequence numbers (a command was lost).
    """

    ENABLED = 0x01
    ESTOP_ACTIVE = 0x02
    FAULT = 0x04
    SENSOR_INVALID = 0x08
    WATCHDOG = 0x10
    SEQ_GAP = 0x20


_SENSOR_INVALID = int(Status.SENSOR_INVALID)  # a plain int for the receive path


@dataclass(slots=True)
class Feedback:
    """One feedback sample.

    Attributes
    ----------
    seq : int
        Sequence number of the command this feedback answers.
    displacement : float
        Measured actuator displacement (m); NaN when the sensor value is invalid.
    force : float
        Measured specimen force (N); NaN when invalid.
    status : int
        :class:`Status` bit flags.
    age : float
        Time from sending the command to delivering this feedback (s), set by
        :meth:`Driver.receive`; NaN until then.
    """

    seq: int
    displacement: float
    force: float
    status: int
    age: float = math.nan


@dataclass(slots=True)
class DriverStats:
    """Counters every driver keeps; they never reset during a run.

    Attributes
    ----------
    sent, received : int
        Command frames sent and feedback samples delivered by :meth:`Driver.receive`.
    timeouts : int
        Calls to :meth:`Driver.receive` that returned ``None``.
    malformed : int
        Frames rejected; ``malformed_reasons`` breaks them down (``bad_crc``, ``bad_length``,
        ``unknown_id``, ``bad_frame``, ``unexpected_seq``, ``modbus_exception``, …).
    seq_gaps : int
        Sequence numbers never delivered between two delivered feedbacks.
    duplicates, late : int
        Feedback frames skipped because already delivered / answering an older command.
    invalid_values : int
        Delivered feedbacks carrying a NaN (invalid sensor value).
    disconnects : int
        Times the transport was found closed or broken.
    send_errors : int
        Commands that could not be written to the transport.
    estops : int
        E-stop frames sent.
    deadline_overruns : int
        Receives whose driver returned more than ``DEADLINE_SLACK`` past the deadline (the
        driver is then read through a reader thread).
    """

    sent: int = 0
    received: int = 0
    timeouts: int = 0
    malformed: int = 0
    seq_gaps: int = 0
    duplicates: int = 0
    late: int = 0
    invalid_values: int = 0
    disconnects: int = 0
    send_errors: int = 0
    estops: int = 0
    deadline_overruns: int = 0
    malformed_reasons: dict[str, int] = field(default_factory=dict)

    def count_malformed(self, reason: str) -> None:
        """Count one rejected frame under ``reason``."""
        self.malformed += 1
        self.malformed_reasons[reason] = self.malformed_reasons.get(reason, 0) + 1

    def as_dict(self) -> dict[str, Any]:
        """All counters as a plain dict (for logs and run reports)."""
        return asdict(self)


def extend_seq(raw: int, reference: int, bits: int) -> int:
    """Extend a ``bits``-wide wire sequence number to the full one at or just below ``reference``.

    The result ``s`` satisfies ``s ≡ raw (mod 2**bits)`` and
    ``reference - 2**bits < s ≤ reference``.
    """
    mask = (1 << bits) - 1
    return reference - ((reference - raw) & mask)


def check_command(
    seq: int, displacement: float, lsb: float | None = DISPLACEMENT_LSB, control: str = DISPLACEMENT
) -> None:
    """Raise :class:`InputError` for a command that must never reach an actuator.

    Parameters
    ----------
    seq : int
        Step sequence number, must be ≥ 0.
    displacement : float
        Command (m, or N when ``control`` is ``"force"``), must be finite and, when ``lsb`` is
        given, representable in signed 32 bit.
    lsb : float or None
        Fixed-point resolution of the bus (unit per count), or ``None`` for a float wire format.
    control : str
        The wire mode, ``"displacement"`` or ``"force"`` (names the quantity in the message).
    """
    what, unit = ("force", "N") if control == FORCE else ("displacement", "m")
    if seq < 0:
        raise InputError(f"command sequence number must be >= 0, got {seq}")
    if not math.isfinite(displacement):
        raise InputError(f"command {what} for step {seq} is not finite ({displacement})")
    if lsb is not None and abs(displacement) > _S32_MAX * lsb:
        raise InputError(
            f"command {what} {displacement} {unit} for step {seq} exceeds the bus range "
            f"±{_S32_MAX * lsb:.1f} {unit}"
        )


class LinkDown(Exception):
    """Raised by :meth:`Driver._recv_internal` when the transport is closed or gone."""


class Driver(ABC):
    """Bus driver: lockstep command/feedback exchange with an actuator controller.

    The base class owns the driver contract, in the style of python-can's ``BusABC.recv`` /
    ``_recv_internal``: :meth:`send` checks the command and keeps the books, :meth:`receive`
    owns the deadline (absolute, from :func:`time.perf_counter`), the timeout accounting, the
    sequence rules (:meth:`_classify`) and the counters. A driver implements

    * :meth:`open`, :meth:`close` and :meth:`estop` (and :meth:`heartbeat` where the bus has one);
    * :meth:`_send_raw` ``(seq, displacement, enable)``: encode and write one command;
    * :meth:`_recv_internal` ``(deadline)``: the next well-formed feedback that arrived, or
      ``None`` when nothing usable came (a malformed frame counted in :attr:`stats`, or the
      deadline passed), **without blocking past** ``deadline``.

    A driver whose class does not declare :attr:`honours_deadline` is read through a reader
    thread (as python-can reads interfaces that ignore the timeout through a
    :class:`can.Notifier`): :meth:`receive` then waits on a queue that honours the deadline to
    the microsecond, so a driver that blocks cannot hold the loop — and its watchdog — past the
    deadline. A driver that declares it and still returns more than :data:`DEADLINE_SLACK` late
    is counted (``stats.deadline_overruns``), logged once and moved to the reader thread (the
    slack is wide, 50 ms, so that a process the OS did not schedule for a while is not taken for
    a blocking driver; the reader thread is the protection, this only a fallback).

    A subclass may still override :meth:`send` and :meth:`receive` whole (the contract of
    earlier releases); it then keeps ``_last_sent``, the counters and the sequence rules itself
    (:meth:`_classify`).

    Class attributes a driver sets: :attr:`name`, :attr:`honours_deadline`,
    :attr:`echoes_seq`, :attr:`command_lsb`, :attr:`atomic_command`, :attr:`control_modes`.
    What the plan knows before any bus is opened (the link, its load, who may share it, the
    twin, the profile format) is not the driver's: it is the protocol's descriptor
    (:class:`rths_hil.drivers.protocol.Protocol`, see ``docs/protocols.md``, "Adding a
    driver").
    """

    name: ClassVar[str]
    #: ``_recv_internal`` never blocks past its deadline (then it is called from the loop's
    #: thread; otherwise from a reader thread).
    honours_deadline: ClassVar[bool] = False
    #: A receive that returns more than :data:`DEADLINE_SLACK` late moves the driver to a
    #: reader thread (the fallback). ``False`` for a driver whose every wait takes the deadline
    #: as its timeout (a late return is then the process not scheduled, which a thread does
    #: not cure) and whose bus other drivers share: a reader thread of one node would take the
    #: other nodes' replies off the bus while they wait on it, and they would miss them.
    reader_fallback: ClassVar[bool] = True
    #: The controller echoes the command's sequence number in its feedback. ``False``: the
    #: first feedback received after a command was sent answers it (its age is recorded).
    echoes_seq: ClassVar[bool] = True
    #: Fixed-point resolution of the command on the wire (m per count) for
    #: :func:`check_command`; ``None`` for a float wire format (or one whose driver checks the
    #: range itself). In force mode a fixed-point command is checked at :data:`FORCE_LSB`.
    command_lsb: ClassVar[float | None] = DISPLACEMENT_LSB
    #: The set-point and the enable flag travel together in one frame (a CAN frame, a serial
    #: frame, the built-in Modbus FC 23 request): the position of an ``enable=False`` command is
    #: not a set-point a controller follows. ``False`` for a protocol that writes the set-point
    #: apart from the enable (a register map whose controller applies the set-point on write;
    #: CiA 402's target and controlword): :meth:`arm` then reads where the actuator is first
    #: (:meth:`poll`) and writes only that (see :meth:`arm`, "no start jump").
    atomic_command: ClassVar[bool] = True

    #: The wire control modes this driver can run (:meth:`set_control`): ``"displacement"``
    #: (the command is a position, m) and, for a driver that can, ``"force"`` (the command is a
    #: force set-point, N). A driver whose force capability depends on its profile or device
    #: lists ``"force"`` here and refuses in :meth:`set_control` what its profile lacks.
    control_modes: ClassVar[tuple[str, ...]] = (DISPLACEMENT,)
    #: The wire mode this driver runs, set by :meth:`set_control` before :meth:`open`.
    control: str = DISPLACEMENT
    #: The connection settings the driver takes (``driver.connection``): name →
    #: :class:`~rths_hil.config.Key` (kind, default, SI unit, range, doc), read by
    #: :func:`~rths_hil.drivers.registry.check_connection` before the driver is built; the
    #: defaults are those of ``__init__``. ``None``: the constructor's signature is checked.
    CONNECTION: ClassVar[Mapping[str, Key] | None] = None

    stats: DriverStats
    # class-level defaults: a subclass that does not call Driver.__init__ still works
    _last_sent = -1
    _last_delivered = -1
    _t_sent = 0.0
    _rx_thread: threading.Thread | None = None
    _rx_queue: queue.Queue | None = None
    _rx_stop: threading.Event | None = None
    _last_receive = 0.0
    _last_position = 0.0  # the last finite measured displacement delivered (m)
    _last_force = 0.0  # the last finite measured force delivered (N)
    _overrun_warned = False
    _threaded = True
    #: Why the transport is down (the :class:`LinkDown` message of the last receive), or
    #: ``None`` while it is up: set when :meth:`receive` catches :class:`LinkDown`, cleared by
    #: the next delivered feedback. The loop trips on it at once (a dead link is not a pause).
    link_down: str | None = None

    def __init__(self) -> None:
        self.stats = DriverStats()
        self._last_sent = -1
        self._last_delivered = -1
        self._t_sent = 0.0
        self._threaded = not self.honours_deadline

    @abstractmethod
    def open(self) -> None:
        """Open the transport (idempotent)."""

    @abstractmethod
    def close(self) -> None:
        """Close the transport (idempotent, never raises)."""

    def __enter__(self) -> Driver:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop_reader()
        self.close()

    def set_control(self, mode: str) -> None:
        """Select the wire control mode, once, before :meth:`open`.

        In ``"force"`` mode :meth:`send` carries a force set-point (N) where it carries a
        displacement otherwise; :class:`Feedback` is unchanged (displacement m, force N), and
        :meth:`arm` holds the measured force instead of the position (no start jump).

        Parameters
        ----------
        mode : str
            ``"displacement"`` or ``"force"`` (a ``"load"`` channel asks for ``"force"``).

        Raises
        ------
        InputError
            ``mode`` is not one of :attr:`control_modes` (one line naming the driver and the
            mode). A driver overriding this also refuses a profile or device that lacks what
            the mode needs, naming what is missing.
        """
        name = getattr(self, "name", type(self).__name__)
        if mode not in self.control_modes:
            raise InputError(
                f"driver {name!r} cannot run a {mode!r}-controlled channel (its control modes: "
                f"{', '.join(self.control_modes)})"
            )
        self.control = mode

    # -- the contract: what a driver implements -------------------------------------------------
    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        """Encode and write the command of step ``seq`` (already checked).

        Transport failures are counted (``stats.send_errors``), never raised.
        """
        raise NotImplementedError(f"{type(self).__name__}: implement _send_raw (or override send)")

    def _recv_internal(self, deadline: float) -> Feedback | None:
        """The next well-formed feedback, or ``None``, without blocking past ``deadline``.

        Parameters
        ----------
        deadline : float
            Absolute time (:func:`time.perf_counter`) after which the call must return.

        Returns
        -------
        Feedback or None
            A feedback decoded from the wire with its full sequence number (the driver extends
            a narrow wire counter, e.g. with :func:`extend_seq` against ``self._last_sent``;
            ``seq`` is ignored when :attr:`echoes_seq` is false); ``None`` when nothing usable
            arrived — the base class calls again while time remains. Malformed frames are
            counted by the driver (``stats.count_malformed``); lost connections in
            ``stats.disconnects``. It never raises on what the bus brings.

        Raises
        ------
        LinkDown
            The transport is closed or gone: nothing can arrive before the deadline (the
            receive ends at once, counted as a timeout, instead of waiting it out).
        """
        raise NotImplementedError(
            f"{type(self).__name__}: implement _recv_internal (or override receive)"
        )

    # -- the contract: what the base class does -------------------------------------------------
    def send(self, seq: int, displacement: float, enable: bool = True) -> None:
        """Send the command for step ``seq``: ``displacement`` in metres, ``enable`` flag.

        In force mode (:meth:`set_control`) ``displacement`` is the force set-point in N.
        Raises :class:`~rths_hil.errors.InputError` for a non-finite or out-of-range command;
        transport failures are counted (``send_errors``), not raised.
        """
        lsb = self.command_lsb
        if self.control == FORCE and lsb is not None:
            lsb = FORCE_LSB  # a fixed-point force set-point, N per count
        check_command(seq, displacement, lsb, self.control)
        prev = self._last_sent
        self._last_sent = seq
        self._t_sent = _perf()
        try:
            self._send_raw(seq, displacement, enable)
        except InputError:  # refused by the wire format (e.g. out of a DBC signal's range)
            self._last_sent = prev
            raise
        self.stats.sent += 1

    def receive(self, timeout: float) -> Feedback | None:
        """Wait up to ``timeout`` seconds for the feedback of the last command sent.

        Returns ``None`` on timeout (counted); never raises on bus faults. What arrives is
        sorted by the sequence rules (module docstring); a delivered feedback carries its
        :attr:`Feedback.age` (time since the command was sent, s).
        """
        now = _perf()
        deadline = now + (timeout if timeout > 0.0 else 0.0)
        self._last_receive = now
        if self._threaded:
            recv = self._recv_queued
        else:
            recv = self._recv_internal
        stats = self.stats
        while True:
            try:
                fb = recv(deadline)
            except LinkDown as exc:
                stats.timeouts += 1
                self.link_down = str(exc) or type(exc).__name__
                return None
            now = _perf()
            if fb is not None:
                if self.echoes_seq:
                    ok = self._classify(fb.seq)
                else:
                    ok = self._match(fb)
                if ok:
                    stats.received += 1
                    if self.link_down is not None:
                        self.link_down = None
                    if fb.status & _SENSOR_INVALID:  # the controller flags the sample invalid
                        fb.displacement = math.nan
                    d = fb.displacement
                    f = fb.force
                    if d != d or f != f:
                        stats.invalid_values += 1
                    else:
                        if d - d == 0.0:
                            self._last_position = d
                        if f - f == 0.0:
                            self._last_force = f
                    fb.age = now - self._t_sent
                    return fb
            if now >= deadline:
                if now - deadline > DEADLINE_SLACK and recv is not self._recv_queued:
                    self._overran(now - deadline)
                stats.timeouts += 1
                return None

    def _accept(self, fb: Feedback | None) -> Feedback | None:
        """Apply the sequence rules and the counters to one decoded feedback.

        This is what :meth:`receive` does with each; ``fb`` if it is delivered, else ``None``.
        """
        if fb is None:
            return None
        ok = self._classify(fb.seq) if self.echoes_seq else self._match(fb)
        if not ok:
            return None
        self.stats.received += 1
        self.link_down = None
        if fb.status & _SENSOR_INVALID:
            fb.displacement = math.nan
        if fb.displacement != fb.displacement or fb.force != fb.force:
            self.stats.invalid_values += 1
        else:
            if math.isfinite(fb.displacement):
                self._last_position = fb.displacement
            if math.isfinite(fb.force):
                self._last_force = fb.force
        fb.age = _perf() - self._t_sent
        return fb

    def _match(self, fb: Feedback) -> bool:
        """Sequence rule without an echo: the first feedback after a command answers it."""
        last = self._last_sent
        if last < 0 or last == self._last_delivered:
            self.stats.duplicates += 1
            return False
        prev = self._last_delivered
        if prev >= 0 and last > prev + 1:
            self.stats.seq_gaps += last - prev - 1
        self._last_delivered = last
        fb.seq = last
        return True

    def _overran(self, late: float) -> None:
        self.stats.deadline_overruns += 1
        if not self._overrun_warned:
            self._overrun_warned = True
            log.warning(
                "driver %s returned %.1f ms past its receive deadline: %s",
                getattr(self, "name", type(self).__name__),
                late * 1e3,
                "reading it through a reader thread from now on"
                if self.reader_fallback
                else "the process was not scheduled in time (counted)",
            )
        if self.reader_fallback:
            self._threaded = True

    @abstractmethod
    def estop(self) -> None:
        """Send the emergency stop with the bus's highest priority.

        The controller latches it and holds position (status ``ESTOP_ACTIVE``) until a command
        with ``enable=False`` acknowledges it.
        """

    def heartbeat(self) -> None:  # noqa: B027 - deliberately a no-op by default
        """Send a keep-alive where the bus needs one; a no-op otherwise."""

    def link_check(self, fs: float) -> str | None:
        """What the link, as measured when it opened, means at loop rate ``fs`` (Hz).

        A one-line warning when the controller cannot carry a step every period (for example
        a Modbus server that answers one request at a time, too slowly for the step's
        requests), said at arming by ``run`` and ``commission``; ``None`` when there is
        nothing to say or nothing was measured (the default).
        """
        return None

    def poll(
        self, timeout: float, receive: Callable[[float], Feedback | None] | None = None
    ) -> Feedback | None:
        """Read the controller's status and where the actuator is, writing no set-point.

        Needed by a driver whose :attr:`atomic_command` is false (:meth:`arm`): a status read
        (Modbus input registers, a CiA 402 TPDO or an SDO upload). Default: ``None`` (this
        driver cannot read without commanding).
        """
        return None

    def arm(
        self, timeout: float, receive: Callable[[float], Feedback | None] | None = None
    ) -> Feedback | None:
        """Start a new run on the controller: send the arming command, forget old sequences.

        The arming command is sequence number 0 with ``enable=False``. A controller (every
        twin) takes it as the start of a new run: it restarts its sequence count (so the run's
        step 0 is a new command, whatever a previous run sent), acknowledges a latched e-stop or
        watchdog trip and holds position; the run's first command with ``enable=True`` then
        enables it. Afterwards this driver's own sequence bookkeeping is reset, so the reply to
        step 0 is not taken for a duplicate of the arming reply.

        **No start jump** (the contract every driver keeps, its own ``arm`` included): arming
        writes no set-point the actuator would follow.

        * :attr:`atomic_command` true (set-point and enable in one frame): the arming command's
          position is not followed by a disabled controller; it carries the last position this
          driver measured (0.0 before any reply), never a target.
        * :attr:`atomic_command` false: the driver first reads where the actuator is without
          writing (:meth:`poll`) and the arming command writes exactly that position as the
          set-point, still disabled; when the position cannot be read, nothing is written and
          ``None`` is returned (the start is refused on hardware).

        In force mode (:meth:`set_control`) the same holds for the force: the arming command
        carries the last measured force (atomic), or the force :meth:`poll` read (not atomic),
        so the first force set-point equals the measured force and goes ahead of the enable.

        The runner then sends the run's first ``enable=True`` command with the position the
        arming reply reported — the start ramp's first point, or without a ramp a step-0
        command within ``start.tolerance`` of it (:mod:`rths_hil.hybrid.phases`) — and keeps
        commanding and heartbeating every period from there to step 0 (``docs/loop.md``).

        Returns the controller's reply to the arming command (its status before the run and
        where the actuator is: the run starts from there), or ``None`` when none came within
        ``timeout`` seconds. ``receive`` replaces :meth:`receive` (the loop passes its own,
        which serves an inline twin first).
        """
        recv = receive or self.receive
        force = self.control == FORCE
        hold = self._last_force if force else self._last_position
        if not self.atomic_command:
            where = self.poll(timeout, receive)
            held = math.nan if where is None else (where.force if force else where.displacement)
            if not math.isfinite(held):
                log.warning(
                    "driver %s: the actuator's %s could not be read before arming; nothing written",
                    getattr(self, "name", type(self).__name__),
                    "force" if force else "position",
                )
                return None
            hold = held
        self.send(0, hold, False)
        fb = recv(timeout)
        self._last_sent = -1
        self._last_delivered = -1
        return fb

    # -- reader thread (drivers that do not honour the deadline) --------------------------------
    def _recv_queued(self, deadline: float) -> Feedback | None:
        q = self._rx_queue
        if q is None or self._rx_thread is None or not self._rx_thread.is_alive():
            self._start_reader()
            q = self._rx_queue
        try:
            if q.queue:  # type: ignore[union-attr]
                item = q.get_nowait()  # type: ignore[union-attr]
            else:
                rem = deadline - _perf()
                item = q.get(True, rem) if rem > 0.0 else None  # type: ignore[union-attr]
        except queue.Empty:
            return None
        if isinstance(item, LinkDown):
            raise item
        return item

    def _start_reader(self) -> None:
        self._rx_queue = queue.Queue()
        self._rx_stop = threading.Event()
        self._rx_thread = threading.Thread(
            target=self._read_loop,
            args=(self._rx_queue, self._rx_stop),
            name=f"driver-{getattr(self, 'name', type(self).__name__)}-reader",
            daemon=True,
        )
        self._rx_thread.start()

    def _read_loop(self, q: queue.Queue, stop: threading.Event) -> None:
        """Feed ``q`` from :meth:`_recv_internal` until stopped or idle for READER_IDLE s."""
        while not stop.is_set():
            now = _perf()
            if now - self._last_receive > READER_IDLE:
                break  # nobody receives any more (the run ended): stop polling
            until = now + READER_POLL
            try:
                fb = self._recv_internal(until)
            except LinkDown as exc:
                q.put(exc)
                stop.wait(READER_POLL)
                continue
            except Exception:  # a broken driver must not kill the loop with a traceback
                log.exception("driver %s: _recv_internal failed", type(self).__name__)
                if hasattr(self, "stats"):
                    self.stats.disconnects += 1
                stop.wait(READER_POLL)
                continue
            if fb is not None:
                q.put(fb)
            elif _perf() < until:
                stop.wait(min(until - _perf(), 1e-3))  # returned early with nothing: no spin
        if self._rx_queue is q:
            self._rx_thread = None

    def stop_reader(self) -> None:
        """Stop the reader thread, if one runs (idempotent; :meth:`__exit__` calls it)."""
        stop, t = self._rx_stop, self._rx_thread
        self._rx_thread = None
        self._rx_queue = None
        if stop is not None:
            stop.set()
        if t is not None and t is not threading.current_thread():
            t.join(timeout=1.0)

    # -- shared sequence bookkeeping ------------------------------------------------------------
    def _classify(self, seq: int) -> bool:
        """Apply the sequence rules to a well-formed feedback; True if it must be delivered."""
        last_sent = self._last_sent
        if seq == last_sent:
            prev = self._last_delivered
            if seq == prev:
                self.stats.duplicates += 1
                return False
            if prev >= 0 and seq > prev + 1:
                self.stats.seq_gaps += seq - prev - 1
            self._last_delivered = seq
            return True
        if seq > last_sent:
            self.stats.count_malformed("unexpected_seq")
        elif seq <= self._last_delivered:
            self.stats.duplicates += 1
        else:
            self.stats.late += 1
        return False

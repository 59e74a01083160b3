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
above the previous delivered one, the missing ones are counted in ``seq_gaps``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from enum import IntFlag
from types import TracebackType
from typing import Any, ClassVar

from rths_hil.errors import InputError

__all__ = [
    "DISPLACEMENT_LSB",
    "FORCE_LSB",
    "INVALID_S32",
    "Driver",
    "DriverStats",
    "Feedback",
    "Status",
    "check_command",
    "extend_seq",
]

#: Fixed-point resolution of displacements on CAN and Modbus (m per count, signed 32 bit).
DISPLACEMENT_LSB = 1e-7
#: Fixed-point resolution of forces on CAN and Modbus (N per count, signed 32 bit).
FORCE_LSB = 1e-2
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
        raw value).
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
    """

    seq: int
    displacement: float
    force: float
    status: int


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


def check_command(seq: int, displacement: float, lsb: float | None = DISPLACEMENT_LSB) -> None:
    """Raise :class:`InputError` for a command that must never reach an actuator.

    Parameters
    ----------
    seq : int
        Step sequence number, must be ≥ 0.
    displacement : float
        Command (m), must be finite and, when ``lsb`` is given, representable in signed 32 bit.
    lsb : float or None
        Fixed-point resolution of the bus (m per count), or ``None`` for a float wire format.
    """
    if seq < 0:
        raise InputError(f"command sequence number must be >= 0, got {seq}")
    if not math.isfinite(displacement):
        raise InputError(f"command displacement for step {seq} is not finite ({displacement})")
    if lsb is not None and abs(displacement) > _S32_MAX * lsb:
        raise InputError(
            f"command displacement {displacement} m for step {seq} exceeds the bus range "
            f"±{_S32_MAX * lsb:.1f} m"
        )


class Driver(ABC):
    """Bus driver: lockstep command/feedback exchange with an actuator controller.

    Subclasses implement :meth:`open`, :meth:`close`, :meth:`send`, :meth:`receive`,
    :meth:`estop` and, where the bus needs it, :meth:`heartbeat`. They use :meth:`_classify`
    for the shared sequence-number rules (module docstring).
    """

    name: ClassVar[str]
    stats: DriverStats

    def __init__(self) -> None:
        self.stats = DriverStats()
        self._last_sent = -1
        self._last_delivered = -1

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
        self.close()

    @abstractmethod
    def send(self, seq: int, displacement: float, enable: bool = True) -> None:
        """Send the command for step ``seq``: ``displacement`` in metres, ``enable`` flag.

        Raises :class:`~rths_hil.errors.InputError` for a non-finite or out-of-range command;
        transport failures are counted (``send_errors``), not raised.
        """

    @abstractmethod
    def receive(self, timeout: float) -> Feedback | None:
        """Wait up to ``timeout`` seconds for the feedback of the last command sent.

        Returns ``None`` on timeout (counted); never raises on bus faults.
        """

    @abstractmethod
    def estop(self) -> None:
        """Send the emergency stop with the bus's highest priority.

        The controller latches it and holds position (status ``ESTOP_ACTIVE``) until a command
        with ``enable=False`` acknowledges it.
        """

    def heartbeat(self) -> None:  # noqa: B027 - deliberately a no-op by default
        """Send a keep-alive where the bus needs one; a no-op otherwise."""

    def arm(
        self, timeout: float, receive: Callable[[float], Feedback | None] | None = None
    ) -> Feedback | None:
        """Start a new run on the controller: send the arming command, forget old sequences.

        The arming command is sequence number 0 with ``enable=False`` (position 0.0 is not
        used: the controller holds). A controller (every twin) takes it as the start of a new
        run: it restarts its sequence count (so the run's step 0 is a new command, whatever a
        previous run sent), acknowledges a latched e-stop or watchdog trip and holds position;
        the run's first command (step 0, ``enable=True``) then enables it. Afterwards this
        driver's own sequence bookkeeping is reset, so the reply to step 0 is not taken for a
        duplicate of the arming reply.

        Returns the controller's reply to the arming command (its status before the run), or
        ``None`` when none came within ``timeout`` seconds. ``receive`` replaces
        :meth:`receive` (the loop passes its own, which serves an inline twin first).
        """
        self.send(0, 0.0, False)
        fb = (receive or self.receive)(timeout)
        self._last_sent = -1
        self._last_delivered = -1
        return fb

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

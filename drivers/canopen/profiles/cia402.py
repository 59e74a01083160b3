"""CiA 402 (drives and motion control): the profile of a drive in cyclic synchronous position
mode (0x6060 = 8).

The tables of :class:`canopen.profiles.p402.State402` (status-word masks, control-word
commands, transition table) are used as they are; this module only chooses the transitions.
A force-controlled channel runs the drive in cyclic synchronous torque mode (CST, 0x6060 = 10)
with the target torque 0x6071 (INTEGER16, per mille of the motor rated torque 0x6076) as the
set-point (:meth:`~.base.Profile.for_control`); the state machine is the same. The bridge's
e-stop is the drive's quick stop, which the drive itself latches.
"""

from __future__ import annotations

from dataclasses import dataclass

from canopen.profiles.p402 import State402

from .base import ENABLED, ESTOP, FAULT, Profile

__all__ = ["CiA402", "state402"]

_SW402 = tuple(State402.SW_MASK.items())
_T402 = State402.TRANSITIONTABLE


def state402(statusword: int) -> str:
    """The CiA 402 FSA state named by ``statusword`` (``State402.SW_MASK``)."""
    for name, (mask, value) in _SW402:
        if statusword & mask == value:
            return name
    return "NOT READY TO SWITCH ON"


@dataclass(frozen=True)
class CiA402(Profile):
    """The CiA 402 device profile (:class:`~.base.Profile` documents the fields)."""

    @property
    def mode_bit(self) -> int | None:
        """The bit of the profile's mode in the supported drive modes 0x6502 (bit 7 cyclic
        synchronous position, 8 velocity, 9 torque), or None."""
        if self.mode is None:
            return None
        return {8: 7, 9: 8, 10: 9}.get(self.mode[2])

    def state(self, statusword: int) -> str:
        """FSA state named by ``statusword``."""
        return state402(statusword)

    def flags(self, state: str, latched: bool) -> int:
        """:class:`~rths_hil.drivers.base.Status` flags of a drive in ``state`` (the quick
        stop is the e-stop, whoever started it)."""
        if state == "OPERATION ENABLED":
            return ENABLED
        if state == "QUICK STOP ACTIVE":
            return ESTOP
        if state in ("FAULT", "FAULT REACTION ACTIVE"):
            return FAULT
        return 0

    def device_latched(self, state: str) -> bool:
        """Whether the drive itself holds a latched stop (quick stop active)."""
        return state == "QUICK STOP ACTIVE"

    def estop_word(self) -> int:
        """Control word of the e-stop: quick stop (0x0002)."""
        return State402.CW_QUICK_STOP

    def cyclic_word(self, state: str, enable: bool, latched: bool) -> int:
        """Control word sent with a step's set-point, from the drive's last reported state.

        ``enable`` walks the FSA one transition per step towards operation (shutdown → switch
        on → enable operation). Without ``enable`` the drive is kept switched on. While
        ``latched`` the quick stop is repeated. A fault is never reset here (only
        :meth:`arm_words` at the start of a run).
        """
        if latched:
            return State402.CW_QUICK_STOP
        if state in ("FAULT", "FAULT REACTION ACTIVE", "NOT READY TO SWITCH ON"):
            return State402.CW_SHUTDOWN  # no effect there: a fault is reset only at arming
        if not enable:
            if state == "OPERATION ENABLED":
                return State402.CW_SWITCH_ON  # disable operation (transition 5): hold
            if state == "SWITCH ON DISABLED":
                return State402.CW_SHUTDOWN
            if state == "QUICK STOP ACTIVE":
                return State402.CW_DISABLE_VOLTAGE  # acknowledge (transition 12)
            return State402.CW_SWITCH_ON
        if state == "OPERATION ENABLED":
            return State402.CW_OPERATION_ENABLED
        if state == "QUICK STOP ACTIVE":
            return State402.CW_QUICK_STOP  # a device-initiated quick stop stays until acknowledged
        nxt = State402.next_state_indirect(state)
        return _T402.get((state, nxt), State402.CW_SHUTDOWN)

    def arm_words(self, state: str) -> list[int]:
        """Control words (written by SDO) that bring a drive from ``state`` to switched on.

        Fault → fault reset (0x0000 then 0x0080, a rising edge) → switch on disabled →
        shutdown → switch on; quick stop active → disable voltage first.
        """
        words: list[int] = []
        if state in ("FAULT", "FAULT REACTION ACTIVE"):
            words += [State402.CW_DISABLE_VOLTAGE, State402.CW_SWITCH_ON_DISABLED]
        elif state == "QUICK STOP ACTIVE":
            words.append(State402.CW_DISABLE_VOLTAGE)
        if state == "OPERATION ENABLED":
            return [State402.CW_SWITCH_ON]
        return [*words, State402.CW_SHUTDOWN, State402.CW_SWITCH_ON]

    def disable_words(self, state: str) -> list[int]:
        """Control words (by SDO) handing the drive back disabled at a normal end.

        Shutdown (→ ready to switch on) then disable voltage (→ switch on disabled; from quick
        stop active it is the acknowledgement, so nothing stays latched).
        """
        if state in ("FAULT", "FAULT REACTION ACTIVE", "QUICK STOP ACTIVE"):
            return [State402.CW_DISABLE_VOLTAGE]
        return [State402.CW_SHUTDOWN, State402.CW_DISABLE_VOLTAGE]

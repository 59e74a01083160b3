"""CiA 408 (fluid power: proportional valves and hydrostatic drives): the profile of a valve
axis with its set-point over the bus.

Device control word 0x6040 bits 0–3 ``D`` (disabled), ``H`` (hold), ``M`` (device mode
active), ``R`` (reset fault, rising edge), device status word 0x6041 bits 0–3 ``D H M R``
(``R`` = ready, cleared in the fault states); axis position set-point 0x6600:01 and actual
value 0x6601:01 (INTEGER32), device mode 0x6042 = 1 (set-point via the bus). The 408 FSA has
no quick-stop state: the bridge's e-stop is ``HOLD`` (the axis holds at its hold set-point),
latched by the driver (:mod:`rths_hil.drivers.canopen.driver`).
"""

from __future__ import annotations

from dataclasses import dataclass

from .base import ENABLED, ESTOP, FAULT, Profile

__all__ = [
    "CW408_ACTIVE",
    "CW408_DISABLED",
    "CW408_HOLD",
    "CW408_RESET",
    "STATES408",
    "SW408",
    "CiA408",
    "state408",
]

#: Status word bits 0-3 R M H D → state (Moog ACV manual, Fig. 19 / Table 31).
STATES408 = {
    0b0000: "NOT READY",  # also FAULT INIT; both: nothing active, nothing to hold
    0b1000: "INIT",
    0b1001: "DISABLED",
    0b1011: "HOLD",
    0b1111: "ACTIVE",
    0b0001: "FAULT DISABLED",
    0b0011: "FAULT HOLD",
    0b0111: "FAULT REACTION",
}
#: 408 control words (bits M H D; bit 3 R resets a fault on its rising edge).
CW408_DISABLED, CW408_HOLD, CW408_ACTIVE, CW408_RESET = 0x01, 0x03, 0x07, 0x08
#: 408 status word of each state (bits R M H D), for the twin.
SW408 = {name: code for code, name in STATES408.items()}


def state408(statusword: int) -> str:
    """The CiA 408 device state named by the low four bits of ``statusword``."""
    return STATES408.get(statusword & 0x0F, "NOT READY")


@dataclass(frozen=True)
class CiA408(Profile):
    """The CiA 408 device profile (:class:`~.base.Profile` documents the fields)."""

    def state(self, statusword: int) -> str:
        """Device state named by ``statusword``."""
        return state408(statusword)

    def flags(self, state: str, latched: bool) -> int:
        """:class:`~rths_hil.drivers.base.Status` flags of a device in ``state``: ``HOLD`` is
        the e-stop only while the bridge latched it."""
        if state.startswith("FAULT"):
            return FAULT
        if state == "ACTIVE":
            return ENABLED
        if latched and state == "HOLD":
            return ESTOP
        return 0

    def estop_word(self) -> int:
        """Control word of the e-stop: hold (0x0003)."""
        return CW408_HOLD

    def cyclic_word(self, state: str, enable: bool, latched: bool) -> int:
        """Control word sent with a step's set-point: active with ``enable``, hold without it
        or while the e-stop is latched."""
        if latched or not enable:
            return CW408_HOLD
        return CW408_ACTIVE

    def arm_words(self, state: str) -> list[int]:
        """Control words (written by SDO) that bring a device from ``state`` to holding: a
        reset (bit 3 rising edge) from a fault state, then hold."""
        if state.startswith("FAULT"):
            return [CW408_HOLD, CW408_HOLD | CW408_RESET, CW408_HOLD]
        return [CW408_HOLD]

    def disable_words(self, state: str) -> list[int]:
        """Control words (by SDO) handing the device back disabled at a normal end."""
        return [CW408_DISABLED]

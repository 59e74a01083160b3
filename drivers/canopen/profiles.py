"""The two CANopen device profiles the driver speaks: CiA 402 and CiA 408.

Each :class:`Profile` names the objects used (index, sub-index), the start-up writes and the
device finite state automaton (FSA): how a status word maps to a state, how a state maps to the
bridge's :class:`~rths_hil.drivers.base.Status` flags, and which control word leads from a state
towards the one the bridge wants. Object indices and state codings are cited in
``docs/canopen.md``.

**CiA 402** (drives and motion control, cyclic synchronous position mode, 0x6060 = 8): the
tables of :class:`canopen.profiles.p402.State402` (status-word masks, control-word commands,
transition table) are used as they are; this module only chooses the transitions. A
force-controlled channel runs the drive in cyclic synchronous torque mode (CST, 0x6060 = 10)
with the target torque 0x6071 (INTEGER16, per mille of the motor rated torque 0x6076) as the
set-point (:meth:`Profile.for_control`); the state machine is the same.

**CiA 408** (fluid power: proportional valves and hydrostatic drives): device control word
0x6040 bits 0–3 ``D`` (disabled), ``H`` (hold), ``M`` (device mode active), ``R`` (reset fault,
rising edge), device status word 0x6041 bits 0–3 ``D H M R`` (``R`` = ready, cleared in the
fault states); axis position set-point 0x6600:01 and actual value 0x6601:01 (INTEGER32), device
mode 0x6042 = 1 (set-point via the bus). The 408 FSA has no quick-stop state: the bridge's
e-stop is ``HOLD`` (the axis holds at its hold set-point), latched by the driver (module
:mod:`rths_hil.drivers.canopen`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from canopen.profiles.p402 import State402

from ..base import Status

__all__ = ["PROFILES", "Profile", "state402", "state408"]

_ENABLED = int(Status.ENABLED)
_ESTOP = int(Status.ESTOP_ACTIVE)
_FAULT = int(Status.FAULT)

# ---------------------------------------------------------------------------------------------
# CiA 402
_SW402 = tuple(State402.SW_MASK.items())
_T402 = State402.TRANSITIONTABLE


def state402(statusword: int) -> str:
    """The CiA 402 FSA state named by ``statusword`` (``State402.SW_MASK``)."""
    for name, (mask, value) in _SW402:
        if statusword & mask == value:
            return name
    return "NOT READY TO SWITCH ON"


# ---------------------------------------------------------------------------------------------
# CiA 408: status word bits 0-3 R M H D → state (Moog ACV manual, Fig. 19 / Table 31)
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
class Profile:
    """What the driver needs to know about one device profile.

    Attributes
    ----------
    name : str
        ``cia402`` or ``cia408``.
    number : int
        Profile number in the low 16 bits of the device type 0x1000 (402 or 408).
    control, status, setpoint, actual : tuple of (int, int)
        (index, sub-index) of the control word, status word, position set-point and actual
        position.
    mode : tuple of (int, int, int) or None
        Object written at start-up (pre-operational) and its value: 402 modes of operation
        0x6060 = 8 (cyclic synchronous position), 408 device mode 0x6042 = 1 (set-point via bus).
    control_mode : str
        What the set-point is: ``"displacement"`` (a position, counts) or ``"force"`` (402:
        the target torque of cyclic synchronous torque, per mille of the rated torque).
    setpoint_name : str
        The set-point object's name, for messages.
    force : tuple or None
        The force-control variant of the profile: (set-point object, its name, mode object
        and value) — 402: target torque 0x6071, 0x6060 = 10 (CST); ``None`` where the
        profile has no force control the driver speaks.
    """

    name: str
    number: int
    control: tuple[int, int]
    status: tuple[int, int]
    setpoint: tuple[int, int]
    actual: tuple[int, int]
    mode: tuple[int, int, int] | None
    control_mode: str = "displacement"
    setpoint_name: str = "position set-point"
    force: tuple[tuple[int, int], str, tuple[int, int, int]] | None = None

    def for_control(self, mode: str) -> Profile | None:
        """The profile of a channel in wire mode ``mode``: this one for ``"displacement"``;
        for ``"force"`` the force-control variant (402: CST, set-point 0x6071, mode 10), or
        ``None`` when the profile has none."""
        if mode != "force":
            return self
        if self.force is None:
            return None
        setpoint, name, mode_obj = self.force
        return replace(
            self, setpoint=setpoint, setpoint_name=name, mode=mode_obj, control_mode="force"
        )

    @property
    def mode_bit(self) -> int | None:
        """The bit of the profile's mode in the supported drive modes 0x6502 (402: bit 7
        cyclic synchronous position, 8 velocity, 9 torque), or None."""
        if self.number != 402 or self.mode is None:
            return None
        return {8: 7, 9: 8, 10: 9}.get(self.mode[2])

    def state(self, statusword: int) -> str:
        """FSA state named by ``statusword``."""
        return state402(statusword) if self.number == 402 else state408(statusword)

    def flags(self, state: str, latched: bool) -> int:
        """:class:`Status` flags of a device in ``state`` (``latched``: the bridge's e-stop)."""
        if self.number == 402:
            if state == "OPERATION ENABLED":
                return _ENABLED
            if state == "QUICK STOP ACTIVE":
                return _ESTOP
            if state in ("FAULT", "FAULT REACTION ACTIVE"):
                return _FAULT
            return 0
        if state.startswith("FAULT"):
            return _FAULT
        if state == "ACTIVE":
            return _ENABLED
        if latched and state == "HOLD":
            return _ESTOP
        return 0

    def is_fault(self, state: str) -> bool:
        """Whether ``state`` is a fault state (only a reset at arming leaves it)."""
        return state.startswith("FAULT")

    def device_latched(self, state: str) -> bool:
        """Whether the device itself holds a latched stop (402 quick stop active)."""
        return state == "QUICK STOP ACTIVE"

    def estop_word(self) -> int:
        """Control word of the e-stop: 402 quick stop (0x0002), 408 hold (0x0003)."""
        return State402.CW_QUICK_STOP if self.number == 402 else CW408_HOLD

    def cyclic_word(self, state: str, enable: bool, latched: bool) -> int:
        """Control word sent with a step's set-point, from the device's last reported state.

        ``enable`` walks the FSA one transition per step towards operation (402: shutdown →
        switch on → enable operation; 408: active). Without ``enable`` the device is kept
        powered and holding (402 switched on, 408 hold). While ``latched`` the e-stop word is
        repeated. A fault is never reset here (only :meth:`arm_words` at the start of a run).
        """
        if self.number == 408:
            if latched or not enable:
                return CW408_HOLD
            return CW408_ACTIVE
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
        """Control words (written by SDO) that bring a device from ``state`` to holding.

        402: fault → fault reset (0x0000 then 0x0080, a rising edge) → switch on disabled →
        shutdown → switch on; quick stop active → disable voltage first. 408: reset (bit 3
        rising edge) from a fault state, then hold.
        """
        if self.number == 408:
            if state.startswith("FAULT"):
                return [CW408_HOLD, CW408_HOLD | CW408_RESET, CW408_HOLD]
            return [CW408_HOLD]
        words: list[int] = []
        if state in ("FAULT", "FAULT REACTION ACTIVE"):
            words += [State402.CW_DISABLE_VOLTAGE, State402.CW_SWITCH_ON_DISABLED]
        elif state == "QUICK STOP ACTIVE":
            words.append(State402.CW_DISABLE_VOLTAGE)
        if state == "OPERATION ENABLED":
            return [State402.CW_SWITCH_ON]
        return [*words, State402.CW_SHUTDOWN, State402.CW_SWITCH_ON]

    def disable_words(self, state: str) -> list[int]:
        """Control words (by SDO) handing the device back disabled at a normal end.

        402: shutdown (→ ready to switch on) then disable voltage (→ switch on disabled; from
        quick stop active it is the acknowledgement, so nothing stays latched). 408: disabled.
        """
        if self.number == 408:
            return [CW408_DISABLED]
        if state in ("FAULT", "FAULT REACTION ACTIVE", "QUICK STOP ACTIVE"):
            return [State402.CW_DISABLE_VOLTAGE]
        return [State402.CW_SHUTDOWN, State402.CW_DISABLE_VOLTAGE]


#: The profiles by name (``driver.connection.profile``).
PROFILES: dict[str, Profile] = {
    "cia402": Profile(
        "cia402",
        402,
        (0x6040, 0),
        (0x6041, 0),
        (0x607A, 0),
        (0x6064, 0),
        (0x6060, 0, 8),
        force=((0x6071, 0), "target torque", (0x6060, 0, 10)),
    ),
    "cia408": Profile(
        "cia408", 408, (0x6040, 0), (0x6041, 0), (0x6600, 1), (0x6601, 1), (0x6042, 0, 1)
    ),
}

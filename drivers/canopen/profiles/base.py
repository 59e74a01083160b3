"""The device profile the CANopen driver speaks through: what every profile says.

A :class:`Profile` names the objects used (index, sub-index), the start-up writes and the
device finite state automaton (FSA): how a status word maps to a state, how a state maps to
the bridge's :class:`~rths_hil.drivers.base.Status` flags, and which control word leads from a
state towards the one the bridge wants. Each device profile is a subclass in a module of its
own, as the ``canopen`` library keeps ``canopen.profiles.p402``: :mod:`.cia402` (drives and
motion control), :mod:`.cia408` (fluid power). Object indices and state codings are cited in
``docs/canopen.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ...base import Status

__all__ = ["ENABLED", "ESTOP", "FAULT", "Profile"]

#: The bridge's status flags as integers (what :meth:`Profile.flags` returns).
ENABLED = int(Status.ENABLED)
ESTOP = int(Status.ESTOP_ACTIVE)
FAULT = int(Status.FAULT)


@dataclass(frozen=True)
class Profile:
    """What the driver needs to know about one device profile (a subclass per profile).

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
        """The bit of the profile's mode in the supported drive modes 0x6502, or None."""
        return None

    def state(self, statusword: int) -> str:
        """FSA state named by ``statusword``."""
        raise NotImplementedError

    def flags(self, state: str, latched: bool) -> int:
        """:class:`Status` flags of a device in ``state`` (``latched``: the bridge's e-stop)."""
        raise NotImplementedError

    def is_fault(self, state: str) -> bool:
        """Whether ``state`` is a fault state (only a reset at arming leaves it)."""
        return state.startswith("FAULT")

    def device_latched(self, state: str) -> bool:
        """Whether the device itself holds a latched stop (none unless the profile has one)."""
        return False

    def estop_word(self) -> int:
        """Control word of the e-stop."""
        raise NotImplementedError

    def cyclic_word(self, state: str, enable: bool, latched: bool) -> int:
        """Control word sent with a step's set-point, from the device's last reported state.

        ``enable`` walks the FSA one transition per step towards operation. Without
        ``enable`` the device is kept powered and holding. While ``latched`` the e-stop word is
        repeated. A fault is never reset here (only :meth:`arm_words` at the start of a run).
        """
        raise NotImplementedError

    def arm_words(self, state: str) -> list[int]:
        """Control words (written by SDO) that bring a device from ``state`` to holding."""
        raise NotImplementedError

    def disable_words(self, state: str) -> list[int]:
        """Control words (by SDO) handing the device back disabled at a normal end."""
        raise NotImplementedError

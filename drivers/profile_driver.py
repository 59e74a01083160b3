"""What the drivers of a lab's controller profile share
(:class:`~rths_hil.drivers.can.profile.CANProfileDriver`,
:class:`~rths_hil.drivers.modbus.profile.ModbusProfileDriver`): the profile, loaded and checked
for the driver's protocol, and the control mode that picks the profile's set-point role."""

from __future__ import annotations

from typing import Any, ClassVar

from rths_hil.errors import InputError

from .base import Driver
from .profile import CONTROL_MODES, load_profile

__all__ = ["ProfileDriver"]


class ProfileDriver(Driver):
    """Base of a driver for a controller described by a profile (:mod:`.profile`).

    A subclass calls :meth:`_load_profile` in its ``__init__`` and defines
    :meth:`_use_setpoint` (what it precomputes for the set-point role of :attr:`profile`).

    Attributes
    ----------
    profile : ModbusProfile or CANProfile
        The profile of the channel's control mode (:meth:`set_control`).
    """

    command_lsb: ClassVar[float | None] = None  # the profile's set-point range is checked
    #: force when the profile maps ``roles.force_setpoint`` (:meth:`set_control`)
    control_modes: ClassVar[tuple[str, ...]] = CONTROL_MODES

    profile: Any
    _base_profile: Any

    def _load_profile(self, profile: str, fmt: type, what: str) -> Any:
        """The profile at ``profile``, refused unless a ``fmt`` (``what``: its protocol's
        name in the refusal); it becomes :attr:`profile`."""
        prof = load_profile(profile)
        if not isinstance(prof, fmt):
            raise InputError(f"{self.name} driver: profile {profile} is not a {what} profile")
        self.profile = self._base_profile = prof
        return prof

    def _use_setpoint(self) -> None:
        """Precompute what the set-point role of :attr:`profile` needs on the wire."""
        raise NotImplementedError

    def set_control(self, mode: str) -> None:
        """Select the wire mode before :meth:`open` (:meth:`Driver.set_control`).

        ``"force"`` carries the force set-point (N) in the profile's ``roles.force_setpoint``
        every step instead of ``roles.setpoint``; a profile without it is refused with one line.
        """
        super().set_control(mode)
        try:
            prof = self._base_profile.for_control(mode)
        except InputError as exc:
            self.control = "displacement"
            raise InputError(f"{self.name} driver: {exc}") from None
        if prof is not self.profile:
            self.profile = prof
            self._use_setpoint()

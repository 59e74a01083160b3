"""The two CANopen device profiles the driver speaks: CiA 402 and CiA 408.

:mod:`.base` holds what every profile says (:class:`Profile`: the objects, the start-up
writes, the FSA's questions), :mod:`.cia402` and :mod:`.cia408` each profile's answers, as the
``canopen`` library keeps its CiA 402 support in ``canopen.profiles.p402``. Object indices and
state codings are cited in ``docs/canopen.md``.
"""

from __future__ import annotations

from .base import Profile
from .cia402 import CiA402, state402
from .cia408 import SW408, CiA408, state408

__all__ = ["PROFILES", "SW408", "CiA402", "CiA408", "Profile", "state402", "state408"]

#: The profiles by name (``driver.connection.device_profile``).
PROFILES: dict[str, Profile] = {
    "cia402": CiA402(
        "cia402",
        402,
        (0x6040, 0),
        (0x6041, 0),
        (0x607A, 0),
        (0x6064, 0),
        (0x6060, 0, 8),
        force=((0x6071, 0), "target torque", (0x6060, 0, 10)),
    ),
    "cia408": CiA408(
        "cia408", 408, (0x6040, 0), (0x6041, 0), (0x6600, 1), (0x6601, 1), (0x6042, 0, 1)
    ),
}

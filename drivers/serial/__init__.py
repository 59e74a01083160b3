"""The serial protocol's package: :mod:`.framing` (the COBS/CRC frames the driver and its twin
share), :mod:`.driver` (:class:`SerialDriver`) and :mod:`.linkbudget` (its link model), and
:data:`PROTOCOL`, its planning facts (:mod:`rths_hil.drivers.protocol`)."""

from ..protocol import Protocol
from . import linkbudget
from .driver import SerialDriver

__all__ = ["PROTOCOL", "SerialDriver"]

#: The serial protocol's planning facts: the hooks of its link model (:mod:`.linkbudget`).
PROTOCOL = Protocol.from_hooks("serial", SerialDriver, linkbudget)

"""The serial protocol's package: :mod:`.framing` (the COBS/CRC frames the driver and its twin
share), :mod:`.driver` (:class:`SerialDriver`) and :mod:`.linkbudget` (its link model)."""

from .driver import SerialDriver

__all__ = ["SerialDriver"]

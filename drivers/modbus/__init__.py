"""Modbus (TCP and RTU): the protocol's package, as pymodbus shares one framer and one PDU layer
between its client and its server.

* :mod:`.transport` — the client's connection (:class:`~.transport.Link`: a TCP connection,
  shared by the units on one server, or a serial line; the e-stop's own connection), the
  framers and the request checks the twins' servers use too.
* :mod:`.layout` — a register map's precompiled wire layouts, each checked against pymodbus.
* :mod:`.driver` — :class:`ModbusDriver`, the built-in register map (one FC 23 per step).
* :mod:`.profile_format` — the register-map profile format (``ModbusProfile``).
* :mod:`.profile` — :class:`ModbusProfileDriver`, a lab's own register map from a profile;
  :mod:`.requests` (its requests on the connection: pipelined, or one at a time and the
  queue) and :mod:`.estop` (its e-stop path) are its bases.
* :mod:`.options` — the ``rths-hil twin serve`` options of a Modbus twin.
* :mod:`.linkbudget` — the Modbus link model (RTU transactions and silences, TCP segments)
  and the planning facts of the protocol (:data:`PROTOCOL`).

The twins (:mod:`rths_hil.sim_backends.endpoints.modbus`,
:mod:`rths_hil.sim_backends.endpoints.modbus_profile`) import their framing from here.
"""

from ..base import Driver
from ..protocol import Protocol
from . import linkbudget, options
from .driver import (
    COIL_ESTOP,
    FORCE_LSB,
    READ_ADDRESS,
    READ_COUNT,
    REG,
    WRITE_ADDRESS,
    WRITE_COUNT,
    ModbusDriver,
    feedback_crc,
)
from .profile import ModbusProfileDriver
from .transport import MAX_UNIT, Link

__all__ = [
    "COIL_ESTOP",
    "FORCE_LSB",
    "MAX_UNIT",
    "PROTOCOL",
    "READ_ADDRESS",
    "READ_COUNT",
    "REG",
    "WRITE_ADDRESS",
    "WRITE_COUNT",
    "Link",
    "ModbusDriver",
    "ModbusProfileDriver",
    "feedback_crc",
]


def _profile_driver() -> type[Driver]:
    """A lab's own register map: :class:`~.profile.ModbusProfileDriver`."""
    return ModbusProfileDriver


#: The Modbus protocol's planning facts (:mod:`rths_hil.drivers.protocol`): the hooks of its link
#: model (:mod:`.linkbudget`) and what else differs from the defaults.
PROTOCOL = Protocol.from_hooks(
    "modbus",
    ModbusDriver,
    linkbudget,
    profile_protocol="modbus",
    profile_driver=_profile_driver,
    serve_options=options.serve_options,
)

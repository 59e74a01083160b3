"""Bus drivers between the bridge and an actuator controller.

One package per protocol — ``rths_hil.drivers.can`` (python-can + a shipped DBC read by
cantools), ``rths_hil.drivers.canopen`` (CiA 402 / CiA 408 through the ``canopen`` library),
``rths_hil.drivers.modbus`` (pymodbus, TCP and RTU), ``rths_hil.drivers.serial`` (pyserial, COBS
frames with a CRC) — each with its driver(s), its link model and its ``PROTOCOL`` descriptor
(``rths_hil.drivers.protocol.Protocol``: what the plan knows before a bus is opened), behind one
small bus contract (``rths_hil.drivers.base.Driver``) and a registry by name
(``rths_hil.drivers.registry``) that also loads third-party drivers from the
``rths_hil.drivers`` entry-point group.
"""

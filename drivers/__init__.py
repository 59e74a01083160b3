"""Bus drivers between the bridge and an actuator controller.

One module (or folder) per bus — ``rths_hil.drivers.can`` (python-can + a shipped DBC read by
cantools), ``rths_hil.drivers.modbus`` (pymodbus, TCP and RTU), ``rths_hil.drivers.serial``
(pyserial, COBS frames with a CRC) — behind one small interface (``rths_hil.drivers.base.Driver``)
and a registry by name that also loads third-party drivers from the ``rths_hil.drivers`` entry-point
group.
"""

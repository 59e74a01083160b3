"""Twin endpoints: one module per protocol's twin, each the server side of its driver's wire.

The module named after a driver shipped in ``rths_hil.drivers`` (``can.py`` for ``drivers/can/``)
is that driver's twin, and declares itself at its top level; that line is all the
registration there is (:func:`rths_hil.sim_backends.registry.builtin_twins` lists the modules,
:func:`~rths_hil.sim_backends.registry.builtin_entry` imports the one a twin needs)::

    from ..registry import TwinEntry

    TWIN = TwinEntry("rths_hil.sim_backends.endpoints.mine:MyTwin")

naming the endpoint class (a :class:`~rths_hil.sim_backends.endpoints.base.TwinEndpoint`
subclass) and what :class:`~rths_hil.sim_backends.registry.TwinEntry` says of it (``seq_bits``,
``transports``, ``fresh_channel``). The other modules here (``base``, ``can_profile``,
``modbus_profile``, ``modbus_server``, ``nullmodem``) are what those twins are made of.
"""

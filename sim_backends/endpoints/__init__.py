"""Twin endpoints: one module per protocol's twin, each the server side of its driver's wire.

An endpoint module declares itself at its top level, and that line is all the registration
there is (:func:`rths_hil.sim_backends.registry.builtin_twins` reads it from the module's
source, without importing the module, in every folder of this package's ``__path__``)::

    from ..registry import TwinEntry

    TWIN = TwinEntry("rths_hil.sim_backends.endpoints.mine:MyTwin", driver="mine")

with literal arguments: the endpoint class (a
:class:`~rths_hil.sim_backends.endpoints.base.TwinEndpoint` subclass), the driver whose protocol
it speaks, and what :class:`~rths_hil.sim_backends.registry.TwinEntry` says of it (``seq_bits``,
``transports``, ``fresh_channel``).
"""

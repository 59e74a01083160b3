"""Virtual servo-hydraulic twins: actuator models behind real protocol endpoints.

A twin is a plant (:class:`rths_hil.sim_backends.plant.TwinPlant`: an actuator model with the
transport delay and gain of the FEI paper's Fig. 4.1, servo dynamics, an effects catalogue, a
specimen model for the force, sensor noise) behind a protocol endpoint that speaks a driver's real
protocol over a real transport (a python-can bus, a pymodbus server on 127.0.0.1, a
pseudo-terminal). Tests, CI and an operator's dry run need no hardware. Endpoints and actuator
models are registered in :mod:`rths_hil.sim_backends.registry`, effects in
:data:`rths_hil.sim_backends.effects.EFFECTS`.
"""

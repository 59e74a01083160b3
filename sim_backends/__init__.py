"""Virtual servo-hydraulic twins: actuator models behind real protocol endpoints.

A twin is an actuator model (delay + gain per the FEI paper's Fig. 4.1, servo dynamics, an effects
catalogue, a specimen model for the force) plus a protocol endpoint that speaks a driver's real
protocol over a real transport (a python-can bus, a pymodbus server on 127.0.0.1, a
pseudo-terminal). Tests, CI and an operator's dry run need no hardware.
"""

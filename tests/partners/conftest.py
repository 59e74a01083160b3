"""Fixtures of the conformance partners (each its own process)."""

from tests.partners.modbus_fixtures import modbus_servo  # noqa: F401

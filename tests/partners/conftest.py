"""Fixtures of the conformance partners (each its own process)."""

from tests.partners.canopen_fixtures import cia402_drive  # noqa: F401
from tests.partners.modbus_fixtures import modbus_servo  # noqa: F401

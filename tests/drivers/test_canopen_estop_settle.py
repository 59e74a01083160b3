"""The CiA 402 driver's e-stop settle: the device's answer to the e-stop's own SYNC (sent for
the last step, already delivered) tells that the device reports QUICK STOP ACTIVE, so the
confirmation poll after an e-stop does not wait out ``ESTOP_SETTLE`` on a prompt device."""

from __future__ import annotations

import logging
import time

import pytest
from rths_hil.drivers.canopen import ESTOP_SETTLE
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.twin import default_plant, start_twin

pytestmark = pytest.mark.timing  # a twin on a bus and the wall clock


def test_estop_state_seen_from_the_estop_sync_answer(caplog):
    with start_twin("canopen", default_plant(), device_profile="cia402") as twin:
        drv = create_driver("canopen", **twin.connection)
        drv.open()
        try:
            assert drv.arm(1.0) is not None
            for k in range(5):
                drv.send(k, 0.0, True)
                assert drv.receive(1.0) is not None
            drv.estop()
            with caplog.at_level(logging.WARNING, logger="rths_hil.drivers.canopen"):
                t0 = time.perf_counter()
                drv.send(5, 0.0, True)  # the loop's confirmation poll
                settle = time.perf_counter() - t0
                fb = drv.receive(1.0)
        finally:
            drv.close()
    assert fb is not None and fb.status & 0x02  # ESTOP_ACTIVE
    assert twin.history[-2:] == ["OPERATION ENABLED", "QUICK STOP ACTIVE"]  # left latched
    assert "did not report the e-stop state" not in caplog.text
    assert settle < ESTOP_SETTLE

"""Twins served as their own processes over python-can's ``udp_multicast`` interface (CAN
frames in UDP datagrams of one multicast group; on one machine they stay on the loopback): the
bridge reads that bus from the loop's thread, as it reads SocketCAN (no notifier thread), and a
lockstep run against a served CAN and CANopen twin completes on a reply at every step and hands
the controller back disabled."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from rths_hil.drivers.can import TIMEOUT_HONOURED, release_bus, shared_bus

from tests.helpers.procs import ServedTwin, bridge_cmd

# against the wall clock or with other processes: run apart from the parallel tests
# (the "timing" marker, pyproject.toml; make test)
pytestmark = pytest.mark.timing

# each test its own group, apart from the default one a lab's dry run would use
GROUPS = {"can": "239.74.163.201", "canopen": "239.74.163.202"}


def test_the_bridge_reads_udp_multicast_from_the_loops_thread():
    """``recv`` waits in ``select`` with the time left: no notifier thread is started for it
    (the serial line, whose read ignores the timeout, gets one)."""
    assert "udp_multicast" in TIMEOUT_HONOURED
    share = shared_bus("bridge", "udp_multicast", "239.74.163.203")
    try:
        assert share.notifier is None and share.reader is None
        assert share.bus.recv(0.0) is None  # nothing on a fresh group
    finally:
        release_bus(share)


@pytest.mark.parametrize("driver", sorted(GROUPS))
def test_lockstep_run_against_a_twin_served_over_udp_multicast(driver, tmp_path):
    twin = ServedTwin(
        "--driver", driver, "--interface", "udp_multicast", "--channel", GROUPS[driver]
    )  # fmt: skip
    try:
        conn = twin.connection
        assert conn["interface"] == "udp_multicast" and conn["channel"] == GROUPS[driver]
        out = tmp_path / "run"
        cmd = bridge_cmd(driver, conn, out, "--lockstep", "--duration", "0.5")
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        rec = np.load(out / "record.npy")
        assert len(rec) == 512 and rec["feedback_ok"].all()
        assert np.ptp(rec["measured"]) > 1e-5  # the served plant moved (80 µm in 0.5 s)
        events = [json.loads(x) for x in (out / "events.jsonl").read_text().splitlines()]
        end = [e for e in events if e["kind"] == "end"]
        assert end and end[-1]["status"] == "completed", events[-3:]
        assert end[-1]["handback"] is True  # the controller replied disabled, not latched
    finally:
        twin.stop()

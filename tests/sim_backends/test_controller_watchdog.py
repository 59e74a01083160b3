"""Controller-side watchdog: every twin holds and latches its e-stop when the bridge dies.

The twin runs as its own process (``rths-hil twin serve``), the bridge (``rths-hil run``) as
another; the bridge is killed with SIGKILL in the middle of a run, so it sends nothing more —
no e-stop, no close. The twin must latch within its watchdog timeout (measured from the kill to
the twin's log line), report it over its own protocol (Modbus: coil 0 and register 17 read
with a plain pymodbus client; serial and CAN: the status of the next reply), hold its position,
and accept a new run afterwards (the new run arms it and starts its sequence afresh). CAN
crosses processes over python-can's serial-line interfaces (``serial``
and ``slcan``) on the served twin's null-modem pair of pseudo-terminals, with a paced bridge
(python-can's virtual bus reaches only buses in the same process, and SocketCAN is not
available here). The in-process twins, threaded, are checked the same way with a bridge that
falls silent.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from rths_hil.drivers.base import Status
from rths_hil.drivers.registry import create_driver

from rths_hil.records.recorder import read_run
from tests.helpers.procs import (
    LATCH_LINE,
    ROOT,
    ServedTwin,
    bridge_cmd,
    kill9,
    run_bridge,
    start_bridge,
    wait_rows,
)

# against the wall clock or with other processes: run apart from the parallel tests
# (the "timing" marker, pyproject.toml; make test)
pytestmark = pytest.mark.timing

# The twins' watchdog in these tests (s). Served twins: 0.25 s, so that a lockstep bridge
# descheduled for tens of ms on a loaded 2-core machine is not taken for a dead one; in-process
# twins fed by a tight loop: 0.1 s.
TIMEOUT = 0.25
TIMEOUT_IN = 0.1
# kill → latch: the timeout since the last command, plus the watchdog's poll (timeout / 4, at
# most 50 ms), plus the log line's trip through a pipe, on a loaded machine
SLACK = 0.25
# steps the bridge takes before it is killed (the twin enabled and fed by then)
ROWS = 300
LATCHED = int(Status.ESTOP_ACTIVE | Status.WATCHDOG)


def _second_run(driver, connection, out, *overrides):
    """A new lockstep run against the same twin: must arm it and complete (0.25 s: 256 steps,
    each on a reply). In this process: a new run is what the twin must accept, not a new
    process."""
    r = run_bridge(driver, connection, out, *overrides, mode="lockstep", duration=0.25)
    assert r.result.status == "completed", r.result.trip
    arm = next(e for e in r.run.events if e["kind"] == "arm")
    return arm, r.run.record


@pytest.fixture()
def modbus_twin():
    twin = ServedTwin(
        "--driver", "modbus", "--heartbeat-timeout", f"{TIMEOUT * 1e3:g}ms"
    )  # fmt: skip
    yield twin
    twin.stop()


MAP = ROOT / "examples" / "controllers" / "modbus_map.toml"
DBC = ROOT / "examples" / "controllers" / "can_dbc.toml"


@pytest.fixture()
def modbus_map_twin():
    twin = ServedTwin(
        "--driver", "modbus", "--profile", str(MAP), "--heartbeat-timeout", f"{TIMEOUT * 1e3:g}ms"
    )  # fmt: skip
    yield twin
    twin.stop()


@pytest.fixture()
def serial_twin():
    twin = ServedTwin(
        "--driver", "serial", "--transport", "tcp", "--heartbeat-timeout", f"{TIMEOUT * 1e3:g}ms"
    )  # fmt: skip
    yield twin
    twin.stop()


# a paced bridge that keeps stepping on a loaded 2-core machine: the rule under test is the
# twin's (the bridge's estimators off); its own watchdog at 1 s (at load 5 the CAN bridge once
# saw 0.2 s without a good reply), overruns counted, not tripped
PACED = [
    "--set", "fei.enabled=false",
    "--set", "kalman.enabled=false",
    "--set", "safety.max_overruns=1000000",
    "--set", "safety.watchdog_timeout=1.0",
    "--set", "safety.watchdog_missed=1000000",
]  # fmt: skip
# python-can interface over the served CAN twin's pseudo-terminals → how the bridge runs and
# the twin's watchdog (s). ``serial`` answers in ≈ 0.3 ms: paced at 1024 Hz. ``slcan`` (ASCII,
# parsed a byte at a time in both processes) answers in ≈ 0.6–0.9 ms, too slow for a paced
# 1024 Hz loop here, and its CPU-hungry lockstep bridge was starved for > 0.25 s on the loaded
# 2-core machine: lockstep, with the served twin's default watchdog (0.5 s).
CAN_INTERFACES = {"serial": (["--paced", *PACED], TIMEOUT), "slcan": (["--lockstep"], 0.5)}


@pytest.fixture(params=sorted(CAN_INTERFACES))
def can_twin(request):
    timeout = CAN_INTERFACES[request.param][1]
    twin = ServedTwin(
        "--driver", "can", "--interface", request.param,
        "--heartbeat-timeout", f"{timeout * 1e3:g}ms",
    )  # fmt: skip
    yield twin, request.param
    twin.stop()


def test_can_twin_latches_when_the_bridge_is_killed(can_twin, tmp_path):
    twin, interface = can_twin
    mode, timeout = CAN_INTERFACES[interface]
    conn = twin.connection
    assert conn["interface"] == interface and conn["channel"].startswith("/dev/pts/")
    run1 = tmp_path / "run1"
    bridge = start_bridge(bridge_cmd("can", conn, run1, "--duration", "60", *mode))
    wait_rows(run1, ROWS, bridge)
    t_kill = kill9(bridge)
    t_latch = twin.first(LATCH_LINE, after=t_kill - 1.0)
    assert t_latch is not None, twin.lines
    dt_ms = (t_latch - t_kill) * 1e3
    row = f"can {interface} | bridge_killed | {mode[0][2:]} | twin latch | {dt_ms:.0f} ms"
    ok = read_run(run1).record["feedback_ok"]
    print(f"\nMATRIX | {row} | replies on time {ok.mean() * 100:.0f} %")
    assert 0.0 < t_latch - t_kill <= timeout + SLACK, t_latch - t_kill
    # the bridge was stepping on replies from the other process until it was killed (paced on a
    # loaded machine most may come late: the fraction on time is in the row above)
    ok = read_run(run1).record["feedback_ok"]
    assert len(ok) >= ROWS and ok.any(), (len(ok), ok.mean())
    # a new client's next command (a sequence ahead of the killed run's, within the 16-bit
    # window) is answered with the latch, position held
    seq = len(ok) + 5000
    with create_driver("can", **conn) as drv:
        drv.send(seq, 0.005, True)
        fb1 = drv.receive(1.0)
        drv.send(seq + 1, 0.005, True)
        fb2 = drv.receive(1.0)
    assert fb1 is not None and fb2 is not None
    assert fb1.status & LATCHED == LATCHED and not fb1.status & Status.ENABLED
    assert fb1.displacement == fb2.displacement  # holds, ignores the 5 mm command
    # a second run against the same twin arms it (sequence afresh) and completes
    arm, rec = _second_run("can", conn, tmp_path / "run2")
    assert arm["replied"] and arm["status"] & LATCHED == LATCHED  # latched until armed
    assert rec["feedback_ok"].all() and len(rec) == 256


def _kill_bridge_and_time_latch(twin, driver, row, out, *extra):
    """A lockstep bridge against the served ``twin``, killed with SIGKILL once stepping: the
    twin must log its latch within its watchdog timeout (+ slack) of the kill."""
    bridge = start_bridge(bridge_cmd(driver, twin.connection, out, "--lockstep", *extra))
    wait_rows(out, ROWS, bridge)
    t_kill = kill9(bridge)
    t_latch = twin.first(LATCH_LINE, after=t_kill - 1.0)
    assert t_latch is not None, twin.lines
    dt_ms = (t_latch - t_kill) * 1e3
    print(f"\nMATRIX | {row} | bridge_killed | lockstep | twin latch | {dt_ms:.0f} ms")
    assert 0.0 < t_latch - t_kill <= TIMEOUT + SLACK, t_latch - t_kill


def test_canopen_twin_latches_when_the_bridge_is_killed(tmp_path):
    """A CiA 402 twin served as its own process over python-can's ``serial`` framing on its
    null-modem pair of pseudo-terminals: the bridge killed, the device's heartbeat consumer
    puts it in FAULT (EMCY 0x8130) within the consumer time; a new client reads that state by
    SDO; a second run resets the fault at arming (reported as the latched watchdog) and
    completes."""
    from rths_hil.drivers.canopen import EMCY_HEARTBEAT

    twin = ServedTwin(
        "--driver", "canopen", "--interface", "serial",
        "--heartbeat-timeout", f"{TIMEOUT * 1e3:g}ms",
    )  # fmt: skip
    try:
        conn = twin.connection
        assert conn["interface"] == "serial" and conn["channel"].startswith("/dev/pts/")
        _kill_bridge_and_time_latch(twin, "canopen", "canopen serial", tmp_path / "run1")
        assert twin.first(f"EMCY 0x{EMCY_HEARTBEAT:04X}", timeout=2.0) is not None, twin.lines
        drv = create_driver("canopen", **conn)
        drv.open()
        try:  # the status word by SDO: FAULT (0x0008 under the CiA 402 mask 0x004F)
            assert drv._sdo_read(0x6041, 0) & 0x004F == 0x0008
        finally:
            drv.close()
        # the heartbeat fault (0x8130 in the error field 0x1003) is the controller's latched
        # watchdog, which arming acknowledges as every controller's
        arm, rec = _second_run("canopen", conn, tmp_path / "run2")
        assert arm["replied"] and arm["status"] & LATCHED == LATCHED
        assert not arm["status"] & int(Status.FAULT)
        assert rec["feedback_ok"].all() and len(rec) == 256
    finally:
        twin.stop()


def test_modbus_twin_latches_when_the_bridge_is_killed(modbus_twin, tmp_path):
    from pymodbus.client import ModbusTcpClient

    conn = modbus_twin.connection
    _kill_bridge_and_time_latch(modbus_twin, "modbus", "modbus", tmp_path / "run1")
    # what a plain Modbus client sees: coil 0 (e-stop) on, STATUS latched and not ENABLED
    client = ModbusTcpClient(conn["host"], port=conn["port"])
    assert client.connect()
    try:
        coil = client.read_coils(0, count=1, device_id=conn["device_id"])
        assert coil.bits[0] is True
        r1 = client.read_holding_registers(16, count=7, device_id=conn["device_id"]).registers
        time.sleep(0.3)
        r2 = client.read_holding_registers(16, count=7, device_id=conn["device_id"]).registers
    finally:
        client.close()
    status = r1[1]
    assert status & LATCHED == LATCHED and not status & Status.ENABLED
    assert r1 == r2  # holding: position and force unchanged
    # a second run against the same twin arms it (sequence afresh) and completes
    arm, rec = _second_run("modbus", conn, tmp_path / "run2")
    assert arm["replied"] and arm["status"] & LATCHED == LATCHED  # latched until armed
    assert rec["feedback_ok"].all() and len(rec) == 256


def test_modbus_map_twin_latches_when_the_bridge_is_killed(modbus_map_twin, tmp_path):
    """The lab's own register map: the latch is read as the map's status word says it."""
    from pymodbus.client import ModbusTcpClient
    from rths_hil.drivers.profile import load_profile

    prof = load_profile(MAP)
    conn = modbus_map_twin.connection
    profile = f"driver.profile={MAP}"
    _kill_bridge_and_time_latch(
        modbus_map_twin, "modbus", "modbus-map", tmp_path / "run1", f"--set={profile}"
    )
    # what a plain Modbus client sees at the map's addresses: the status word latched, not
    # enabled, and the position and force input registers held
    pos, st = prof.points["position"], prof.points["status"]
    client = ModbusTcpClient(conn["host"], port=conn["port"])
    assert client.connect()
    try:
        unit = conn["device_id"]
        r1 = client.read_input_registers(pos.address, count=st.end - pos.address, device_id=unit)
        time.sleep(0.3)
        r2 = client.read_input_registers(pos.address, count=st.end - pos.address, device_id=unit)
    finally:
        client.close()
    word = r1.registers[st.address - pos.address]
    masks = prof.masks
    assert word & masks[int(Status.ESTOP_ACTIVE)] and word & masks[int(Status.WATCHDOG)]
    assert not word & masks[int(Status.ENABLED)]
    assert r1.registers == r2.registers  # holding: position and force unchanged
    # a second run against the same twin acknowledges and arms it, and completes (the map's
    # status is read after the acknowledge was written: the latch shows cleared)
    arm, rec = _second_run("modbus", conn, tmp_path / "run2", profile)
    assert arm["replied"] and arm["status"] & LATCHED == 0
    assert rec["feedback_ok"].all() and len(rec) == 256


def test_can_dbc_twin_latches_when_the_bridge_is_killed(tmp_path):
    """The lab's own DBC, the twin its own process over python-can's ``serial`` framing on its
    null-modem pair of pseudo-terminals: the latch is what a plain python-can + cantools client
    reads in the status frame, as the profile's masks say."""
    import can
    from rths_hil.drivers.profile import load_profile

    prof = load_profile(DBC)
    twin = ServedTwin(
        "--driver", "can", "--profile", str(DBC), "--interface", "serial",
        "--heartbeat-timeout", f"{TIMEOUT * 1e3:g}ms",
    )  # fmt: skip
    try:
        conn = twin.connection
        assert conn["interface"] == "serial" and conn["channel"].startswith("/dev/pts/")
        profile = f"driver.profile={DBC}"
        _kill_bridge_and_time_latch(
            twin, "can", "can-dbc serial", tmp_path / "run1", f"--set={profile}"
        )
        cmd, fb = prof.command, prof.feedback
        sp, en = prof.roles["setpoint"], prof.actions["enable"]
        pos, st = prof.roles["position"], prof.roles["status"]
        values = {sig.name: 0 for sig in cmd.signals}
        values[en.signal] = en.value
        replies = []
        with can.Bus(
            interface="serial", channel=conn["channel"], **conn.get("bus_options", {})
        ) as bus:
            for mm in (5.0, 9.0):  # two enabled commands far from where it holds
                values[sp.signal] = mm
                bus.send(can.Message(arbitration_id=cmd.frame_id, data=cmd.encode(values),
                                     is_extended_id=cmd.is_extended_frame))  # fmt: skip
                end = time.monotonic() + 1.0
                while time.monotonic() < end:
                    msg = bus.recv(0.1)
                    if msg is not None and msg.arbitration_id == fb.frame_id:
                        replies.append(fb.decode(msg.data, decode_choices=False))
                        break
        assert len(replies) == 2, replies
        masks = prof.masks
        for r in replies:
            word = int(r[st.signal])
            assert word & masks[int(Status.ESTOP_ACTIVE)] and word & masks[int(Status.WATCHDOG)]
            assert not word & masks[int(Status.ENABLED)]
        assert replies[0][pos.signal] == replies[1][pos.signal]  # holds, ignores both commands
        # a second run against the same twin acknowledges the latch at arming and completes
        arm, rec = _second_run("can", conn, tmp_path / "run2", profile)
        assert arm["replied"] and arm["status"] & LATCHED == LATCHED
        assert rec["feedback_ok"].all() and len(rec) == 256
    finally:
        twin.stop()


def test_serial_twin_latches_when_the_bridge_is_killed(serial_twin, tmp_path):
    conn = serial_twin.connection
    _kill_bridge_and_time_latch(serial_twin, "serial", "serial", tmp_path / "run1")
    # a new client's next command is answered with the latch, position held
    with create_driver("serial", **conn) as drv:
        drv.send(10**6, 0.005, True)
        fb1 = drv.receive(1.0)
        drv.send(10**6 + 1, 0.005, True)
        fb2 = drv.receive(1.0)
    assert fb1 is not None and fb2 is not None
    assert fb1.status & LATCHED == LATCHED and not fb1.status & Status.ENABLED
    assert fb1.displacement == fb2.displacement  # holds, ignores the 5 mm command


@pytest.mark.parametrize(
    "driver, profile",
    [("can", None), ("modbus", None), ("serial", None), ("modbus", MAP), ("can", DBC)],
    ids=["can", "modbus", "serial", "modbus-map", "can-dbc"],
)
def test_in_process_twin_latches_when_commands_stop(driver, profile):
    """The in-process twins (threaded) hold and latch the same way when the bridge falls silent
    — the built-in protocols and the controller profiles."""
    from rths_hil.sim_backends.twin import default_plant, start_twin

    extra = {} if profile is None else {"profile": str(profile)}
    with start_twin(driver, default_plant(), heartbeat_timeout=TIMEOUT_IN, **extra) as twin:
        with create_driver(driver, **twin.connection) as drv:
            assert drv.arm(1.0) is not None
            for k in range(200):
                # the twin's watchdog counts from the command's arrival: after this, before the
                # reply is back
                t_last = time.monotonic()
                drv.send(k, 0.002 * np.sin(k / 50), True)
                fb = drv.receive(1.0)
                assert fb is not None and fb.status & Status.ENABLED
            while not twin.controller.watchdog_tripped and time.monotonic() - t_last < 2.0:
                time.sleep(0.001)
            t_latch = time.monotonic() - t_last
            assert twin.controller.watchdog_tripped
            assert TIMEOUT_IN <= t_latch <= TIMEOUT_IN + SLACK, t_latch
            drv.send(200, 0.01, True)
            fb = drv.receive(1.0)
            assert fb is not None and fb.status & LATCHED == LATCHED
            assert abs(fb.displacement - twin.controller.displacement) <= 1e-7  # held (LSB)
            # re-armed by a new run: enabled again, sequence from 0 (a register map is read
            # after its acknowledge was written: the latch shows cleared already)
            armed = drv.arm(1.0)
            assert armed is not None
            assert armed.status & LATCHED == (0 if profile == MAP else LATCHED)
            drv.send(0, 0.0, True)
            fb = drv.receive(1.0)
            assert fb is not None and fb.seq == 0 and fb.status & Status.ENABLED
            assert not fb.status & LATCHED


def test_holding_on_purpose_does_not_trip_the_watchdog():
    """enable=False (hold) is not a dead bridge: the watchdog watches an enabled controller."""
    from rths_hil.sim_backends.twin import default_plant, start_twin

    with start_twin("modbus", default_plant(), heartbeat_timeout=TIMEOUT_IN) as twin:
        with create_driver("modbus", **twin.connection) as drv:
            drv.arm(1.0)
            time.sleep(5 * TIMEOUT_IN)
            assert not twin.controller.watchdog_tripped

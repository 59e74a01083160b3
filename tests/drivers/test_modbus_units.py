"""Several Modbus units on one TCP connection: real twins, real drivers, 127.0.0.1.

``examples/modbus_units.toml`` is ``two_actuators.toml`` with both actuators over Modbus TCP,
units 1 and 2 of one server: lockstep end to end (each channel's FEI delay against its twin's
delay), a fault on one unit stopping both, a duplicate unit refused with exit 2, per-unit
controller watchdogs, the pipelined transactions on the wire read by a plain pymodbus client,
and ``rths-hil twin serve`` with several ``--device-id``.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient
from rths_hil.drivers.base import Status
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.cli import main as cli
from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.hybrid import RTHSLoop
from tests.helpers.loop import run_loop
from tests.helpers.procs import ServedTwin

ROOT = Path(__file__).resolve().parents[2]
UNITS = ROOT / "examples" / "modbus_units.toml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(tmp_path, name, overrides=(), duration=10.0, **kw):
    port = f"driver.connection.port={_free_port()}"
    r = run_loop(tmp_path / name, UNITS, port, *overrides, mode="lockstep", duration=duration, **kw)
    return r.loop, r.result, r.run


def _median_delay(rec, sfx: str) -> float:
    v = rec["fei_valid" + sfx]
    assert v.sum() > 2000
    return float(np.median(rec["fei_delay" + sfx][v]))


def test_two_units_on_one_connection_fei_delay_per_channel(tmp_path):
    loop, res, run = _run(tmp_path, "on")
    assert res.status == "completed" and res.steps == 10240 and res.missed_replies == 0
    a, b = loop.channels
    # one server, one TCP connection for the steps and one for the e-stop: the two drivers
    # shared them
    assert a.twin.server is b.twin.server and a.twin.server.accepted == 2
    assert [c.driver.device_id for c in loop.channels] == [1, 2]
    for ch in loop.channels:
        assert ch.twin.stats.steps == res.steps and ch.driver.stats.malformed == 0
        assert ch.driver.stats.received == res.steps + 2  # and the arming and hand-back replies
    rec = run.record
    assert abs(_median_delay(rec, "_storey1")) < 1e-3
    assert abs(_median_delay(rec, "_storey3")) < 1e-3
    assert np.all(rec["feedback_time_storey1"] > 0) and np.all(rec["skew"] >= 0)

    _, res, run = _run(tmp_path, "off", ["compensation.enabled=false"])
    assert res.status == "completed"
    assert abs(_median_delay(run.record, "_storey1") - 0.010) < 1e-3
    assert abs(_median_delay(run.record, "_storey3") - 0.020) < 1e-3


@pytest.mark.timing  # a wall-clock lockstep timeout
@pytest.mark.parametrize("fault", ["stuck", "disconnect"])
def test_a_fault_on_one_unit_stops_both(tmp_path, fault):
    over = {
        "stuck": ["actuators.storey3.twin.faults=stuck_from=3000"],
        "disconnect": [
            "actuators.storey3.twin.faults=disconnect_from=3000",
            "loop.lockstep_timeout=0.2",
        ],
    }[fault]
    loop, res, run = _run(tmp_path, "r", over, duration=6.0)
    rule = {"stuck": "stuck", "disconnect": "watchdog"}[fault]
    assert res.status == "trip" and res.exit_code == 3
    assert res.trip.rule == rule and res.trip.channel == "storey3"
    k = res.trip.step
    assert k >= 3000 and len(run.record) == k + 1
    healthy, faulty = loop.channels
    assert k + 1 <= healthy.twin.stats.steps <= k + 1 + 2
    for ch in loop.channels:
        assert ch.driver.stats.estops == 1
    # unit 1 latched its own e-stop and confirmed it on the shared connection
    assert healthy.twin.stats.estops == 1 and healthy.twin.controller.estop_latched
    estops = {e["channel"]: e for e in run.events if e["kind"] == "estop"}
    assert estops["storey1"]["confirmed"] is True
    assert estops["storey1"]["status"] & Status.ESTOP_ACTIVE
    if fault == "stuck":  # unit 2 is alive: it latched and confirmed too
        assert faulty.twin.stats.estops == 1 and faulty.twin.controller.estop_latched
        assert estops["storey3"]["confirmed"] is True
    else:  # unit 2 fell silent: nothing reaches it, the unconfirmed latch is recorded
        assert faulty.twin.stats.estops == 0 and estops["storey3"]["confirmed"] is False


def test_same_unit_twice_is_refused_one_line_exit_2(tmp_path, capsys):
    args = [
        "run",
        str(UNITS),
        "--lockstep",
        "--duration=0.1s",
        "--set=actuators.storey3.driver.connection.device_id=1",
        "--out",
        str(tmp_path / "o"),
    ]
    assert cli(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert "'storey1' and 'storey3'" in err[0] and "unit 1 on 127.0.0.1:1502" in err[0]
    assert "driver.connection.device_id" in err[0]
    assert not (tmp_path / "o").exists()
    where = r"actuators\[1\] \(storey3\): driver.connection.device_id"
    with pytest.raises(InputError, match=where):
        RTHSLoop(load_config(UNITS, ["actuators.storey3.driver.connection.device_id=0"]), tmp_path)


def test_driver_refuses_a_unit_already_open_on_the_connection():
    with start_twin("modbus", default_plant()) as twin:
        with create_driver("modbus", **twin.connection):
            with pytest.raises(InputError, match="unit 1 is already open"):
                create_driver("modbus", **twin.connection).open()


@pytest.mark.timing  # a client polling in wall-clock time
def test_pipelined_units_on_the_wire_and_a_plain_pymodbus_client():
    """Both requests written before either reply; the server answers each unit in its own
    transaction (distinct transaction ids); a plain pymodbus client reads each unit's state."""
    port = _free_port()
    p1, p2 = default_plant(delay=0.0), default_plant(delay=0.0, gain=0.5)
    with (
        start_twin("modbus", p1, port=port, device_id=1) as t1,
        start_twin("modbus", p2, port=port, device_id=2) as t2,
    ):
        assert t1.server is t2.server
        d1 = create_driver("modbus", **t1.connection)
        d2 = create_driver("modbus", **t2.connection)
        with d1, d2:
            assert d1.link is d2.link and (d1._tid_x, d2._tid_x) == (0, 0x100)
            for d in (d1, d2):
                d.arm(1.0)
            for k in range(50):
                x = 1e-3 * np.sin(0.1 * k)
                d1.send(k, x)
                d2.send(k, x)
                f1, f2 = d1.receive(1.0), d2.receive(1.0)
                assert f1.seq == f2.seq == k
                assert f1.displacement == pytest.approx(x, abs=1e-7)
                assert f2.displacement == pytest.approx(0.5 * x, abs=1e-7)
            d2.estop()
            time.sleep(0.05)
            assert t2.controller.estop_latched and not t1.controller.estop_latched
        with ModbusTcpClient("127.0.0.1", port=port) as client:
            assert client.read_coils(0, count=1, device_id=2).bits[0]
            assert not client.read_coils(0, count=1, device_id=1).bits[0]
            assert client.read_holding_registers(16, count=1, device_id=1).registers == [49]
            assert client.read_coils(0, count=1, device_id=9).isError()  # no such unit
    assert t1.stats.steps == t2.stats.steps == 50


def test_estop_over_its_own_connection_is_read_back(caplog):
    """The e-stop goes over the driver's own second connection while a step's request is
    outstanding on the link, and is read back (coil 0); a plain pymodbus client sees the
    latch. Without that connection it is written on the link, not read back."""
    for own in (True, False):
        with start_twin("modbus", default_plant(delay=0.0), port=_free_port()) as twin:
            drv = create_driver("modbus", estop_connection=own, **twin.connection)
            with drv, caplog.at_level("WARNING"):
                assert drv.arm(1.0) is not None
                drv.send(0, 0.0, True)  # outstanding
                drv.estop()
                assert drv.estop_latched is (True if own else None)
                assert drv.receive(1.0) is not None  # the step's reply still arrives
                time.sleep(0.05)
                assert twin.controller.estop_latched
            c = twin.connection
            with ModbusTcpClient("127.0.0.1", port=c["port"]) as client:
                assert client.read_coils(0, count=1, device_id=1).bits[0]
    assert sum("latched (coil 0 reads ON)" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.timing  # the twins' wall-clock watchdogs
def test_each_unit_has_its_own_controller_watchdog():
    port = _free_port()
    with (
        start_twin("modbus", default_plant(), port=port, device_id=1, heartbeat_timeout=0.1) as t1,
        start_twin("modbus", default_plant(), port=port, device_id=2, heartbeat_timeout=0.1) as t2,
    ):
        d1 = create_driver("modbus", **t1.connection)
        d2 = create_driver("modbus", **t2.connection)
        with d1, d2:
            for d in (d1, d2):
                d.arm(1.0)
                d.send(0, 0.0)
                assert d.receive(1.0).status & Status.ENABLED
            end = time.monotonic() + 0.4
            k = 1
            while time.monotonic() < end:  # only unit 1 is commanded
                d1.send(k, 0.0)
                assert d1.receive(1.0) is not None
                k += 1
                time.sleep(0.01)
        assert not t1.controller.watchdog_tripped
        assert t2.controller.watchdog_tripped and t2.controller.estop_latched


@pytest.mark.timing  # a served twin (another process)
def test_twin_serve_several_units(tmp_path):
    served = ServedTwin("--driver", "modbus", "--device-id", "1", "--device-id", "2")
    try:
        conn = served.connection
        assert conn["device_id"] == 1
        drivers = [create_driver("modbus", **{**conn, "device_id": u}) for u in (1, 2)]
        for d in drivers:
            d.open()
        try:
            assert drivers[0].link is drivers[1].link
            for d in drivers:
                d.arm(1.0)
            for k in range(20):
                for d in drivers:
                    d.send(k, 1e-3)
                for d in drivers:
                    fb = d.receive(1.0)
                    assert fb is not None and fb.seq == k
        finally:
            for d in drivers:
                d.close()
    finally:
        served.stop()
    served._reader.join(5)
    text = "\n".join(line for _, line in served.lines)
    assert "unit 1: stopped after 20 steps" in text and "unit 2: stopped after 20 steps" in text


def test_two_channels_on_one_rtu_line_are_refused(tmp_path):
    over = [
        "driver.connection.transport=rtu",
        "driver.connection.device=/dev/ttyUSB0",
        "twin.enabled=false",
        "loop.fs=50",
    ]
    with pytest.raises(InputError, match=r"'storey1' and 'storey3' use one Modbus RTU line"):
        RTHSLoop(load_config(UNITS, over), tmp_path / "r")


def test_a_unit_read_late_leaves_the_other_units_replies_to_it():
    """A receive that returns far past its deadline (``rths_hil.drivers.base.DEADLINE_SLACK``,
    a stalled machine) is counted. Were unit 1 then read through a reader thread (the fallback
    of a driver that may block), that thread would read unit 2's replies off the shared
    connection into unit 2's inbox while unit 2 waits on the socket, and unit 2 would miss
    them: every reply must reach its unit."""
    port = _free_port()
    with (
        start_twin("modbus", default_plant(delay=0.0), port=port, device_id=1) as t1,
        start_twin("modbus", default_plant(delay=0.0), port=port, device_id=2) as t2,
    ):
        d1 = create_driver("modbus", **t1.connection)
        d2 = create_driver("modbus", **t2.connection)
        with d1, d2:
            for d in (d1, d2):
                assert d.arm(1.0) is not None
            d1._overran(0.06)  # unit 1's receive came back 60 ms late
            missed = 0
            for k in range(40):
                d1.send(k, 0.0)
                d2.send(k, 0.0)
                f1, f2 = d1.receive(0.2), d2.receive(0.2)
                missed += (f1 is None or f1.seq != k) + (f2 is None or f2.seq != k)
            assert missed == 0
            assert d1.stats.deadline_overruns == 1 and d2.stats.timeouts == 0

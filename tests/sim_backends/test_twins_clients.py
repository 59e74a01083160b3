"""Twins driven by independent clients, the heartbeat watchdog, and ``rths-hil twin serve``.

* CAN: plain python-can + cantools, using nothing but ``drivers/can/actuator.dbc``.
* Modbus: plain pymodbus clients (TCP, and RTU over the twin's pseudo-terminal), using only the
  documented register map and pymodbus's own INT32 register conversion.
* ``twin serve`` as a subprocess: read the listen line, talk with a driver, SIGINT, exit 0.
"""

from __future__ import annotations

import binascii
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from rths_hil.drivers.base import Status
from rths_hil.drivers.can import CANDriver
from rths_hil.drivers.can.codec import DBC_PATH
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.delay import fractional_delay
from rths_hil.sim_backends.plant import TwinPlant
from rths_hil.sim_backends.twin import default_plant, start_twin

# Exchanges with waits of 1 s and more, and "twin serve" as a process, run with the parallel
# tests; the heartbeat watchdog of 50 ms runs apart from them (the "timing" marker,
# pyproject.toml; make test).

DT = 1.0 / 1024.0
DELAY, GAIN, K = 0.0042, 1.05, 3.0e5
ROOT = Path(__file__).resolve().parents[2]


def plant() -> TwinPlant:
    return default_plant(DELAY, GAIN, K, DT)


def commands(n: int) -> np.ndarray:
    return 0.003 * np.sin(2 * np.pi * 2.0 * np.arange(n) * DT)


def expected(cmd_q: np.ndarray) -> np.ndarray:
    return GAIN * fractional_delay(cmd_q, DELAY, 1.0 / DT)


def test_can_twin_with_plain_python_can_and_cantools() -> None:
    db = cantools.database.load_file(str(DBC_PATH))
    n = 150
    cmd = commands(n)
    with (
        start_twin("can", plant()) as twin,
        can.Bus(interface="virtual", channel=twin.connection["channel"]) as bus,
    ):
        command = db.get_message_by_name("Command")
        got = []
        for k in range(n):
            data = command.encode({"Seq": k, "Displacement": float(cmd[k]), "Control": 1})
            bus.send(can.Message(arbitration_id=command.frame_id, data=data, is_extended_id=False))
            msg = bus.recv(1.0)
            assert msg is not None
            got.append(db.decode_message(msg.arbitration_id, msg.data, decode_choices=False))
            assert db.get_message_by_frame_id(msg.arbitration_id).name == "Feedback"
        assert [g["Seq"] for g in got] == [k % 256 for k in range(n)]
        x = expected(np.round(cmd / 1e-7) * 1e-7)
        disp = np.array([g["Displacement"] for g in got])
        force = np.array([g["Force"] for g in got])
        np.testing.assert_allclose(disp, x, atol=0.5e-7 + 1e-12)
        np.testing.assert_allclose(force, K * x, atol=0.25 + 1e-9)
        assert np.max(np.abs(x)) > 2e-3
        # e-stop with the DBC's key, then the controller holds and says so
        estop = db.get_message_by_name("EStop")
        bus.send(
            can.Message(
                arbitration_id=estop.frame_id,
                data=estop.encode({"EStopKey": "ESTOP"}),
                is_extended_id=False,
            )
        )
        data = command.encode({"Seq": n, "Displacement": 0.02, "Control": 1})
        bus.send(can.Message(arbitration_id=command.frame_id, data=data, is_extended_id=False))
        fb = db.decode_message(0x180, bus.recv(1.0).data)
        assert fb["Status"] & Status.ESTOP_ACTIVE
        assert fb["Displacement"] == pytest.approx(disp[-1], abs=1e-12)


def _client_step(client, seq: int, cmd: float, enable: bool = True):
    raw = round(cmd / 1e-7)
    values = [seq & 0xFFFF, int(enable), *client.convert_to_registers(raw, client.DATATYPE.INT32)]
    rr = client.readwrite_registers(
        read_address=16, read_count=7, address=0, values=values, device_id=1
    )
    assert not rr.isError(), rr
    regs = rr.registers
    block = struct.pack(">6H", *regs[:6])
    assert regs[6] == binascii.crc_hqx(block, 0xFFFF)  # FB_CRC as documented
    disp = client.convert_from_registers(regs[2:4], client.DATATYPE.INT32) * 1e-7
    force = client.convert_from_registers(regs[4:6], client.DATATYPE.INT32) * 0.01
    return regs[0], regs[1], disp, force


def test_modbus_tcp_twin_with_plain_pymodbus_client() -> None:
    n = 120
    cmd = commands(n)
    with start_twin("modbus", plant()) as twin:
        conn = twin.connection
        client = ModbusTcpClient(conn["host"], port=conn["port"], timeout=2)
        assert client.connect()
        try:
            out = [_client_step(client, k, float(cmd[k])) for k in range(n)]
            assert [o[0] for o in out] == list(range(n))
            assert all(o[1] == Status.ENABLED for o in out)
            x = expected(np.round(cmd / 1e-7) * 1e-7)
            np.testing.assert_allclose([o[2] for o in out], x, atol=0.5e-7 + 1e-12)
            np.testing.assert_allclose([o[3] for o in out], K * x, atol=0.005 + 1e-9)
            # monitoring read (FC 3) sees the same command registers
            rr = client.read_holding_registers(0, count=4, device_id=1)
            assert rr.registers[0] == n - 1
            # e-stop coil (FC 5), read back (FC 1), then the twin holds
            assert not client.read_coils(0, count=1, device_id=1).bits[0]
            assert not client.write_coil(0, True, device_id=1).isError()
            assert client.read_coils(0, count=1, device_id=1).bits[0]
            seq, status, disp, _ = _client_step(client, n, 0.05)
            assert seq == n
            assert status & Status.ESTOP_ACTIVE and disp == pytest.approx(out[-1][2], abs=1e-12)
            # an unsupported function gets a Modbus exception, not silence
            assert client.write_register(5, 1, device_id=1).isError()
            # a write outside registers 0-3 in FC 23 is an illegal address
            bad = client.readwrite_registers(
                read_address=16, read_count=7, write_address=8, values=[1, 2], device_id=1
            )
            assert bad.isError()
        finally:
            client.close()


def test_modbus_rtu_twin_with_plain_pymodbus_serial_client() -> None:
    with start_twin("modbus", plant(), transport="rtu") as twin:
        client = ModbusSerialClient(twin.connection["device"], baudrate=115200, timeout=1)
        assert client.connect()
        try:
            out = [_client_step(client, k, 0.001) for k in range(20)]
        finally:
            client.close()
    assert [o[0] for o in out] == list(range(20))
    x = expected(np.full(20, 0.001))
    np.testing.assert_allclose([o[2] for o in out], x, atol=0.5e-7 + 1e-12)


@pytest.mark.timing  # a 50 ms heartbeat timeout
def test_heartbeat_watchdog_trips_estop() -> None:
    with start_twin("can", plant(), heartbeat_timeout=0.05) as twin:
        with CANDriver(**twin.connection) as drv:
            for k in range(5):
                drv.heartbeat()
                drv.send(k, 0.001)
                assert drv.receive(1.0).status == Status.ENABLED
            time.sleep(0.2)  # heartbeats stop
            drv.send(5, 0.001)
            fb = drv.receive(1.0)
            assert fb.status & Status.WATCHDOG and fb.status & Status.ESTOP_ACTIVE
            assert twin.stats.heartbeats == 5


def test_start_twin_rejects_unknown_driver_and_setting() -> None:
    from rths_hil.errors import InputError

    with pytest.raises(InputError, match="no twin for driver 'profibus'"):
        start_twin("profibus", plant())
    with pytest.raises(InputError, match="bad endpoint setting"):
        start_twin("serial", plant(), baud=9600)


def test_twin_with_model_file_plant(tmp_path: Path) -> None:
    modelfile = pytest.importorskip("rths_hil.sim_backends.modelfile")
    path = tmp_path / "twin.toml"
    path.write_text("[actuator]\ndelay = 0.0042\ngain = 1.05\n")
    p = modelfile.load_plant(path, DT)
    n = 80
    cmd = commands(n)
    with start_twin("serial", p) as twin, create_driver("serial", **twin.connection) as drv:
        disp = []
        for k in range(n):
            drv.send(k, float(cmd[k]))
            disp.append(drv.receive(1.0).displacement)
    np.testing.assert_allclose(disp, expected(cmd), atol=1e-12)


# -- twin serve as its own process -------------------------------------------------------------
def _serve(*args: str) -> tuple[subprocess.Popen, dict]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "twin", "serve", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=ROOT,
    )
    line = proc.stdout.readline()  # blocks until the twin listens (or the process dies)
    if not line:
        proc.kill()
        pytest.fail(f"twin serve printed nothing; stderr: {proc.stderr.read()}")
    assert "listening on" in line
    return proc, json.loads(line.split(" connection ", 1)[1])


@pytest.mark.parametrize(
    "args",
    [("--driver", "modbus"), ("--driver", "serial"), ("--driver", "modbus", "--transport", "rtu")],
)
def test_twin_serve_subprocess(args: tuple[str, ...], tmp_path: Path) -> None:
    model = tmp_path / "twin.toml"
    model.write_text("[actuator]\ndelay = 0.0042\ngain = 1.05\n")
    proc, conn = _serve(*args, "--model", str(model))
    try:
        with create_driver(args[1], **conn) as drv:
            cmd = commands(40)
            disp = []
            for k in range(40):
                drv.send(k, float(cmd[k]))
                fb = drv.receive(2.0)
                assert fb is not None and fb.seq == k
                disp.append(fb.displacement)
        lsb = 1e-7 if args[1] == "modbus" else 0.0
        q = np.round(cmd / lsb) * lsb if lsb else cmd
        np.testing.assert_allclose(disp, expected(q), atol=lsb / 2 + 1e-12)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert rc == 0, proc.stderr.read()
    assert "stopped after 40 steps" in proc.stderr.read()


def test_twin_serve_bad_arguments_exit_2() -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "rths_hil",
            "twin",
            "serve",
            "--driver",
            "can",
            "--interface",
            "virtual",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert r.returncode == 2
    assert "virtual bus only reaches buses inside the same process" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1

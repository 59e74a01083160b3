"""pytest fixtures: the Modbus TCP servo partner (``modbus_servo.py``) as its own process.

``modbus_servo`` is a factory: ``modbus_servo(position=0.005, pause_rate=0)`` starts the
partner on a free 127.0.0.1 port and returns a :class:`ServoPartner`; every partner started is
stopped when the test ends. The partner's state is read independently of the bridge, over a
Modbus connection of the test's own (pymodbus's client), or from its state file at exit.
"""

from __future__ import annotations

import json
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

SCRIPT = Path(__file__).with_name("modbus_servo.py")
PROFILE = Path(__file__).with_name("modbus_servo.toml")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServoPartner:
    """A running ``modbus_servo.py`` and a watching Modbus connection of the test's own."""

    def __init__(self, tmp: Path, **options: Any) -> None:
        self.port = free_port()
        self.state_file = tmp / f"modbus_servo_{self.port}.json"
        cmd = [sys.executable, str(SCRIPT), "--port", str(self.port)]
        cmd += ["--state-json", str(self.state_file)]
        for key, value in options.items():
            cmd += [f"--{key.replace('_', '-')}", str(value)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if "listening" not in line:
            self.proc.kill()
            err = self.proc.stderr.read() if self.proc.stderr else ""
            raise RuntimeError(f"modbus_servo did not start: {line!r} {err}")
        self._client: ModbusTcpClient | None = None
        self.final: dict[str, Any] | None = None

    @property
    def connection(self) -> dict[str, Any]:
        """``driver.connection`` for the bridge."""
        return {"transport": "tcp", "host": "127.0.0.1", "port": self.port}

    def client(self) -> ModbusTcpClient:
        """The test's own connection (served concurrently with the bridge's)."""
        if self._client is None:
            self._client = ModbusTcpClient("127.0.0.1", port=self.port, timeout=0.5, retries=0)
            if not self._client.connect():
                raise RuntimeError("cannot connect to modbus_servo")
        return self._client

    def read(self) -> tuple[float, float, int]:
        """(position m, force N, status register) read over the test's own connection; the
        partner may drop a request (its pauses): retried up to 1 s."""
        end = time.monotonic() + 1.0
        while True:
            try:
                r = self.client().read_input_registers(2048, count=5)
                if not r.isError():
                    regs = r.registers
                    pos = struct.unpack(">f", struct.pack(">HH", *regs[0:2]))[0]
                    force = struct.unpack(">f", struct.pack(">HH", *regs[2:4]))[0]
                    return pos * 1e-3, force * 1e3, regs[4]
            except Exception:  # a dropped request: a timeout of the client
                if self._client is not None:
                    self._client.close()
                self._client = None
            if time.monotonic() > end:
                raise RuntimeError("modbus_servo does not answer the test's reads")

    def status(self) -> int:
        """The status register, read over the test's own connection."""
        return self.read()[2]

    def stop(self) -> dict[str, Any]:
        """Stop the partner; its state and history (``--state-json``)."""
        if self._client is not None:
            self._client.close()
            self._client = None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.final is None and self.state_file.exists():
            self.final = json.loads(self.state_file.read_text())
        return self.final or {}


@pytest.fixture
def modbus_servo(tmp_path: Path) -> Iterator[Any]:
    """Factory: start a Modbus servo partner (options as its command line's); all stopped at
    the end of the test."""
    started: list[ServoPartner] = []

    def start(**options: Any) -> ServoPartner:
        partner = ServoPartner(tmp_path, **options)
        started.append(partner)
        return partner

    yield start
    for partner in started:
        partner.stop()

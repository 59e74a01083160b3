"""pytest fixtures: the CiA 402 drive partner (``cia402_drive.py``) as its own process.

``cia402_drive`` is a factory: ``cia402_drive("slcan", position=0.005)`` opens a null-modem pair
of pseudo-terminals (the test side's helper, :class:`NullModem`), starts the partner on one end
and returns a :class:`DrivePartner` whose :attr:`~DrivePartner.connection` is the bridge's
``driver.connection`` on the other end. Every partner started is stopped when the test ends.
Its state is read independently of the bridge: by SDO with a plain ``canopen.RemoteNode`` on
the bridge's end once the bridge has let go of it (:meth:`DrivePartner.sdo_read`), and from the
state file the partner writes when it is stopped (:meth:`DrivePartner.stop`).
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import canopen
import pytest
from canopen.objectdictionary import ODVariable
from rths_hil.sim_backends.endpoints.nullmodem import NullModem

SCRIPT = Path(__file__).with_name("cia402_drive.py")
EDS = Path(__file__).with_name("vendor_cia402.eds")
#: python-can options of the bridge's end of the line (slcan: no wait for an adapter to boot)
BUS_OPTIONS = {"slcan": {"sleep_after_open": 0.0}, "serial": {}}


class DrivePartner:
    """A running ``cia402_drive.py`` on a null-modem cable."""

    def __init__(self, tmp: Path, interface: str = "serial", node_id: int = 5, **options: Any):
        self.interface, self.node_id = interface, node_id
        self.cable = NullModem()
        self.state_file = tmp / f"cia402_drive_{node_id}_{id(self)}.json"
        cmd = [sys.executable, str(SCRIPT), "--interface", interface]
        cmd += ["--channel", self.cable.twin_path, "--node-id", str(node_id)]
        cmd += ["--state-file", str(self.state_file)]
        for key, value in options.items():
            cmd += [f"--{key.replace('_', '-')}", str(value)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        if not line.startswith("READY"):
            self.proc.kill()
            err = self.proc.stderr.read() if self.proc.stderr else ""
            self.cable.close()
            raise RuntimeError(f"cia402_drive did not start: {line!r} {err}")
        self.final: dict[str, Any] | None = None

    @property
    def connection(self) -> dict[str, Any]:
        """``driver.connection`` for the bridge (the EDS is the vendor's)."""
        return {
            "device_profile": "cia402",
            "eds": str(EDS),
            "node_id": self.node_id,
            "interface": self.interface,
            "channel": self.cable.bridge_path,
            "bus_options": dict(BUS_OPTIONS[self.interface]),
            "counts_per_m": 1e6,
        }

    def toml_connection(self, **extra: Any) -> str:
        """:attr:`connection` (with ``extra``) as an inline TOML table."""
        c = {**self.connection, **extra}
        parts = []
        for k, v in c.items():
            if isinstance(v, dict):
                inner = ", ".join(f"{ik} = {json.dumps(iv)}" for ik, iv in v.items())
                parts.append(f"{k} = {{ {inner} }}")
            else:
                parts.append(f"{k} = {json.dumps(v)}")
        return "{ " + ", ".join(parts) + " }"

    def sdo_read(self, *objects: tuple[int, int]) -> list[int]:
        """Read ``objects`` ((index, sub) each) by SDO with a plain RemoteNode on the bridge's
        end of the line (only once the bridge has closed it)."""
        net = canopen.Network()
        net.connect(
            interface=self.interface, channel=self.cable.bridge_path, **BUS_OPTIONS[self.interface]
        )
        try:
            node = canopen.RemoteNode(self.node_id, str(EDS))
            net.add_node(node)
            out = []
            for index, sub in objects:
                var = node.sdo[index]
                if not isinstance(var.od, ODVariable):
                    var = var[sub]
                out.append(int(var.raw))
            return out
        finally:
            net.disconnect()

    def stop(self) -> dict[str, Any]:
        """Stop the partner; its state at exit (the state file)."""
        if self.final is None:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(5)
            self.final = json.loads(self.state_file.read_text()) if self.state_file.exists() else {}
            self.cable.close()
        return self.final


@pytest.fixture
def cia402_drive(tmp_path: Path) -> Iterator[Any]:
    """Factory of :class:`DrivePartner` (``cia402_drive(interface, **options)``); all stopped at
    the end of the test."""
    started: list[DrivePartner] = []

    def start(interface: str = "serial", **options: Any) -> DrivePartner:
        p = DrivePartner(tmp_path, interface, **options)
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()

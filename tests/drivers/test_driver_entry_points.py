"""A lab's own driver, installed as a distribution with an ``rths_hil.drivers`` entry point, is
found by the registry beside the built-in drivers (which need no package metadata)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest
from rths_hil.drivers.base import Driver
from rths_hil.drivers.registry import BUILTIN, available, create_driver, driver_class

from rths_hil.errors import InputError

_MODULE = """
from rths_hil.drivers.base import Driver


class MyLabDriver(Driver):
    def __init__(self, host="127.0.0.1", port=9000):
        self.host, self.port = host, port

    def open(self):
        pass

    def close(self):
        pass

    def send(self, seq, displacement, enable=True):
        pass

    def receive(self, timeout):
        return None

    def estop(self):
        pass


class NotADriver:
    pass
"""


@pytest.fixture
def lab_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A real distribution on sys.path: a module and its dist-info with entry_points.txt."""
    (tmp_path / "mylab_driver.py").write_text(_MODULE)
    info = tmp_path / "mylab_driver-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mylab-driver\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[rths_hil.drivers]\nmylab = mylab_driver:MyLabDriver\nbroken = mylab_driver:NotADriver\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    yield tmp_path
    sys.modules.pop("mylab_driver", None)


def test_builtin_drivers_need_no_metadata() -> None:
    assert set(BUILTIN) == {"can", "modbus", "serial", "canopen"}
    for name in BUILTIN:
        assert issubclass(driver_class(name), Driver)


def test_lab_driver_from_entry_point(lab_package: Path) -> None:
    names = available()
    assert names["mylab"] == "mylab_driver:MyLabDriver"
    assert set(BUILTIN) <= set(names)
    drv = create_driver("mylab", port=9100)
    assert type(drv).__name__ == "MyLabDriver" and drv.port == 9100
    with pytest.raises(InputError, match=r"unknown connection setting.*baud"):
        create_driver("mylab", baud=9600)
    with pytest.raises(InputError, match=r"not a rths_hil\.drivers\.base\.Driver subclass"):
        driver_class("broken")

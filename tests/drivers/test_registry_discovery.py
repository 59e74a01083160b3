"""The registries find what is shipped, with no list to edit: the protocol packages (each
folder under ``drivers/``, exporting ``PROTOCOL``), their profile formats (a package's
``profile_format`` module) and the twin endpoints (the endpoint module of a driver's name, its
``TWIN``). They list the folders, not import them: finding them imports no bus library."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from rths_hil.drivers import registry
from rths_hil.drivers.profile import protocol_key
from rths_hil.drivers.protocol import Protocol
from rths_hil.sim_backends import registry as twins

from rths_hil.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ["can", "canopen", "modbus", "serial"]


@pytest.fixture
def clean_caches() -> None:
    """The registries' caches cleared before and after (a test changes a ``__path__``)."""
    registry.clear_cache()
    yield
    registry.clear_cache()


def _extra_folder(
    monkeypatch: pytest.MonkeyPatch, package: str, folder: Path, files: dict[str, str]
) -> None:
    """``files`` (relative path → text) in ``folder``, appended to ``package``'s ``__path__``."""
    for rel, text in files.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_text(textwrap.dedent(text))
    pkg = importlib.import_module(package)
    monkeypatch.setattr(pkg, "__path__", [*pkg.__path__, str(folder)])
    importlib.invalidate_caches()


def test_the_shipped_protocols_are_found_sorted() -> None:
    assert list(registry.builtin()) == SHIPPED == list(registry.BUILTIN)
    assert registry.DEFAULT in registry.builtin()
    for name, target in registry.builtin().items():
        assert target == f"rths_hil.drivers.{name}:PROTOCOL"
        proto = registry.protocol(name)
        assert isinstance(proto, Protocol) and proto.name == name
    assert list(twins.builtin_twins()) == SHIPPED == list(twins.TWINS)


def test_a_missing_default_driver_is_said(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "DEFAULT", "profibus")
    with pytest.raises(RuntimeError, match=r"no package of the default driver 'profibus'"):
        registry.builtin()


def test_each_twin_is_the_endpoint_module_of_its_drivers_name() -> None:
    """Each shipped driver's twin is the module of its name, whose ``TWIN`` names a class of
    that module; every protocol's profile format is one of the formats found."""
    for name, module in twins.builtin_twins().items():
        assert module == f"rths_hil.sim_backends.endpoints.{name}"
        entry = twins.builtin_entry(name)
        assert importlib.import_module(module).TWIN is entry
        cls, got = twins.twin_class(name)
        assert got == entry and f"{cls.__module__}:{cls.__name__}" == entry.target
    formats = registry.profile_formats()
    assert list(formats) == ["can", "modbus"] == list(protocol_key().choices)
    for fmt, target in formats.items():
        module = importlib.import_module(target.partition(":")[0])
        assert module.__name__ == f"rths_hil.drivers.{fmt}.profile_format" and callable(module.load)
    for name in registry.builtin():
        proto = registry.protocol(name)
        assert (proto.profile_protocol is None) == (proto.profile_driver is None)
        assert proto.profile_protocol is None or proto.profile_protocol in formats


def test_finding_imports_no_protocol_package() -> None:
    """Listing drivers and twins imports none of their packages; a lookup imports its own."""
    code = """
        import json, sys
        from rths_hil.drivers import registry
        from rths_hil.sim_backends.registry import available_twins
        registry.available(), available_twins(), registry.profile_formats()
        listed = sorted(m for m in sys.modules if m.startswith(("rths_hil.drivers.",
                        "rths_hil.sim_backends.endpoints.")) and m.count(".") >= 2)
        registry.protocol("can")
        looked = sorted(m for m in sys.modules if m.startswith("rths_hil.drivers."))
        print(json.dumps([listed, looked, "pymodbus" in sys.modules, "canopen" in sys.modules]))
    """
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    ).stdout
    listed, looked, pymodbus, canopen = json.loads(out)
    assert not [m for m in listed if m.split(".")[2] in SHIPPED or "endpoints." in m], listed
    assert "rths_hil.drivers.can" in looked
    # (the CAN link model may use the serial line's helpers; never Modbus's or CANopen's)
    assert not [m for m in looked if m.split(".")[2] in ("modbus", "canopen")], looked
    assert not pymodbus and not canopen


def test_a_folder_whose_protocol_is_not_its_own_is_refused_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_caches: None
) -> None:
    """Every folder under ``drivers/`` is a protocol: one whose ``PROTOCOL`` is another's, or
    that has none, is refused in one line when asked for."""
    _extra_folder(
        monkeypatch,
        "rths_hil.drivers",
        tmp_path,
        {
            "empty/__init__.py": '"""No PROTOCOL here."""\n',
            "wrong/__init__.py": """
                from rths_hil.drivers.can import PROTOCOL
            """,
        },
    )
    found = registry.builtin()
    assert found["wrong"] == "rths_hil.drivers.wrong:PROTOCOL"
    for name in ("wrong", "empty"):
        with pytest.raises(InputError) as exc:
            registry.protocol(name)
        msg = str(exc.value)
        assert "\n" not in msg and f"rths_hil.drivers.{name}" in msg, msg
        assert name == "empty" or "named 'wrong'" in msg, msg
    for name in ("wrong", "empty"):
        sys.modules.pop(f"rths_hil.drivers.{name}", None)


def test_an_endpoint_module_without_a_twin_entry_is_refused_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_caches: None
) -> None:
    """A driver's endpoint module whose ``TWIN`` is not a :class:`TwinEntry` is said in one
    line when its twin is asked for; a module of no driver's name is no twin."""
    _extra_folder(
        monkeypatch,
        "rths_hil.drivers",
        tmp_path / "drivers",
        {"mine/__init__.py": "from rths_hil.drivers.can import PROTOCOL\n"},
    )
    _extra_folder(
        monkeypatch,
        "rths_hil.sim_backends.endpoints",
        tmp_path / "endpoints",
        {"mine.py": 'TWIN = "rths_hil.sim_backends.endpoints.mine:Mine"\n', "helper.py": ""},
    )
    assert twins.builtin_twins()["mine"] == "rths_hil.sim_backends.endpoints.mine"
    assert "helper" not in twins.available_twins()
    with pytest.raises(InputError) as exc:
        twins.twin_class("mine")
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(
        "twin endpoint rths_hil.sim_backends.endpoints.mine: TWIN must be a "
        "rths_hil.sim_backends.registry.TwinEntry"
    ), msg
    for mod in ("rths_hil.drivers.mine", "rths_hil.sim_backends.endpoints.mine"):
        sys.modules.pop(mod, None)

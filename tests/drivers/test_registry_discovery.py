"""The registries find what is shipped, with no list to edit: the protocol packages (a folder
under ``drivers/`` binding ``PROTOCOL``), their profile formats (a ``profile_format`` module's
``FORMAT``) and the twin endpoints (an endpoint module's ``TWIN``). They read the sources, not
import them: what they read is what the modules say when imported, and finding them imports no
bus library."""

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
    twins.clear_cache()
    yield
    registry.clear_cache()
    twins.clear_cache()


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


def test_what_is_read_is_what_the_modules_say() -> None:
    """Each endpoint's ``TWIN`` and each format's ``FORMAT``, read from the source, are the
    imported module's; every protocol's profile format is one of the formats found."""
    for name, entry in twins.builtin_twins().items():
        module = importlib.import_module(entry.target.partition(":")[0])
        assert module.TWIN == entry and entry.driver == name
        cls, got = twins.twin_class(name)
        assert got == entry and cls.__name__ == entry.target.partition(":")[2]
    formats = registry.profile_formats()
    assert list(formats) == ["can", "modbus"] == list(protocol_key().choices)
    for fmt, target in formats.items():
        module = importlib.import_module(target.partition(":")[0])
        assert module.FORMAT == fmt and callable(module.load)
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


def test_a_folder_without_protocol_is_no_driver(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_caches: None
) -> None:
    """A helper package (no ``PROTOCOL``) is not listed; a ``PROTOCOL`` that is not the
    folder's own is refused in one line when asked for."""
    _extra_folder(
        monkeypatch,
        "rths_hil.drivers",
        tmp_path,
        {
            "helpers/__init__.py": '"""Shared code; mentions PROTOCOL in prose only."""\n',
            "wrong/__init__.py": """
                from rths_hil.drivers.can import PROTOCOL
            """,
        },
    )
    found = registry.builtin()
    assert "helpers" not in found and found["wrong"] == "rths_hil.drivers.wrong:PROTOCOL"
    with pytest.raises(InputError) as exc:
        registry.protocol("wrong")
    msg = str(exc.value)
    assert "\n" not in msg and "rths_hil.drivers.wrong" in msg and "named 'wrong'" in msg, msg
    with pytest.raises(InputError, match=r"unknown driver 'helpers'"):
        registry.protocol("helpers")
    sys.modules.pop("rths_hil.drivers.wrong", None)


@pytest.mark.parametrize(
    ("files", "needle"),
    [
        (
            {"bad.py": 'from ..registry import TwinEntry\nTWIN = TwinEntry(f"{__name__}:X")\n'},
            "twin endpoint rths_hil.sim_backends.endpoints.bad: TWIN must be TwinEntry(...) "
            "with literal arguments",
        ),
        (
            {"bad.py": 'from ..registry import TwinEntry\nTWIN = TwinEntry("m:X")\n'},
            "twin endpoint rths_hil.sim_backends.endpoints.bad: TWIN must name its driver",
        ),
        (
            {"bad.py": 'from ..registry import TwinEntry\nTWIN = TwinEntry("m:X", driver="can")\n'},
            "twin endpoints rths_hil.sim_backends.endpoints.bad and "
            "rths_hil.sim_backends.endpoints.can both declare a twin for driver 'can'",
        ),
    ],
)
def test_a_bad_twin_declaration_is_refused_in_one_line(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    clean_caches: None,
    files: dict[str, str],
    needle: str,
) -> None:
    _extra_folder(monkeypatch, "rths_hil.sim_backends.endpoints", tmp_path, files)
    with pytest.raises(InputError) as exc:
        twins.available_twins()
    msg = str(exc.value)
    assert "\n" not in msg and needle in msg, msg


def test_a_twin_declared_over_several_lines_and_a_list(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, clean_caches: None
) -> None:
    """The declaration is one statement however it is laid out; a list of transports is
    read as a tuple, as the module's own."""
    text = """
        from ..registry import TwinEntry

        TWIN: TwinEntry = TwinEntry(  # the lab's twin
            "rths_hil.sim_backends.endpoints.mine:Mine",
            driver="mine",
            transports=["tcp",
                        "pty"],
        )
        OTHER = 1
    """
    _extra_folder(monkeypatch, "rths_hil.sim_backends.endpoints", tmp_path, {"mine.py": text})
    entry = twins.builtin_twins()["mine"]
    assert entry == twins.TwinEntry(
        "rths_hil.sim_backends.endpoints.mine:Mine", driver="mine", transports=("tcp", "pty")
    )

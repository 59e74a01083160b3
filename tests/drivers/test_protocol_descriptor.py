"""The protocol descriptor's shared pieces: :meth:`Protocol.from_hooks` (a package's planning
hooks taken from its link model by name, the defaults for the rest) and :func:`link_model` (the
``link_load`` hook's contract: inputs checked, the link named, written once)."""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import pytest
from rths_hil.drivers.protocol import HOOKS, LinkInputs, Protocol, link_model
from rths_hil.drivers.registry import protocol

from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad


class _Toy:
    """Stands for a driver class (the descriptor only stores it)."""


def _line(c):
    return f"toy {c.get('line', 'A')}"


def _refuse(channels):
    raise InputError("actuators: toy lines carry one channel")


def test_from_hooks_takes_the_hooks_it_finds_and_defaults_the_rest() -> None:
    p = Protocol.from_hooks("toy", _Toy, SimpleNamespace(link_key=_line, check_sharing=_refuse))
    assert p.link_key({"line": "B"}) == "toy B"
    with pytest.raises(InputError, match="one channel"):
        p.check_sharing([])
    # link_load by default: frame sizes unknown, on the link its link_key names
    ld = p.link_load({"line": "C"}, 3, 100)
    assert (ld.link, ld.load, ld.channels, ld.fs) == ("toy C", None, 3, 100.0)
    assert "not checked" in ld.detail
    assert p.link_advice(ld, 0.8) == []
    assert p.inline_twin({}) is False
    assert p.own_link({}) is True and p.own_link({"port": "/dev/ttyUSB0"}) is False


def test_from_hooks_passes_the_other_facts() -> None:
    p = Protocol.from_hooks("toy", _Toy, SimpleNamespace(), path_keys=("map",))
    assert p.path_keys == ("map",)
    assert p.link_key({"b": 2, "a": 1}) == "toy a=1,b=2"  # the default key: sorted settings


@pytest.mark.parametrize("name", ["can", "canopen", "modbus", "serial"])
def test_the_built_in_descriptors_carry_their_link_models_hooks(name) -> None:
    model = importlib.import_module(f"rths_hil.drivers.{name}.linkbudget")
    default = Protocol("x", _Toy)
    p = protocol(name)
    for hook in HOOKS:
        want = getattr(model, hook, None)
        got = getattr(p, hook)
        if want is not None:
            assert got is want, (name, hook)
        elif hook != "link_key":  # the default key closes over the name
            assert got.__code__ is getattr(default, hook).__code__, (name, hook)


def test_link_model_checks_the_inputs_and_names_the_link() -> None:
    seen = []

    @link_model(_line)
    def load(i: LinkInputs) -> LinkLoad:
        """Toy link model."""
        seen.append(i)
        i.connection["line"] = "changed"  # a copy: the caller's settings stay as they are
        return LinkLoad(i.link, 0.5, "toy", **i.base)

    conn = {"line": "B"}
    ld = load(conn, 2, 50, heartbeat_hz=4)
    assert conn == {"line": "B"}
    assert (ld.link, ld.channels, ld.fs) == ("toy B", 2, 50.0)
    assert seen[0].heartbeat_hz == 4.0 and isinstance(seen[0].heartbeat_hz, float)
    assert load.__name__ == "load" and load.__doc__ == "Toy link model."
    for channels, fs in ((0, 50.0), (1, 0.0), (1, "fast")):
        with pytest.raises(InputError):
            load({}, channels, fs)
    assert len(seen) == 1  # refused before the model runs


def test_a_link_model_hook_on_its_own_refuses_bad_inputs() -> None:
    """The packages' hooks check their inputs themselves (not only through the core)."""
    for name in ("can", "canopen", "modbus", "serial"):
        with pytest.raises(InputError, match="channels on a link must be"):
            protocol(name).link_load({}, 0, 100.0)
        with pytest.raises(InputError):
            protocol(name).link_load({}, 1, -1.0)


def test_serial_hook_load_from_the_frame_sizes() -> None:
    """2 channels × (18 + 26 bytes) × 10 bits at 100 Hz on 115 200 baud (the serial driver's
    COBS frames, 8N1), through the hook directly."""
    ld = protocol("serial").link_load({"url": "/dev/ttyUSB0", "baudrate": 115200}, 2, 100.0)
    assert ld.load == pytest.approx(2 * (18 + 26) * 10 * 100 / 115200)
    assert ld.link == "serial /dev/ttyUSB0"

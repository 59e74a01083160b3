"""Each built-in driver declares its connection keys (``CONNECTION``); the registry reads a
connection with the one validator of configuration, profiles and model files (check_table)."""

from __future__ import annotations

import inspect
import math
from pathlib import Path

import pytest
from rths_hil.drivers.can import CANDriver
from rths_hil.drivers.can.profile import CANProfileDriver
from rths_hil.drivers.canopen import CANopenDriver
from rths_hil.drivers.canopen.profiles import PROFILES
from rths_hil.drivers.modbus import ModbusDriver, ModbusProfileDriver
from rths_hil.drivers.registry import BUILTIN, check_connection, create_driver, protocol
from rths_hil.drivers.serial import SerialDriver
from rths_hil.sim_backends.endpoints.can import CANTwin
from rths_hil.sim_backends.endpoints.can_profile import CANProfileTwin
from rths_hil.sim_backends.endpoints.canopen import CANopenTwin, default_eds
from rths_hil.sim_backends.endpoints.modbus import ModbusTwin
from rths_hil.sim_backends.endpoints.modbus_profile import ModbusProfileTwin
from rths_hil.sim_backends.endpoints.serial import SerialTwin
from rths_hil.sim_backends.twin import twin_keys

from rths_hil.cli import main
from rths_hil.config import REQUIRED
from rths_hil.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples" / "controllers"
MODBUS_MAP = EXAMPLES / "modbus_map.toml"
CAN_DBC = EXAMPLES / "can_dbc.toml"
CLASSES = [
    CANDriver,
    CANProfileDriver,
    ModbusDriver,
    ModbusProfileDriver,
    SerialDriver,
    CANopenDriver,
]


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_declared_keys_are_the_constructor_parameters_with_its_defaults(cls) -> None:
    params = inspect.signature(cls.__init__).parameters
    names = [n for n in params if n not in ("self", "profile")]
    assert cls.CONNECTION is not None and sorted(cls.CONNECTION) == sorted(names)
    for name, key in cls.CONNECTION.items():
        default = params[name].default
        if key.default is REQUIRED:  # the constructor has none, or refuses None itself
            assert default in (inspect.Parameter.empty, None), name
        else:
            assert key.default == default, name


def test_the_protocols_expose_the_keys_of_their_drivers() -> None:
    for name in BUILTIN:
        proto = protocol(name)
        assert proto.connection_keys() == dict(proto.driver.CONNECTION), name
        if proto.profile_driver is not None:
            assert proto.connection_keys(True) == dict(proto.profile_driver().CONNECTION)


def _attrs(drv, names):
    return {n: getattr(drv, n) for n in names}


def test_defaults_are_those_of_the_former_constructors() -> None:
    """Built with no connection (but what has no default), each driver holds the values its
    constructor's signature gave before the keys were declared (written out here)."""
    can_d = create_driver("can")
    assert _attrs(can_d, ["interface", "channel", "bitrate", "bus_options", "node"]) == {
        "interface": "virtual", "channel": "rths-hil", "bitrate": None, "bus_options": {},
        "node": 0,
    }  # fmt: skip
    assert can_d._fb_id == 0x180  # the shipped DBC (dbc = none), node 0
    modbus = {
        "transport": "tcp", "host": "127.0.0.1", "port": 502, "device": None,
        "baudrate": 115200, "parity": "E", "stopbits": 1, "connect_timeout": 1.0,
        "estop_timeout": 0.1, "estop_connection": True,
    }  # fmt: skip
    mb = create_driver("modbus")
    assert _attrs(mb, [*modbus, "device_id"]) == {**modbus, "device_id": 1}
    mbp = create_driver("modbus", profile=str(MODBUS_MAP))
    assert isinstance(mbp, ModbusProfileDriver)
    assert _attrs(mbp, list(modbus)) == modbus
    assert mbp.unit == mbp.profile.unit  # device_id none: the profile's unit
    cp = create_driver("can", profile=str(CAN_DBC))
    assert isinstance(cp, CANProfileDriver)
    assert _attrs(cp, ["interface", "channel", "bitrate", "bus_options"]) == {
        "interface": "virtual", "channel": "rths-hil", "bitrate": None, "bus_options": {},
    }  # fmt: skip
    assert create_driver("serial", url="loop://").baudrate == 921600
    co = create_driver("canopen", eds=default_eds("cia402"))
    assert co.profile is PROFILES["cia402"]
    assert _attrs(co, [
        "node_id", "interface", "channel", "bitrate", "bus_options", "counts_per_m",
        "newtons_per_count", "_newtons_given", "force_per_torque", "bridge_node_id",
        "heartbeat_period", "controller_heartbeat", "controller_heartbeat_timeout",
        "device_watchdog", "start_tolerance", "sdo_timeout", "vendor_id", "product_code",
        "configure_pdo",
    ]) == {
        "node_id": 1, "interface": "virtual", "channel": "rths-canopen", "bitrate": None,
        "bus_options": {}, "counts_per_m": 1e7, "newtons_per_count": 0.01,
        "_newtons_given": None, "force_per_torque": 1.0, "bridge_node_id": 127,
        "heartbeat_period": 0.1, "controller_heartbeat": 0.1,
        "controller_heartbeat_timeout": 1.0, "device_watchdog": None,
        "start_tolerance": 1e-3, "sdo_timeout": 0.5, "vendor_id": None,
        "product_code": None, "configure_pdo": True,
    }  # fmt: skip


@pytest.mark.parametrize(
    ("name", "connection", "message"),
    [
        ("can", {"node": 16}, "node: must be ≤ 15, got 16"),
        ("can", {"bitrate": 0}, "bitrate: must be ≥ 1 bit/s, got 0"),
        ("can", {"interface": 5}, "interface: expected a string, got 5"),
        ("can", {"channel": 1.5}, "channel: expected a string or an integer, got 1.5"),
        ("can", {"bus_options": "x"}, "bus_options: expected a table, got 'x'"),
        (
            "can",
            {"nod": 1},
            "nod: unknown key (did you mean 'node'?); known keys: interface, channel, bitrate, "
            "bus_options, dbc, node",
        ),
        ("can", {"profile": str(CAN_DBC), "node": 1}, "node: unknown key"),
        ("modbus", {"device_id": 300}, "device_id: must be ≤ 255, got 300"),
        ("modbus", {"transport": "udp"}, "transport: must be one of tcp, rtu, got 'udp'"),
        ("modbus", {"port": 70000}, "port: must be ≤ 65535, got 70000"),
        ("modbus", {"parity": "X"}, "parity: must be one of N, E, O, M, S, got 'X'"),
        ("modbus", {"estop_connection": 1}, "estop_connection: expected true or false, got 1"),
        ("modbus", {"estop_timeout": "-5 ms"}, "estop_timeout: must be ≥ 0 s, got -0.005"),
        ("modbus", {"profile": str(MODBUS_MAP), "device_id": -1}, "device_id: must be ≥ 0, got -1"),
        ("serial", {}, "url: missing (serial device or pyserial URL"),
        ("serial", {"url": "loop://", "baudrate": "x"}, "baudrate: expected an integer, got 'x'"),
        ("canopen", {}, "eds: missing (the controller's EDS file"),
        ("canopen", {"eds": "x.eds", "node_id": 0}, "node_id: must be ≥ 1, got 0"),
        (
            "canopen",
            {"eds": "x.eds", "start_tolerance": "-1 mm"},
            "start_tolerance: must be ≥ 0 m, got -0.001",
        ),
    ],
)
def test_a_bad_setting_is_one_line_naming_the_key(name, connection, message) -> None:
    with pytest.raises(InputError) as err:
        create_driver(name, **connection)
    text = str(err.value)
    assert text.startswith(f"driver.connection.{message}"), text
    assert "\n" not in text


def test_checks_the_table_cannot_express_stay_with_the_driver() -> None:
    with pytest.raises(InputError, match="transport 'rtu' needs device="):
        create_driver("modbus", transport="rtu")
    with pytest.raises(InputError, match="node_id and bridge_node_id are both 5"):
        create_driver("canopen", eds=default_eds("cia402"), node_id=5, bridge_node_id=5)


def test_values_reach_the_driver_coerced_to_si() -> None:
    mb = create_driver("modbus", connect_timeout="250 ms", estop_timeout="20ms")
    assert math.isclose(mb.connect_timeout, 0.25) and math.isclose(mb.estop_timeout, 0.02)
    co = create_driver("canopen", eds=default_eds("cia402"), heartbeat_period="50 ms")
    assert math.isclose(co.heartbeat_period, 0.05)


def test_with_a_twin_only_the_drivers_keys_are_read() -> None:
    # the serial twin takes transport/host/port of its own and gives the driver its url
    given = {"transport": "pty", "baudrate": 9600}
    assert check_connection(SerialDriver, given, twin=True, defaults=False) == given
    with pytest.raises(InputError, match=r"^run\.toml: driver\.connection\.baudrate: must be ≥ 1"):
        check_connection(SerialDriver, {"transport": "pty", "baudrate": 0}, "run.toml", twin=True)
    with pytest.raises(InputError, match=r"^driver\.connection\.url: missing"):
        check_connection(SerialDriver, {"baudrate": 9600})


def test_run_refuses_a_bad_connection_in_one_line_exit_2(capsys) -> None:
    cfg = ROOT / "examples" / "modbus.toml"
    argv = ["run", str(cfg), "--lockstep", "--no-plot", "-q", "--duration", "0.1"]
    code = main([*argv, "--set", "driver.connection={device_id=300}"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = [x for x in err.splitlines() if "error" in x]
    assert lines == [
        f"rths-hil run: error: {cfg}: driver.connection.device_id: must be ≤ 255, got 300"
    ], err


# -- with a twin: the driver's keys and those its twin's endpoint declares ----------------------

TWINS = {
    "can": (CANTwin, CANProfileTwin),
    "modbus": (ModbusTwin, ModbusProfileTwin),
    "serial": (SerialTwin, None),
    "canopen": (CANopenTwin, None),
}
ENDPOINTS = [c for pair in TWINS.values() for c in pair if c is not None]


@pytest.mark.parametrize("cls", ENDPOINTS, ids=lambda c: c.__name__)
def test_twin_declared_keys_are_the_endpoint_parameters_with_its_defaults(cls) -> None:
    """What an endpoint declares is what its constructor takes (a twin that hands the
    driver's keys on takes those too), with the constructor's defaults."""
    params = inspect.signature(cls.__init__).parameters
    named = [n for n, p in params.items() if n not in ("self", "controller", "profile")]
    named = [n for n in named if params[n].kind is not inspect.Parameter.VAR_KEYWORD]
    passes_on = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    assert set(named) <= set(cls.CONNECTION)
    rest = set(cls.CONNECTION) - set(named)
    assert rest == (set(CANopenDriver.CONNECTION) - set(named) if passes_on else set())
    for name in named:
        assert cls.CONNECTION[name].default == params[name].default, name


def test_twin_keys_are_those_of_the_endpoint_start_twin_builds() -> None:
    for name, (plain, prof) in TWINS.items():
        assert twin_keys(name) == dict(plain.CONNECTION), name
        if prof is not None:
            assert twin_keys(name, profile=True) == dict(prof.CONNECTION), name
    with pytest.raises(InputError, match="no twin of this protocol speaks a profile"):
        twin_keys("serial", profile=True)


def _check(name, connection, profile=False):
    proto = protocol(name)
    cls = proto.profile_driver_class() if profile else proto.driver
    keys = twin_keys(name, profile)
    return check_connection(cls, connection, "run.toml", defaults=False, twin=True, twin_keys=keys)


def test_with_a_twin_only_the_keys_given_come_back_as_the_twin_takes_them() -> None:
    # serial: url is the twin's to give, transport/host/port the twin's own
    given = {"transport": "tcp", "host": "127.0.0.1", "port": 0}
    assert _check("serial", given) == given
    assert _check("modbus", {"port": 0, "device_id": 7}) == {"port": 0, "device_id": 7}
    out = _check("canopen", {"heartbeat_period": "50 ms", "force_object": ""})
    assert math.isclose(out.pop("heartbeat_period"), 0.05) and out == {"force_object": ""}
    assert _check("can", {}) == {}


@pytest.mark.parametrize(
    ("name", "profile", "connection", "message"),
    [
        ("can", False, {"nod": 1}, "nod: unknown key (did you mean 'node'?)"),
        ("can", True, {"bitrat": 1}, "bitrat: unknown key (did you mean 'bitrate'?)"),
        ("modbus", False, {"devce_id": 2}, "devce_id: unknown key (did you mean 'device_id'?)"),
        (
            "modbus",
            True,
            {"alow_remote": 1},
            "alow_remote: unknown key (did you mean 'allow_remote'?)",
        ),
        ("serial", False, {"baudrat": 1}, "baudrat: unknown key (did you mean 'baudrate'?)"),
        ("serial", False, {"transprt": "pty"}, "transprt: unknown key (did you mean 'transport'?)"),
        ("canopen", False, {"node_di": 2}, "node_di: unknown key (did you mean 'node_id'?)"),
        # the twin's own keys, type and range checked
        ("serial", False, {"transport": "usb"}, "transport: must be one of pty, tcp, got 'usb'"),
        ("serial", False, {"port": 70000}, "port: must be ≤ 65535, got 70000"),
        ("modbus", False, {"allow_remote": 1}, "allow_remote: expected true or false, got 1"),
        ("modbus", False, {"device_id": 250}, "device_id: must be ≤ 247, got 250"),
        ("modbus", False, {"device_id": 300}, "device_id: must be ≤ 255, got 300"),  # driver's
        ("canopen", False, {"newtons_per_count": 0}, "newtons_per_count: must be > 0 N/count"),
        # a key of the driver's that the twin does not take: the twin gives the driver its line
        ("serial", False, {"url": "loop://"}, "url: not a setting of the twin"),
        ("modbus", False, {"parity": "N"}, "parity: not a setting of the twin"),
    ],
)
def test_with_a_twin_a_bad_key_is_one_line_naming_it(name, profile, connection, message) -> None:
    with pytest.raises(InputError) as err:
        _check(name, connection, profile)
    text = str(err.value)
    assert text.startswith(f"run.toml: driver.connection.{message}"), text
    assert "\n" not in text


CONFIGS = {
    "can": ROOT / "examples" / "can.toml",
    "modbus": ROOT / "examples" / "modbus.toml",
    "serial": ROOT / "examples" / "serial.toml",
    "canopen": EXAMPLES / "cia402.toml",
}


@pytest.mark.parametrize(
    ("name", "setting", "line"),
    [
        ("can", "{nod=1}", "driver.connection.nod: unknown key (did you mean 'node'?); known "),
        ("modbus", "{devce_id=2}", "driver.connection.devce_id: unknown key (did you mean "),
        ("serial", "{baudrat=9600}", "driver.connection.baudrat: unknown key (did you mean "),
        ("canopen", "{node_di=2}", "driver.connection.node_di: unknown key (did you mean "),
        ("serial", "{transport='usb'}", "driver.connection.transport: must be one of pty, tcp"),
    ],
)
def test_run_with_a_twin_refuses_a_bad_key_in_one_line_exit_2(
    name, setting, line, capsys, monkeypatch
) -> None:
    """Refused by the plan: no twin is started."""
    import rths_hil.sim_backends.twin as twin_mod

    started: list[str] = []
    real = twin_mod.start_twin
    monkeypatch.setattr(
        twin_mod, "start_twin", lambda *a, **k: started.append(a[0]) or real(*a, **k)
    )
    cfg = CONFIGS[name]
    argv = ["run", str(cfg), "--lockstep", "--no-plot", "-q", "--duration", "0.1"]
    code = main([*argv, "--set", f"driver.connection={setting}"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = [x for x in err.splitlines() if "error" in x]
    assert len(lines) == 1 and lines[0].startswith(f"rths-hil run: error: {cfg}: {line}"), err
    assert started == []


def test_a_twin_only_key_reaches_the_twin(tmp_path, monkeypatch) -> None:
    """The serial twin's transport = "tcp" (not its default): the twin listens on TCP and the
    run's driver reaches it there."""
    built: list[dict] = []
    real_init = SerialTwin.__init__

    def spy(self, controller, **conn):
        built.append(conn)
        real_init(self, controller, **conn)

    monkeypatch.setattr(SerialTwin, "__init__", spy)
    cfg = ROOT / "examples" / "serial.toml"
    argv = ["run", str(cfg), "--lockstep", "--no-plot", "-q", "--duration", "0.05"]
    out = tmp_path / "run"
    setting = "driver.connection={transport='tcp', port=0}"
    code = main([*argv, "--set", setting, "--set", f"output.dir='{out}'"])
    assert code == 0
    assert built == [{"transport": "tcp", "port": 0}]

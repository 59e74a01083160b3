"""CANopen connection keys of the wrong type or out of range: one line naming the key, exit 2,
through ``rths-hil run`` as a lab runs it (the drive's EDS, no twin), before any bus is opened."""

from __future__ import annotations

from pathlib import Path

import pytest
from rths_hil.drivers.canopen import CANopenDriver
from rths_hil.drivers.registry import create_driver

from rths_hil.cli import main
from rths_hil.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
VENDOR_EDS = ROOT / "tests" / "partners" / "vendor_cia402.eds"


def lab_config(tmp_path: Path, eds: Path = VENDOR_EDS) -> Path:
    cfg = tmp_path / "lab.toml"
    cfg.write_text(
        f"""[driver]
name = "canopen"
[driver.connection]
eds = "{eds}"
node_id = 5
counts_per_m = 1e6
interface = "virtual"
channel = "bad-keys"
[twin]
enabled = false
[output]
dir = "{tmp_path}/run"
"""
    )
    return cfg


def one_error_line_exit_2(argv: list[str], capsys, *needles: str) -> None:
    """``rths-hil ARGV`` in-process: exit 2, no traceback, one error line holding every needle
    (the run's own start lines before it are information)."""
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = [x for x in err.splitlines() if "error" in x]
    assert len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], err


@pytest.mark.parametrize(
    "setting, needles",
    [
        (
            'counts_per_m="abc"',
            ["driver.connection.counts_per_m: cannot read 'abc' as a quantity in counts/m"],
        ),
        ("counts_per_m=1e300", ["driver.connection.counts_per_m: must be ≤ 1e+12 counts/m"]),
        ('vendor_id="abc"', ["vendor_id must be an UNSIGNED32", "'abc'"]),
        (
            "vendor_id=1.5",
            ["driver.connection.vendor_id: expected a string or an integer, got 1.5"],
        ),
        ('force_object="0x6040"', ["force_object 0x6040:00", "control word"]),
        ('force_object="0x6064:3"', ["no object 0x6064:03 (force_object)"]),
        ('heartbeat_period="0.1 parsec"', ["driver.connection.heartbeat_period"]),
        (
            'configure_pdo="false"',
            ["driver.connection.configure_pdo: expected true or false", "'false'"],
        ),
        ("bitrate=-1", ["driver.connection.bitrate: must be ≥ 1 bit/s, got -1"]),
        ("bitrate=5e5", ["driver.connection.bitrate: expected an integer, got 500000.0"]),
        ("device_watchdog=1e9", ["driver.connection.device_watchdog: must be ≤ 65.535 s"]),
        ("controller_heartbeat=70", ["driver.connection.controller_heartbeat: must be ≤ 65.535 s"]),
        ("node_id=128", ["driver.connection.node_id: must be ≤ 127, got 128"]),
        ("node_idd=5", ["driver.connection.node_idd: unknown key (did you mean 'node_id'?)"]),
    ],
)
def test_bad_key_is_one_line_exit_2(tmp_path, capsys, setting, needles):
    cfg = lab_config(tmp_path)
    argv = ["run", str(cfg), "--confirm-hardware", "--no-plot", "--duration", "0.1"]
    one_error_line_exit_2([*argv, "--set", f"driver.connection.{setting}"], capsys, *needles)


@pytest.mark.parametrize(
    "cut, needle",
    [
        ("[1017]", "has no object 0x1017 (producer heartbeat time, for controller_heartbeat)"),
        ("[6064]", "has no object 0x6064:00 (actual position)"),
    ],
)
def test_eds_without_a_needed_object_is_one_line_exit_2(tmp_path, capsys, cut, needle):
    text = VENDOR_EDS.read_text()
    a = text.index(cut)
    b = text.index("\n[", a + 1)
    eds = tmp_path / "cut.eds"
    eds.write_text(text[:a] + text[b + 1 :])
    cfg = lab_config(tmp_path, eds)
    argv = ["run", str(cfg), "--confirm-hardware", "--no-plot", "--duration", "0.1"]
    one_error_line_exit_2(argv, capsys, needle)


def test_eds_saying_position_is_not_pdo_mappable_is_refused_when_mapping(tmp_path):
    text = VENDOR_EDS.read_text()
    a = text.index("[6064]")
    b = text.index("PDOMapping=1", a)
    eds = tmp_path / "nomap.eds"
    eds.write_text(text[:b] + "PDOMapping=0" + text[b + len("PDOMapping=1") :])
    with pytest.raises(InputError, match=r"0x6064:00 .* is not PDO-mappable"):
        CANopenDriver(eds=str(eds), node_id=5)
    # taken as the device has it: the device's own mapping decides
    assert CANopenDriver(eds=str(eds), node_id=5, configure_pdo=False).configure_pdo is False


def test_times_and_lengths_take_their_units():
    drv = create_driver(
        "canopen",
        eds=str(VENDOR_EDS), node_id=5, heartbeat_period="0.1 s", controller_heartbeat="50ms",
        device_watchdog="0.5 s", start_tolerance="2 mm", vendor_id="0x0000A3C7",
    )  # fmt: skip
    assert drv.heartbeat_period == pytest.approx(0.1)
    assert drv.controller_heartbeat == pytest.approx(0.05)
    assert drv.device_watchdog == pytest.approx(0.5)
    assert drv.start_tolerance == pytest.approx(0.002)
    assert drv.vendor_id == 0xA3C7


def test_the_link_budget_takes_the_units_as_the_driver():
    from rths_hil.drivers.canopen import link_load

    base = {"bitrate": 1_000_000, "interface": "socketcan"}
    a = link_load({**base, "heartbeat_period": "100 ms", "controller_heartbeat": "0.05 s"}, 1, 1024)
    b = link_load({**base, "heartbeat_period": 0.1, "controller_heartbeat": 0.05}, 1, 1024)
    assert a.load == b.load


def test_eds_with_a_read_only_controlword_is_refused(tmp_path):
    text = VENDOR_EDS.read_text()
    a = text.index("[6040]")
    b = text.index("AccessType=rww", a)
    eds = tmp_path / "ro.eds"
    eds.write_text(text[:b] + "AccessType=ro" + text[b + len("AccessType=rww") :])
    with pytest.raises(
        Exception, match=r"0x6040:00 \(Controlword, the control word\) is read-only"
    ):
        CANopenDriver(eds=str(eds), node_id=5)


@pytest.mark.parametrize(
    "eds, message",
    [("/dev/zero", "is not a regular file"), ("/nonexistent/x.eds", "no such file")],
)
def test_an_eds_path_that_is_no_file_is_named_as_such(eds, message):
    with pytest.raises(InputError, match=message):
        CANopenDriver(eds=eds, node_id=5)


def test_the_link_budget_counts_a_fixed_mapping_from_the_eds(tmp_path):
    """The vendor EDS fixes RPDO1 = controlword (16) + target (32) and TPDO1 = statusword (16)
    + position (32) + torque (16) bits, no TPDO2: 6 and 8 bytes, one TPDO per step. The same
    EDS with the mapping writable: the driver's own mapping (6 + 6 + the torque's 2 bytes)."""
    from rths_hil.drivers.canopen import step_frames

    got = step_frames({"eds": str(VENDOR_EDS), "node_id": 5})
    assert (got["rpdo"], got["tpdo1"], got["tpdo2"]) == (6, 8, 0)
    text = VENDOR_EDS.read_text().replace("AccessType=ro\nDefaultValue=0x60", "AccessType=rw\n"
                                          "DefaultValue=0x60")  # fmt: skip
    (tmp_path / "rw.eds").write_text(text)
    got = step_frames({"eds": str(tmp_path / "rw.eds"), "node_id": 5, "force_object": "0x6077"})
    assert (got["rpdo"], got["tpdo1"], got["tpdo2"]) == (6, 6, 2)

"""A force-controlled channel run end to end (``rths-hil run``, lockstep) through each protocol
family's twin: the column example's axial-load channel, and a force-controlled SDOF (``control =
"force"``), over the Modbus map with a force set-point register, a DBC profile with a force
set-point signal, and a CiA 402 drive in cyclic synchronous torque. The twin's plant is the same
force-controlled one each time, so the three records must agree step for step to the wire's
resolution (the set-point's 0.5 N of the DBC, 20 N of the CiA 402 target torque, 2 N in the
SDOF, float32 kN of the map); a built-in fixed-format driver on the load channel is refused by
the CLI in one line, exit 2."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.records.recorder import read_run
from tests.helpers.cli import one_line_exit_2

ROOT = Path(__file__).resolve().parents[2]
COLUMN = ROOT / "examples" / "column_axial.toml"
EXAMPLES = ROOT / "examples" / "controllers"
RUN = ["--lockstep", "--duration", "1.5", "--set", "loop.console=0", "--set", "output.plot=false"]
RUN += ["--set", "actuators.vertical.control.load_ramp=0.5", "-q"]

LOAD = 600e3  # N, the example's control.load
#: the vertical channel's driver per family (the Modbus map is the example's own)
DRIVERS = {
    "modbus": None,
    "can": 'driver = { name = "can", profile = "can_force.toml" }',
    "canopen": 'driver = { name = "canopen", connection = { device_profile = "cia402" } }',
}
#: how far each family's axial force may lie from the map's: its set-point's resolution (N)
#: times the force loop's static gain (1), plus the measured force's (0.5 N DBC, 0.01 N 0x2100)
TOLERANCE = {"can": 0.25 + 0.25, "canopen": 10.0 + 0.01}


def _column(driver: str | None) -> str:
    """The column example with the vertical channel's driver line replaced by ``driver``
    (``None``: the example's own, its profile path made absolute)."""
    text = COLUMN.read_text()
    i = text.index('driver = { name = "modbus"')
    j = text.index("\n", i)
    if driver is None:
        line = text[i:j]
        m = re.search(r'profile = "([^"]+)"', line)
        assert m is not None, line
        driver = line.replace(m.group(1), str(COLUMN.parent / m.group(1)))
    return text[:i] + driver + text[j:]


def _config(directory: Path, family: str) -> Path:
    text = _column(DRIVERS[family])
    dbc = (EXAMPLES / "lab_axis.dbc").read_text()
    anchor = ' SG_ AckCmd : 38|1@0+ (1,0) [0|1] "" Axis\n'
    force = ' SG_ ForceSetpoint : 47|24@0- (0.5,0) [-4194304|4194303.5] "N" Axis\n'
    (directory / "lab_axis.dbc").write_text(dbc.replace(anchor, anchor + force))
    (directory / "can_force.toml").write_text(
        (EXAMPLES / "can_dbc.toml").read_text()
        + '\n[roles.force_setpoint]\nmessage = "AxisCommand"\nsignal = "ForceSetpoint"\n'
    )
    p = directory / f"column_{family}.toml"
    p.write_text(text)
    return p


def _run(directory: Path, family: str):
    out = directory / f"run_{family}"
    code = main(["run", str(_config(directory, family)), *RUN, "--set", f"output.dir={out}"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "completed", summary["trip"]
    return read_run(out).record


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The run over the Modbus map (the example as shipped)."""
    return _run(tmp_path_factory.mktemp("modbus"), "modbus")


@pytest.mark.skipif(not COLUMN.exists(), reason="no example")
@pytest.mark.parametrize("family", ["can", "canopen"])
def test_force_channel_runs_alike_through_each_family(tmp_path, reference, family):
    rec = _run(tmp_path, family)
    ref_f = np.asarray(reference["force_vertical"])
    f = np.asarray(rec["force_vertical"])
    assert f.shape == ref_f.shape
    # the axial load held within 1 % of its target (600 kN) on every step, on each family
    for rec_ in (reference, rec):
        target = np.asarray(rec_["target_vertical"])
        assert np.all(target == LOAD)
        assert np.max(np.abs(np.asarray(rec_["force_vertical"]) / LOAD - 1.0)) < 0.01
    assert np.max(np.abs(f - ref_f)) <= TOLERANCE[family]
    # the displacement-controlled channel beside it: the same run
    np.testing.assert_allclose(rec["measured_horizontal"], reference["measured_horizontal"])


@pytest.mark.skipif(not COLUMN.exists(), reason="no example")
def test_builtin_driver_on_a_load_channel_is_refused(tmp_path, capsys):
    p = tmp_path / "column_builtin.toml"
    p.write_text(_column('driver = { name = "serial" }'))
    one_line_exit_2(["run", str(p), *RUN], capsys, "'serial'", "force")


@pytest.mark.skipif(not COLUMN.exists(), reason="no example")
def test_profile_without_a_force_role_on_a_load_channel_is_refused(tmp_path, capsys):
    p = tmp_path / "column_no_role.toml"
    p.write_text(
        _column(f'driver = {{ name = "modbus", profile = "{EXAMPLES / "modbus_map.toml"}" }}')
    )
    one_line_exit_2(
        ["run", str(p), *RUN], capsys, "roles.force_setpoint is missing", "modbus_map.toml"
    )


def test_cst_refused_by_an_independent_drive_without_it(tmp_path):
    """The partner drive (tests/partners/cia402_drive.py, written from CiA 402 apart from the
    driver and its twin) supports profile position and CSP only (its 0x6502 = 0x81). With a
    lab EDS that lists the target torque 0x6071 the driver asks the drive itself and refuses
    the force channel in one line before writing the mode."""
    from rths_hil.drivers.registry import create_driver

    from rths_hil.errors import InputError
    from tests.partners.canopen_fixtures import EDS, DrivePartner

    eds = tmp_path / "lab_with_torque.eds"
    eds.write_text(
        EDS.read_text() + "\n[6071]\nParameterName=Target torque\nObjectType=0x7\nDataType=0x0003\n"
        "AccessType=rww\nDefaultValue=0\nPDOMapping=1\n"
    )
    drive = DrivePartner(tmp_path, "serial")
    try:
        drv = create_driver("canopen", **{**drive.connection, "eds": str(eds)})
        drv.set_control("force")
        with pytest.raises(InputError) as exc:
            drv.open()
        assert str(exc.value) == (
            "canopen: node 5 does not support cyclic synchronous torque (supported drive "
            "modes 0x6502 = 0x00000081, bit 9 clear): it cannot run a force-controlled channel"
        )
    finally:
        drive.stop()
    assert drive.final is not None and drive.final["mode"] != 10


# ------------------------------------------------------------------------------------------
# a force-controlled SDOF (control = "force": the command from the numerical substructure)
# ------------------------------------------------------------------------------------------
SDOF = """
control = "force"
[structure]
kind = "sdof"
mass = 5000.0
fn = 2.0
damping = 0.02
bouc_wen = false
k_specimen = 1.19e6
[ground_motion]
pga = 1.0
[twin]
specimen = {{ stiffness = 1.19e6, damping = 114.6 }}
{driver}
"""
SDOF_DRIVERS = {
    "modbus": '[driver]\nname = "modbus"\nprofile = "{map}"\nconnection = {{ transport = "tcp" }}',
    "can": '[driver]\nname = "can"\nprofile = "can_force.toml"',
    # a 2 kN·m rating seen as 2 N per count of the target torque (force_per_torque 0.1)
    "canopen": '[driver]\nname = "canopen"\n'
    'connection = {{ device_profile = "cia402", force_per_torque = 0.1 }}',
}
#: the force's and the command's largest departure from the map's run (N): twice the
#: set-point's half resolution plus the measurement's (0.5 N DBC; 2 N CST, 0.01 N 0x2100)
SDOF_TOLERANCE = {"can": 2 * (0.25 + 0.25), "canopen": 2 * (1.0 + 0.005)}


def _sdof_run(directory: Path, family: str):
    _config(directory, "can")  # the DBC profile with its force signal, beside the config
    driver = SDOF_DRIVERS[family].format(map=EXAMPLES / "column_axial_map.toml")
    p = directory / f"sdof_{family}.toml"
    p.write_text(SDOF.format(driver=driver))
    out = directory / f"sdof_{family}"
    sets = ["--set", "loop.console=0", "--set", "output.plot=false", "-q"]
    code = main(
        ["run", str(p), "--lockstep", "--duration", "2", *sets, "--set", f"output.dir={out}"]
    )
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "completed", summary["trip"]
    return read_run(out).record


@pytest.fixture(scope="module")
def sdof_reference(tmp_path_factory):
    return _sdof_run(tmp_path_factory.mktemp("sdof"), "modbus")


@pytest.mark.skipif(not (EXAMPLES / "column_axial_map.toml").exists(), reason="no example")
@pytest.mark.parametrize("family", ["can", "canopen"])
def test_force_controlled_sdof_runs_alike_through_each_family(tmp_path, sdof_reference, family):
    rec = _sdof_run(tmp_path, family)
    ref = sdof_reference
    assert np.max(np.abs(ref["force"])) > 1e3  # the structure loaded the specimen
    for col in ("force", "command"):
        gap = np.max(np.abs(np.asarray(rec[col]) - np.asarray(ref[col])))
        assert gap <= SDOF_TOLERANCE[family], (col, gap)
    # the displacement the force produced: the same to the force gap over the stiffness
    gap = np.max(np.abs(np.asarray(rec["measured"]) - np.asarray(ref["measured"])))
    assert gap <= SDOF_TOLERANCE[family] / 1.19e6

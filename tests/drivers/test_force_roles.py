"""Force-controlled channels on the driver side (issue #35): ``Driver.set_control``, the force
set-point roles of the controller profiles, and the refusals (one line) of a built-in
fixed-format driver and of a profile without a force role."""

from __future__ import annotations

from pathlib import Path

import pytest
from rths_hil.drivers.base import Driver, Feedback
from rths_hil.drivers.profile import load_profile
from rths_hil.drivers.registry import create_driver

from rths_hil.errors import InputError


# ------------------------------------------------------------------------------------------
# the base contract
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "conn"), [("can", {}), ("modbus", {}), ("serial", {"url": "loop://"})]
)
def test_builtin_fixed_format_drivers_refuse_force_with_one_line(name, conn):
    drv = create_driver(name, **conn)
    assert drv.control_modes == ("displacement",)
    with pytest.raises(InputError) as exc:
        drv.set_control("force")
    msg = str(exc.value)
    assert "\n" not in msg
    assert f"driver {name!r}" in msg and "'force'" in msg
    drv.set_control("displacement")
    assert drv.control == "displacement"


class _Echo(Driver):
    """A driver answering each command with a fixed measurement (the base contract only)."""

    name = "echo"
    honours_deadline = True
    control_modes = ("displacement", "force")

    def __init__(self, atomic: bool, measured: tuple[float, float]) -> None:
        super().__init__()
        self.atomic_command = atomic
        self.measured = measured
        self.sent: list[tuple[int, float, bool]] = []

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def estop(self) -> None:
        pass

    def _send_raw(self, seq, displacement, enable):
        self.sent.append((seq, displacement, enable))

    def _recv_internal(self, deadline):
        if not self.sent:
            return None
        return Feedback(self.sent[-1][0], *self.measured, 0)

    def poll(self, timeout, receive=None):
        return Feedback(-1, *self.measured, 0)


@pytest.mark.parametrize("atomic", [True, False])
def test_arming_in_force_mode_holds_the_measured_force(atomic):
    drv = _Echo(atomic, (0.0123, -4567.8))
    drv.set_control("force")
    if atomic:  # the atomic arming command carries the last measured force
        drv.send(7, 0.0, False)  # an earlier run's last command
        assert drv.receive(0.1) is not None
    fb = drv.arm(0.1)
    assert fb is not None and fb.force == pytest.approx(-4567.8)
    seq, value, enable = drv.sent[-1]
    assert (seq, enable) == (0, False)
    assert value == pytest.approx(-4567.8)  # a force set-point, not the position 0.0123


def test_force_command_checked_as_a_force():
    drv = _Echo(True, (0.0, 0.0))
    drv.set_control("force")
    with pytest.raises(InputError, match="command force for step 3 is not finite"):
        drv.send(3, float("nan"))


# ------------------------------------------------------------------------------------------
# Modbus map: roles.force_setpoint
# ------------------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples" / "controllers"
MODBUS_MAP = EXAMPLES / "modbus_map.toml"

FORCE_ROLE = """
[roles.force_setpoint]
table = "holding"
address = 104
type = "int32"
scale = 0.5
units = "N"
"""


def _map(tmp_path: Path, extra: str = FORCE_ROLE, name: str = "map.toml") -> Path:
    p = tmp_path / name
    p.write_text(MODBUS_MAP.read_text() + extra)
    return p


def test_modbus_map_without_force_role_refuses_force_with_one_line():
    drv = create_driver("modbus", profile=str(MODBUS_MAP))
    with pytest.raises(InputError) as exc:
        drv.set_control("force")
    msg = str(exc.value)
    assert "\n" not in msg
    assert f"profile {MODBUS_MAP}: roles.force_setpoint is missing" in msg
    assert drv.control == "displacement"


def test_modbus_map_force_role_is_the_written_point(tmp_path):
    prof = load_profile(_map(tmp_path))
    assert prof.control_modes == ("displacement", "force")
    assert prof.for_control("displacement") is prof
    force = prof.for_control("force")
    sp = force.points["setpoint"]
    assert (sp.role, sp.address, sp.type) == ("force_setpoint", 104, "int32")
    # the raw value in half-newtons: 1234.5 N is 2469 counts, the inverse gives it back
    assert sp.raw_value(1234.5) == 2469 and sp.si(2469) == 1234.5
    # the map's reads are input registers: FC 16 for the force set-point, then FC 4
    assert force.step_functions() == [16, 4] and force.rtu_frames()[0] == (9 + 2 * 2, 8)
    drv = create_driver("modbus", profile=str(tmp_path / "map.toml"))
    drv.set_control("force")
    assert drv.control == "force" and drv._sp.role == "force_setpoint"


def test_force_setpoint_range_is_checked_against_the_force_limit(tmp_path):
    prof = load_profile(_map(tmp_path, FORCE_ROLE.replace("int32", "int16"))).for_control("force")
    prof.check_setpoint_range(16000.0)  # int16 of 0.5 N: ±16383.5 N
    with pytest.raises(InputError) as exc:
        prof.check_setpoint_range(20000.0)
    assert str(exc.value).endswith(
        "roles.force_setpoint: int16 with scale 0.5 carries -16.384…16.3835 kN, not the force "
        "limit ±20 kN (safety.force_limit)"
    )


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ('units = "N"', 'units = "mm"', "roles.force_setpoint.units: 'mm' is a length unit"),
        ('table = "holding"', 'table = "input"', "roles.force_setpoint: the input table is"),
        ("address = 104", "address = 101", "roles.force_setpoint: holding 101–102 overlaps"),
        ('type = "int32"\n', 'type = "float16"\n', "roles.force_setpoint.type: unknown type"),
    ],
)
def test_modbus_force_role_validated_with_one_line(tmp_path, old, new, needle):
    p = _map(tmp_path, FORCE_ROLE.replace(old, new, 1))
    with pytest.raises(InputError) as exc:
        load_profile(p)
    assert "\n" not in str(exc.value)
    assert needle in str(exc.value)


# ------------------------------------------------------------------------------------------
# DBC profile: roles.force_setpoint
# ------------------------------------------------------------------------------------------
CAN_DBC = EXAMPLES / "can_dbc.toml"
DBC_FORCE = ' SG_ ForceSetpoint : 47|16@0- (2,0) [-65536|65534] "N" Axis\n'


def _can(tmp_path: Path, role: str) -> Path:
    dbc = (EXAMPLES / "lab_axis.dbc").read_text()
    anchor = ' SG_ AckCmd : 38|1@0+ (1,0) [0|1] "" Axis\n'
    (tmp_path / "lab_axis.dbc").write_text(dbc.replace(anchor, anchor + DBC_FORCE))
    p = tmp_path / "can.toml"
    p.write_text(CAN_DBC.read_text() + role)
    return p


def test_dbc_profile_without_force_role_refuses_force_with_one_line():
    drv = create_driver("can", profile=str(CAN_DBC))
    with pytest.raises(InputError) as exc:
        drv.set_control("force")
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith(f"can driver: profile {CAN_DBC}: roles.force_setpoint is missing")
    assert drv.control == "displacement"


def test_dbc_force_role_is_the_command_frames_setpoint(tmp_path):
    role = '\n[roles.force_setpoint]\nmessage = "AxisCommand"\nsignal = "ForceSetpoint"\n'
    prof = load_profile(_can(tmp_path, role))
    assert prof.control_modes == ("displacement", "force")
    force = prof.for_control("force")
    assert force.roles["setpoint"].signal == "ForceSetpoint"
    assert force.command.name == "AxisCommand"
    force.check_setpoint_range(60000.0)  # 16 bits of 2 N, limited by the DBC to ±65 kN
    with pytest.raises(InputError, match=r"carries -65\.536…65\.534 kN, not the force limit"):
        force.check_setpoint_range(70000.0)
    drv = create_driver("can", profile=str(tmp_path / "can.toml"))
    drv.set_control("force")
    with pytest.raises(InputError, match=r"command force 70000\.0 N for step 1: out of the DBC"):
        drv.send(1, 70000.0, True)


@pytest.mark.parametrize(
    ("role", "needle"),
    [
        (
            '\n[roles.force_setpoint]\nmessage = "AxisStatus"\nsignal = "ForceActual"\n',
            "roles.force_setpoint: must be a signal of the command message AxisCommand",
        ),
        (
            '\n[roles.force_setpoint]\nmessage = "AxisCommand"\nsignal = "PositionSetpoint"\n',
            "roles.force_setpoint.units: 'mm' is a length unit; the force_setpoint is a force",
        ),
        (
            '\n[roles.force_setpoint]\nmessage = "AxisCommand"\nsignal = "PositionSetpoint"\n'
            'units = "N"\n',
            "AxisCommand.PositionSetpoint is the displacement set-point's signal",
        ),
    ],
)
def test_dbc_force_role_validated_with_one_line(tmp_path, role, needle):
    with pytest.raises(InputError) as exc:
        load_profile(_can(tmp_path, role))
    assert "\n" not in str(exc.value)
    assert needle in str(exc.value)


# ------------------------------------------------------------------------------------------
# CANopen: CiA 402 cyclic synchronous torque, CiA 408
# ------------------------------------------------------------------------------------------
def _eds_without(tmp_path: Path, *sections: str) -> str:
    """The twin's CiA 402 EDS without the objects ``sections`` (e.g. ``"6071"``)."""
    from rths_hil.sim_backends.endpoints.canopen import default_eds

    text = Path(default_eds("cia402")).read_text()
    blocks = text.split("\n[")
    keep = [b for b in blocks if not any(b.startswith(f"{sec}]") for sec in sections)]
    out = "\n[".join(keep)
    for sec in sections:
        out = out.replace(f"=0x{sec}\n", "=0x6502\n")  # (listed objects stay valid)
    p = tmp_path / "drive.eds"
    p.write_text(out)
    return str(p)


def test_cia402_force_mode_maps_the_target_torque():
    from rths_hil.sim_backends.endpoints.canopen import default_eds

    drv = create_driver("canopen", eds=default_eds("cia402"))
    assert drv.profile.setpoint == (0x607A, 0) and drv.profile.mode == (0x6060, 0, 8)
    drv.set_control("force")
    p = drv.profile
    assert (p.setpoint, p.mode, p.setpoint_name) == ((0x6071, 0), (0x6060, 0, 10), "target torque")
    # RPDO1: control word (UNSIGNED16) + target torque (INTEGER16), little-endian
    assert drv.rpdo_layout.fmt.format == "<Hh" and drv.rpdo_layout.bits == 32


@pytest.mark.parametrize(
    ("missing", "needle"),
    [
        ("6071", "has no object 0x6071:00 (target torque)"),
        ("6076", "has no object 0x6076 (motor rated torque) to scale the target torque 0x6071"),
    ],
)
def test_cia402_force_mode_refuses_an_eds_without_what_it_needs(tmp_path, missing, needle):
    drv = create_driver("canopen", eds=_eds_without(tmp_path, missing))
    with pytest.raises(InputError) as exc:
        drv.set_control("force")
    assert "\n" not in str(exc.value) and needle in str(exc.value)
    assert drv.control == "displacement" and drv.profile.setpoint == (0x607A, 0)


def test_cia402_force_mode_needs_a_measured_force():
    from rths_hil.sim_backends.endpoints.canopen import default_eds

    drv = create_driver("canopen", eds=default_eds("cia402"), force_object="")
    with pytest.raises(InputError, match="a force-controlled channel needs the measured force"):
        drv.set_control("force")


def test_cia408_refuses_force_with_one_line():
    from rths_hil.sim_backends.endpoints.canopen import default_eds

    drv = create_driver("canopen", eds=default_eds("cia408"), device_profile="cia408")
    with pytest.raises(InputError) as exc:
        drv.set_control("force")
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith("canopen: device_profile 'cia408' has no force control")


# ------------------------------------------------------------------------------------------
# actions.force_mode / actions.displacement_mode
# ------------------------------------------------------------------------------------------
MODES = """
[actions.force_mode]
table = "holding"
address = 300
value = 2

[actions.displacement_mode]
table = "holding"
address = 300
value = 1
"""


def test_mode_actions_validated_with_one_line(tmp_path):
    load_profile(_map(tmp_path, FORCE_ROLE + MODES, "ok.toml"))  # both, on one register
    cases = [
        (
            MODES,
            "actions.force_mode: selects a force loop, but the profile maps no "
            "roles.force_setpoint",
        ),
        (
            FORCE_ROLE + MODES.replace("value = 1", "value = 2"),
            "actions.displacement_mode: the same write as actions.force_mode",
        ),
    ]
    for i, (extra, needle) in enumerate(cases):
        with pytest.raises(InputError) as exc:
            load_profile(_map(tmp_path, extra, f"bad{i}.toml"))
        assert "\n" not in str(exc.value) and needle in str(exc.value)
    # a controller that selects its loop, with no force loop action: no force channel
    only_disp = MODES.split("[actions.displacement_mode]")[1]
    prof = load_profile(_map(tmp_path, FORCE_ROLE + "[actions.displacement_mode]" + only_disp))
    assert prof.for_control("displacement") is prof
    with pytest.raises(InputError, match=r"actions\.force_mode is missing: the controller"):
        prof.for_control("force")


def test_profile_drivers_switch_back_to_displacement(tmp_path):
    drv = create_driver("modbus", profile=str(_map(tmp_path)))
    drv.set_control("force")
    assert (drv._sp.role, drv._sp.address) == ("force_setpoint", 104)
    drv.set_control("displacement")
    assert (drv._sp.role, drv._sp.address) == ("setpoint", 100)
    role = '\n[roles.force_setpoint]\nmessage = "AxisCommand"\nsignal = "ForceSetpoint"\n'
    can_drv = create_driver("can", profile=str(_can(tmp_path, role)))
    can_drv.set_control("force")
    assert can_drv._sp_sig == "ForceSetpoint"
    can_drv.set_control("displacement")
    assert can_drv._sp_sig == "PositionSetpoint"

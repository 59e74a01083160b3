"""A force-controlled channel through each protocol family's twin (issue #35): the driver in
force mode (:meth:`Driver.set_control`) writes the profile's force set-point, the twin decodes
it and hands it to the plant in N unchanged (equal to what was sent, to the profile's
resolution), and the measured force comes back; the start does not jump (the first force
set-point is the measured force). A profile without a force role is refused by the twin too.

The plant is a recording force-controlled stand-in (``control = "force"``, the
:class:`~rths_hil.sim_backends.base.Plant` protocol): it stores each set-point it is given and
answers with a spring's displacement and a force of its own (0.9 × the set-point, so that the
force read back is not the set-point echoed by mistake).
"""

from __future__ import annotations

import struct
from pathlib import Path

import can
import pytest
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.twin import start_twin

from rths_hil.errors import InputError

pytestmark = pytest.mark.timing  # TCP servers, CAN buses and threads

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples" / "controllers"
MODBUS_MAP = EXAMPLES / "modbus_map.toml"
CAN_DBC = EXAMPLES / "can_dbc.toml"

STIFFNESS = 2.0e6  # N/m
RATIO = 0.9  # measured force / set-point of the stand-in plant
#: set-points of a short test (N): the first is the measured force at rest (no start jump)
FORCES = [0.0, 1234.56, -2500.26, 7777.7, 12.3, -0.4, 40000.0]


class ForceSpring:
    """A force-controlled stand-in plant: records each set-point (N)."""

    control = "force"
    dt = 1.0 / 1024.0

    def __init__(self) -> None:
        self.got: list[float] = []

    def reset(self) -> None:
        pass

    def step(self, command: float) -> tuple[float, float]:
        self.got.append(command)
        f = RATIO * command
        return f / STIFFNESS, f


def _run(drv, forces):
    """Arm, then one force set-point per step; the feedbacks."""
    fb0 = drv.arm(1.0)
    assert fb0 is not None
    out = []
    for k, f in enumerate(forces):
        drv.send(k, f, True)
        fb = drv.receive(1.0)
        assert fb is not None and fb.seq == k, (k, fb)
        out.append(fb)
    return fb0, out


# ------------------------------------------------------------------------------------------
# Modbus map
# ------------------------------------------------------------------------------------------
#: a force set-point in half-newtons, int32 (resolution 0.5 N), holding registers 104–105
MODBUS_FORCE_ROLE = """
[roles.force_setpoint]      # written every step instead of the set-point in force control
table = "holding"
address = 104
type = "int32"
scale = 0.5
units = "N"
"""


def _modbus_force_map(tmp_path: Path, fc23: bool = False) -> Path:
    text = MODBUS_MAP.read_text() + MODBUS_FORCE_ROLE
    if fc23:  # every point in holding registers: one FC 23 per step
        text = text.replace('table = "input"', 'table = "holding"')
    p = tmp_path / "map_force.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(("fc23", "transport"), [(False, "tcp"), (True, "tcp"), (False, "rtu")])
def test_modbus_map_force_channel_through_its_twin(tmp_path, fc23, transport):
    plant = ForceSpring()
    prof = _modbus_force_map(tmp_path, fc23)
    with start_twin("modbus", plant, transport=transport, profile=str(prof)) as twin:
        drv = create_driver("modbus", **twin.connection)
        drv.set_control("force")
        assert drv.profile.fc23 is fc23
        with drv:
            fb0, fbs = _run(drv, FORCES)
            regs = None
            if transport == "tcp":  # the force set-point registers, read by pymodbus's client
                from pymodbus.client import ModbusTcpClient

                with ModbusTcpClient(twin.connection["host"], port=twin.connection["port"]) as c:
                    regs = c.read_holding_registers(104, count=2, device_id=1).registers
    if regs is not None:  # int32, high word first (the map's word order): half-newtons
        assert struct.unpack(">i", struct.pack(">HH", *regs))[0] == round(FORCES[-1] / 0.5)
    assert fb0.force == 0.0
    # the twin stepped its plant once per enabled step, with the set-point in N as sent, to
    # the map's resolution (0.5 N, round half to even as Python's round)
    assert plant.got == [round(f / 0.5) * 0.5 for f in FORCES]
    for f, fb in zip(FORCES, fbs, strict=True):
        sent = round(f / 0.5) * 0.5
        # float32 kN and mm in the map: 7 significant digits
        assert fb.force == pytest.approx(RATIO * sent, rel=1e-6, abs=1e-3)
        assert fb.displacement == pytest.approx(RATIO * sent / STIFFNESS, rel=1e-6, abs=1e-9)


def test_modbus_twin_refuses_a_force_plant_without_a_force_role():
    with pytest.raises(InputError) as exc:
        start_twin("modbus", ForceSpring(), port=0, profile=str(MODBUS_MAP))
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith("modbus twin: profile ") and "roles.force_setpoint is missing" in msg


# ------------------------------------------------------------------------------------------
# CAN with the lab's DBC
# ------------------------------------------------------------------------------------------
#: a force set-point signal in the command frame: Motorola, 24 bits from bit 47, 0.5 N
DBC_FORCE_SIGNAL = ' SG_ ForceSetpoint : 47|24@0- (0.5,0) [-4194304|4194303.5] "N" Axis\n'
CAN_FORCE_ROLE = """
[roles.force_setpoint]
message = "AxisCommand"
signal = "ForceSetpoint"
"""


def _can_force_profile(tmp_path: Path, role: bool = True) -> Path:
    dbc = (EXAMPLES / "lab_axis.dbc").read_text()
    anchor = ' SG_ AckCmd : 38|1@0+ (1,0) [0|1] "" Axis\n'
    assert anchor in dbc
    (tmp_path / "lab_axis.dbc").write_text(dbc.replace(anchor, anchor + DBC_FORCE_SIGNAL))
    p = tmp_path / "can_force.toml"
    p.write_text(CAN_DBC.read_text() + (CAN_FORCE_ROLE if role else ""))
    return p


def test_can_profile_force_channel_through_its_twin(tmp_path):
    import cantools

    plant = ForceSpring()
    prof = _can_force_profile(tmp_path)
    with start_twin("can", plant, profile=str(prof)) as twin:
        drv = create_driver("can", **twin.connection)
        drv.set_control("force")
        with drv:
            fb0, fbs = _run(drv, FORCES)
            frame = bytes(drv._cmd_data)  # the last command frame as it went out
    assert fb0.force == 0.0
    # the set-point decoded by the twin is what was sent, to the signal's 0.5 N
    assert plant.got == pytest.approx([round(f / 0.5) * 0.5 for f in FORCES], abs=1e-9)
    for f, fb in zip(FORCES, fbs, strict=True):
        sent = round(f / 0.5) * 0.5
        assert fb.force == pytest.approx(RATIO * sent, abs=0.25)  # ForceActual: 0.5 N
        assert fb.displacement == pytest.approx(RATIO * sent / STIFFNESS, abs=0.5e-7)
    # the frame read with cantools from the DBC file alone: the force in its signal, the
    # displacement set-point untouched, the enable on
    db = cantools.database.load_file(str(tmp_path / "lab_axis.dbc"))
    v = db.get_message_by_name("AxisCommand").decode(frame)
    assert v["ForceSetpoint"] == 40000.0 and v["PositionSetpoint"] == 0.0 and v["EnableCmd"] == 1


def test_can_twin_refuses_a_force_plant_without_a_force_role(tmp_path):
    with pytest.raises(InputError) as exc:
        start_twin("can", ForceSpring(), profile=str(_can_force_profile(tmp_path, role=False)))
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith("can twin: profile ") and "roles.force_setpoint is missing" in msg
    assert "a signal of the command message AxisCommand" in msg


# ------------------------------------------------------------------------------------------
# CANopen CiA 402: cyclic synchronous torque
# ------------------------------------------------------------------------------------------
#: the twin's EDS: motor rated torque 0x6076 = 20 000 000 mN (a linear motor rated 20 kN)
RATED_MN = 20_000_000
#: a CST test: the arming force held while the drive walks its state machine, then forces
CST_FORCES = [0.0] * 4 + [1234.56, -2500.26, 7777.7, 12.3, 40000.0, -65000.0]


@pytest.mark.parametrize(("force_object", "force_per_torque"), [(None, 1.0), ("0x6077", 2.0)])
def test_cia402_cst_force_channel_through_its_twin(force_object, force_per_torque):
    plant = ForceSpring()
    keys = {"force_per_torque": force_per_torque}
    with start_twin("canopen", plant, device_profile="cia402", **keys) as twin:
        conn = dict(twin.connection)
        if force_object is not None:  # the torque actual, scaled by 0x6076 as the target
            conn["force_object"] = force_object
            del conn["newtons_per_count"]
        drv = create_driver("canopen", **conn)
        drv.set_control("force")
        drv.open()
        # every frame on the bus, read by a bus of its own (python-can's virtual interface)
        spy = can.Bus(interface="virtual", channel=conn["channel"], receive_own_messages=False)
        try:
            assert twin.mode == 10  # written at start-up: cyclic synchronous torque
            assert "0x6040:00 + 0x6071:00" in drv.mapping["RPDO1"]
            fb0, fbs = _run(drv, CST_FORCES)
            rpdos = []
            while (msg := spy.recv(0.0)) is not None:
                if msg.arbitration_id == 0x200 + conn["node_id"]:
                    rpdos.append(bytes(msg.data))
        finally:
            spy.shutdown()
            drv.close()
    per = RATED_MN / 1e6 * force_per_torque  # N per per-mille of the rated torque
    want = [round(f / per) * per for f in CST_FORCES]
    # RPDO1 as CiA 301 lays it out (little-endian, in mapping order): the control word
    # (UNSIGNED16) and the target torque 0x6071 (INTEGER16, per mille of 0x6076); the last
    # steps' frames carry enable operation (0x000F) and each step's torque
    sent = [struct.unpack("<Hh", d) for d in rpdos[-6:]]
    assert sent == [(0x000F, round(f / per)) for f in CST_FORCES[-6:]]
    # the drive follows from OPERATION ENABLED (armed to SWITCHED ON, the first enabled step
    # enables operation): the plant got the target torque of each step from then on, in N,
    # as sent, to 1 ‰ of 0x6076
    n = len(plant.got)
    assert n >= len(CST_FORCES) - 4
    assert plant.got == pytest.approx(want[-n:], abs=1e-9)
    res = per if force_object == "0x6077" else 0.01  # the torque actual: 1 ‰ of the rating
    for sent, fb in zip(want[-n:], fbs[-n:], strict=True):
        assert fb.force == pytest.approx(RATIO * sent, abs=res / 2 + 1e-9)
        assert fb.displacement == pytest.approx(RATIO * sent / STIFFNESS, abs=1e-7)
    assert fb0.force == 0.0 and all(fb.status & 0x01 for fb in fbs[-n:])


def test_cia402_cst_refused_by_a_position_only_drive():
    """The displacement twin supports cyclic synchronous position only (0x6502 bit 7)."""
    from rths_hil.sim_backends.twin import default_plant

    with start_twin("canopen", default_plant(), device_profile="cia402") as twin:
        drv = create_driver("canopen", **twin.connection)
        drv.set_control("force")
        with pytest.raises(InputError) as exc:
            drv.open()
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg == (
        "canopen: node 1 does not support cyclic synchronous torque (supported drive modes "
        "0x6502 = 0x00000080, bit 9 clear): it cannot run a force-controlled channel"
    )


def test_canopen_twin_refuses_a_force_plant_on_cia408():
    with pytest.raises(InputError, match="device_profile 'cia408' has no force control"):
        start_twin("canopen", ForceSpring(), device_profile="cia408")


# ------------------------------------------------------------------------------------------
# a controller that selects its loop on command (actions.force_mode / displacement_mode)
# ------------------------------------------------------------------------------------------
#: the map's control-mode register: 1 displacement loop, 2 force loop
MODBUS_MODES = """
[actions.force_mode]
table = "holding"
address = 300
value = 2

[actions.displacement_mode]
table = "holding"
address = 300
value = 1
"""
#: the DBC's loop bit in the command frame (byte 4, bit 5): 1 force loop, 0 displacement loop
DBC_LOOP_SIGNAL = ' SG_ ForceLoop : 37|1@0+ (1,0) [0|1] "" Axis\n'
CAN_MODES = """
[actions.force_mode]
message = "AxisCommand"
signal = "ForceLoop"
value = 1

[actions.displacement_mode]
message = "AxisCommand"
signal = "ForceLoop"
value = 0
"""


def _with_modes(path: Path, modes: str, name: str) -> Path:
    p = path.parent / name
    p.write_text(path.read_text() + modes)
    return p


def _can_loop_profile(tmp_path: Path) -> Path:
    prof = _can_force_profile(tmp_path)
    dbc = tmp_path / "lab_axis.dbc"
    text = dbc.read_text()
    anchor = ' SG_ AckCmd : 38|1@0+ (1,0) [0|1] "" Axis\n'
    dbc.write_text(text.replace(anchor, anchor + DBC_LOOP_SIGNAL))
    return prof


@pytest.mark.parametrize("family", ["modbus", "can"])
def test_controller_selecting_its_loop_follows_force_once_selected(tmp_path, family):
    """The driver selects the force loop (Modbus: the mode register written at arming, read
    back with pymodbus's client; CAN: the loop bit in every command frame) and the twin
    follows; a driver whose profile does not select it is not followed (the twin holds,
    never ENABLED), as such a controller stays in its displacement loop."""
    if family == "modbus":
        base = _modbus_force_map(tmp_path)
        modes, extra = MODBUS_MODES, {"port": 0}
    else:
        base = _can_loop_profile(tmp_path)
        modes, extra = CAN_MODES, {}
    full = _with_modes(base, modes, f"{family}_modes.toml")
    plant = ForceSpring()
    with start_twin(family, plant, profile=str(full), **extra) as twin:
        drv = create_driver(family, **twin.connection)
        drv.set_control("force")
        with drv:
            _, fbs = _run(drv, FORCES)
            if family == "modbus":
                from pymodbus.client import ModbusTcpClient

                with ModbusTcpClient(twin.connection["host"], port=twin.connection["port"]) as c:
                    assert c.read_holding_registers(300, count=1).registers == [2]
            else:
                assert drv._values["ForceLoop"] == 1.0
        assert len(plant.got) == len(FORCES) and all(fb.status & 0x01 for fb in fbs)
        # the same controller, driven through the profile without the mode actions
        plant.got.clear()
        other = create_driver(family, **{**twin.connection, "profile": str(base)})
        other.set_control("force")
        with other:
            if family == "modbus":  # the register holds the last run's loop: back to 1
                from pymodbus.client import ModbusTcpClient

                with ModbusTcpClient(twin.connection["host"], port=twin.connection["port"]) as c:
                    c.write_register(300, 1)
            _, fbs = _run(other, FORCES)
        assert plant.got == [] and not any(fb.status & 0x01 for fb in fbs)

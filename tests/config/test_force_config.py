"""control.mode, control.load, control.load_schedule and control.load_ramp: read, refused in one
line (exit 2), and what the plan makes of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.hybrid.plan import LoadSchedule, build_plan
from tests.helpers.cli import one_line_exit_2
from tests.helpers.force_channels import force_map


def _cfg(tmp_path, text: str, sets=()):
    p = tmp_path / "c.toml"
    p.write_text(text)
    return load_config(p, sets)


TWO = """
[[actuators]]
name = "h"
[[actuators]]
name = "v"
"""


def test_modes_read_from_the_section_the_shorthand_and_set(tmp_path):
    assert _cfg(tmp_path, "")["control"]["mode"] == "displacement"
    assert _cfg(tmp_path, 'control = "force"\n')["control"]["mode"] == "force"
    assert _cfg(tmp_path, '[control]\nmode = "force"\n')["control"]["mode"] == "force"
    assert _cfg(tmp_path, "", ["control=force"])["control"]["mode"] == "force"
    cfg = _cfg(
        tmp_path,
        TWO + 'control = {mode = "load", load = "250 kN"}\nsafety = {force_limit = 1e6}\n',
    )
    h, v = cfg.channels()
    assert h.config["control"]["mode"] == "displacement"
    assert v.config["control"] == {
        "mode": "load",
        "load": 250e3,
        "load_schedule": [],
        "load_ramp": 0.0,
    }
    cfg = _cfg(tmp_path, TWO, ["actuators.v.control=load", "actuators.v.control.load=3e3"])
    assert cfg.channels()[1].config["control"]["load"] == 3e3
    cfg = _cfg(
        tmp_path,
        '[control]\nmode = "load"\nload_schedule = [[0, "10 kN"], ["1.5 s", 2e4]]\n'
        'load_ramp = "500 ms"\n',
    )
    assert cfg["control"]["load_schedule"] == [[0.0, 10e3], [1.5, 2e4]]
    assert cfg["control"]["load_ramp"] == 0.5


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('control = "torque"', "control.mode: must be one of displacement, force, load"),
        ('[control]\nmode = "load"', "control.load: a control.mode = 'load' channel needs"),
        ("[control]\nload = 5.0", "only a control.mode = 'load' channel holds a load"),
        (
            '[control]\nmode = "load"\nload = 1.0\nload_schedule = [[0, 1]]',
            "give control.load or control.load_schedule, not both",
        ),
        (
            '[control]\nmode = "load"\nload_schedule = [[1, 1], [0.5, 2]]',
            "load_schedule[1][0]: the times must not decrease",
        ),
        (
            '[control]\nmode = "load"\nload_schedule = [[1, 1, 3]]',
            "load_schedule[0]: expected a pair [time, value]",
        ),
        (
            '[control]\nmode = "load"\nload_schedule = [[-1, 1]]',
            "load_schedule[0][0]: the time must be a finite number ≥ 0 s",
        ),
        (
            '[control]\nmode = "load"\nload = "200 kN"',
            "control.load: 200000 N is not inside the force limit ±100000 N",
        ),
        ('[control]\nmode = "load"\nload = "2 m"', "control.load"),
        ("[control]\nload_ramp = -1", "control.load_ramp: must be ≥ 0"),
        (
            'control = "force"\n[structure]\nk_specimen = 0',
            "structure.k_specimen: a control.mode = 'force' channel",
        ),
        ("[twin]\nforce_loop_gain = 0", "twin.force_loop_gain: must be > 0"),
    ],
)
def test_refused_in_one_line_exit_2(tmp_path, capsys, text, message):
    p = tmp_path / "bad.toml"
    p.write_text(text + "\n")
    with pytest.raises(InputError) as exc:
        load_config(p)
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)
    one_line_exit_2(["run", str(p), "--lockstep", "--duration", "0.1", "-q"], capsys, message)


def test_load_schedule_is_piecewise_linear_and_held_at_the_ends():
    s = LoadSchedule(0.0, [[0.5, 100.0], [1.5, 300.0], [2.0, 300.0], [3.0, -100.0]])
    t = np.array([0.0, 0.5, 1.0, 1.5, 1.75, 2.5, 3.0, 9.0])
    want = [100.0, 100.0, 200.0, 300.0, 300.0, 100.0, -100.0, -100.0]
    assert [s.at(x) for x in t] == pytest.approx(want)
    assert s.peak == 300.0
    c = LoadSchedule(-5e3)
    assert c.at(0.0) == c.at(100.0) == -5e3


def test_plan_of_a_mixed_test(tmp_path):
    text = (
        TWO
        + '[actuators.control]\nmode = "load"\nload = "50 kN"\nload_ramp = 1.0\n'
        + "[actuators.safety]\nforce_limit = 1e6\n"
        + f'[actuators.driver]\nname = "modbus"\nprofile = "{force_map(tmp_path)}"\n'
    )
    plan = build_plan(_cfg(tmp_path, text), tmp_path / "run", duration=0.5)
    h, v = plan.channels
    assert (h.control, h.wire_control, h.dof) == ("displacement", "displacement", 0)
    assert (v.control, v.wire_control, v.dof) == ("load", "force", -1)
    assert not np.any(v.row) and v.load.at(0.0) == 50e3 and v.load_ramp == 1.0
    assert v.monitor.force_mode and not h.monitor.force_mode
    # the load channel's twin is the force-controlled one
    assert getattr(v.plant, "control", "displacement") == "force"
    assert getattr(h.plant, "control", "displacement") == "displacement"
    # the default ramp of a force channel is the start ramp's
    text = f'control = "force"\n[driver]\nname = "modbus"\nprofile = "{force_map(tmp_path)}"\n'
    plan = build_plan(_cfg(tmp_path, text), tmp_path / "r2", duration=0.5)
    (ch,) = plan.channels
    assert ch.load_ramp == 2.0 and ch.k_force == 1.19e6


def test_plan_refusals(tmp_path):
    with pytest.raises(InputError, match="every channel holds a load"):
        build_plan(
            _cfg(tmp_path, '[control]\nmode = "load"\nload = 1e3\n'), tmp_path / "r", duration=0.5
        )
    text = (
        TWO.replace('name = "v"', 'name = "v"\ndof = 1') + 'control = {mode = "load", load = 1}\n'
    )
    with pytest.raises(InputError, match=r"actuators\[1\] \(v\)\.dof: a control.mode = 'load'"):
        build_plan(_cfg(tmp_path, text), tmp_path / "r", duration=0.5)
    # the built-in fixed-format drivers run displacement only
    with pytest.raises(InputError, match="driver 'modbus' cannot run a force-controlled channel"):
        build_plan(
            _cfg(tmp_path, 'control = "force"\n[driver]\nname = "modbus"\n'),
            tmp_path / "r",
            duration=0.5,
        )


def test_commissioning_a_force_channel_is_refused(tmp_path, capsys):
    """Commissioning moves each actuator in displacement: a force set-point would take its
    motions as newtons."""
    example = Path(__file__).resolve().parents[2] / "examples" / "column_axial.toml"
    one_line_exit_2(
        ["commission", str(example), "--yes", "--out", str(tmp_path / "c")],
        capsys,
        "commissioning moves each actuator in displacement control; channel vertical is "
        "load-controlled",
    )

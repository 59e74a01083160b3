"""The TOML model file: round trip, the plant it builds, and one clear error per bad key."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from rths_hil.sim_backends.effects import make_effect
from rths_hil.sim_backends.modelfile import (
    ActuatorSpec,
    EffectSpec,
    ModelSpec,
    SpecimenSpec,
    dump_model,
    load_model,
    load_plant,
    model_to_toml,
)
from rths_hil.sim_backends.models import make_model
from rths_hil.sim_backends.plant import Sensor, TwinPlant
from rths_hil.sim_backends.specimen import KelvinVoigt

from rths_hil.errors import InputError

DT = 1.0 / 1024.0

FULL = """\
[actuator]
delay = "12ms"
gain = 0.98
model = "first_order"
time_constant = 0.008

[[actuator.effects]]
kind = "backlash"
width = "0.2mm"

[[actuator.effects]]
kind = "time_varying_delay"
delay = 0.01
amplitude = 0.002
period = 7.5

[[actuator.effects]]
kind = "force_feedback"
actuator_stiffness = 5e7

[specimen]
stiffness = 2e6
damping = 300.0

[sensor]
displacement_noise = 1e-5
force_noise = 2.5
displacement_resolution = 1e-6
force_resolution = 0.1
seed = 11
"""


def _write(tmp_path, text: str, name: str = "twin.toml"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _cmd(n: int = 4096) -> np.ndarray:
    t = np.arange(n) * DT
    return 0.02 * np.sin(2 * np.pi * 0.8 * t) * np.minimum(t, 1.0)


def test_full_file_loads_with_units_and_defaults(tmp_path):
    spec = load_model(_write(tmp_path, FULL))
    a = spec.actuator
    assert a.delay == pytest.approx(0.012)
    assert a.gain == 0.98
    assert a.model == "servo_lag"  # the old name "first_order" reads as servo_lag
    assert a.params == {"time_constant": 0.008}
    assert [e.kind for e in a.effects] == ["backlash", "time_varying_delay", "force_feedback"]
    assert a.effects[0].params == {"width": pytest.approx(2e-4)}
    # force_feedback takes the specimen's stiffness and damping
    assert a.effects[2].params == {
        "actuator_stiffness": 5e7,
        "specimen_stiffness": 2e6,
        "specimen_damping": 300.0,
    }
    assert spec.specimen == SpecimenSpec(stiffness=2e6, damping=300.0, mass=0.0)
    assert spec.sensor == Sensor(1e-5, 2.5, 1e-6, 0.1, 11)


def test_round_trip_through_toml(tmp_path):
    spec = load_model(_write(tmp_path, FULL))
    out = tmp_path / "out.toml"
    dump_model(spec, out, header="calibrated\nsecond line")
    text = out.read_text()
    assert text.startswith("# calibrated\n# second line\n")
    assert tomllib.loads(text)["actuator"]["effects"][1]["kind"] == "time_varying_delay"
    again = load_model(out)
    assert again.to_dict() == spec.to_dict()
    # and from the parsed dict
    assert load_model(tomllib.loads(text)).to_dict() == spec.to_dict()


def test_toml_floats_survive_exactly():
    spec = ModelSpec(
        ActuatorSpec(
            delay=0.1 + 0.2, gain=1 / 3, effects=[EffectSpec("offset", {"offset": -1e-300})]
        )
    )
    back = load_model(tomllib.loads(model_to_toml(spec)))
    assert back.actuator.delay == 0.1 + 0.2
    assert back.actuator.gain == 1 / 3
    assert back.actuator.effects[0].params["offset"] == -1e-300


def test_plant_equals_manual_composition(tmp_path):
    plant = load_plant(_write(tmp_path, FULL), DT)
    manual = TwinPlant(
        make_model("servo_lag", DT, delay=0.012, gain=0.98, time_constant=0.008),
        [
            make_effect("backlash", DT, width=2e-4),
            make_effect("time_varying_delay", DT, delay=0.01, amplitude=0.002, period=7.5),
            make_effect(
                "force_feedback",
                DT,
                actuator_stiffness=5e7,
                specimen_stiffness=2e6,
                specimen_damping=300.0,
            ),
        ],
        KelvinVoigt(2e6, 300.0, DT),
        Sensor(1e-5, 2.5, 1e-6, 0.1, 11),
    )
    x = _cmd()
    for a, b in zip(plant.simulate(x), manual.simulate(x), strict=True):
        np.testing.assert_array_equal(a, b)
    assert plant.dt == DT


def test_minimal_file_and_defaults(tmp_path):
    spec = load_model(_write(tmp_path, "[actuator]\ndelay = 0.01\ngain = 1.0\n"))
    assert spec.actuator == ActuatorSpec(delay=0.01, gain=1.0)
    assert spec.specimen is None and spec.sensor == Sensor()
    plant = spec.build(DT)
    x = _cmd()
    d, f = plant.simulate(x)
    from rths_hil.sim_backends.delay import fractional_delay

    np.testing.assert_allclose(d, fractional_delay(x, 0.01, 1 / DT), atol=1e-15)
    # default specimen: the benchmark's spring-dashpot
    np.testing.assert_allclose(f, KelvinVoigt(1.19e6, 114.6, DT).simulate(d), rtol=1e-12)


def test_benchmark_model_takes_specimen_keys():
    spec = load_model({"actuator": {"model": "benchmark"}, "specimen": {"stiffness": 3e6}})
    assert spec.actuator.params == {"specimen_stiffness": 3e6}
    spec = load_model(
        {
            "actuator": {"model": "benchmark", "specimen_stiffness": 1e6},
            "specimen": {"stiffness": 3e6},
        }
    )
    assert spec.actuator.params == {"specimen_stiffness": 1e6}


BAD = [
    (
        "[actuator]\n[[actuator.effects]]\nkind='offset'\noffset=1e-3\n"
        "[[actuator.effects]]\nkind='foo'\n",
        "twin.toml: actuator.effects[1].kind: unknown effect 'foo' (known: offset, drift, "
        "backlash, velocity_limit, stroke_limit, servo_lag, time_varying_delay, force_feedback)",
    ),
    ("[actuator]\ndealy = 0.01\n", "twin.toml: actuator.dealy: unknown key"),
    ("[actuator]\n[sensr]\n", "twin.toml: sensr: unknown key"),
    ("[sensor]\n", "twin.toml: actuator: missing table [actuator]"),
    (
        "[actuator]\nmodel = 'hexapod'\n",
        "twin.toml: actuator.model: unknown actuator model 'hexapod'",
    ),
    ("[actuator]\nmodel = 'servo_lag'\n", "twin.toml: actuator.time_constant: required by model"),
    (
        "[actuator]\nmodel = 'servo_lag'\ntime_constant = -1.0\n",
        "twin.toml: actuator.time_constant: must be > 0",
    ),
    ("[actuator]\ndelay = -0.001\n", "twin.toml: actuator.delay: must be ≥ 0 s"),
    ("[actuator]\ndelay = '5 parsecs'\n", "twin.toml: actuator.delay: cannot read value"),
    ("[actuator]\ngain = 'high'\n", "twin.toml: actuator.gain: cannot read value 'high'"),
    ("[actuator]\ngain = true\n", "twin.toml: actuator.gain: expected a number, got true"),
    ("[actuator]\ngain = nan\n", "twin.toml: actuator.gain: must be a finite number"),
    (
        "[actuator]\n[[actuator.effects]]\nwidth = 1e-4\n",
        "twin.toml: actuator.effects[0].kind: missing",
    ),
    (
        "[actuator]\n[[actuator.effects]]\nkind = 'backlash'\nwidht = 1e-4\n",
        "twin.toml: actuator.effects[0].widht: unknown key (did you mean 'width'?)",
    ),
    (
        "[actuator]\n[[actuator.effects]]\nkind = 'backlash'\n",
        "twin.toml: actuator.effects[0].width: required by effect 'backlash'",
    ),
    ("[actuator]\neffects = 3\n", "twin.toml: actuator.effects: expected an array of tables"),
    (
        "[actuator]\n[specimen]\nmodel = 'bouc_wen'\n",
        "twin.toml: specimen.model: must be one of kelvin_voigt",
    ),
    ("[actuator]\n[specimen]\nstiffness = -5.0\n", "twin.toml: specimen.stiffness: must be ≥ 0"),
    (
        "[actuator]\n[sensor]\nseed = 1.5\n",
        "twin.toml: sensor.seed: expected an integer, got 1.5",
    ),
    ("[actuator]\n[sensor]\nforce_noise = -1.0\n", "twin.toml: sensor.force_noise: must be ≥ 0"),
    ("[actuator\n", "twin.toml: invalid TOML"),
]


@pytest.mark.parametrize("text,message", BAD)
def test_bad_files_raise_one_clear_error(tmp_path, text, message):
    path = _write(tmp_path, text)
    with pytest.raises(InputError) as info:
        load_model(path)
    expected = str(path) + message.removeprefix("twin.toml")
    assert str(info.value).startswith(expected), str(info.value)
    assert "\n" not in str(info.value)


def test_missing_file_and_dict_source(tmp_path):
    with pytest.raises(InputError, match=r"nope\.toml: cannot read model file"):
        load_model(tmp_path / "nope.toml")
    with pytest.raises(InputError, match=r"^actuator\.effects\[0\]\.kind: unknown effect"):
        load_model({"actuator": {"effects": [{"kind": "foo"}]}})
    with pytest.raises(InputError, match=r"^cfg: actuator\.dealy: unknown key"):
        load_model({"actuator": {"dealy": 0.01}}, name="cfg")


def test_cli_error_is_one_line(tmp_path, capsys):
    # the CLI maps InputError to one line and exit 2; use calibrate's --out check as the path
    from rths_hil.cli import main

    bad = _write(tmp_path, "[actuator]\nbogus = 1\n")
    with pytest.raises(InputError):
        load_plant(bad, DT)
    rc = main(["twin", "calibrate", str(tmp_path / "missing.csv")])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing.csv" in err


def test_every_quantity_takes_a_unit_as_the_configuration_does():
    # the reference values are the unit definitions (1 lbf = 4.4482216152605 N exactly)
    spec = load_model(
        {
            "actuator": {
                "delay": "5 ms",
                "gain": "98%",
                "effects": [
                    {"kind": "backlash", "width": "0.2 mm"},
                    {"kind": "drift", "rate": "3 mm/s"},
                ],
            },
            "specimen": {"stiffness": "1.19 MN/m", "damping": 114.6, "mass": "2 kg"},
            "sensor": {"displacement_noise": "16 um", "force_noise": "0.5 lbf", "seed": 3},
        }
    )
    assert spec.actuator.delay == pytest.approx(5e-3)
    assert spec.actuator.gain == pytest.approx(0.98)
    assert spec.actuator.effects[0].params["width"] == pytest.approx(2e-4)
    assert spec.actuator.effects[1].params["rate"] == pytest.approx(3e-3)
    assert spec.specimen is not None and spec.specimen.stiffness == pytest.approx(1.19e6)
    assert spec.specimen.mass == pytest.approx(2.0)
    assert spec.sensor.displacement_noise == pytest.approx(16e-6)
    assert spec.sensor.force_noise == pytest.approx(0.5 * 4.4482216152605)
    # a force twin reads offset in N: a length is refused naming the key
    with pytest.raises(
        InputError, match=r"^actuator\.effects\[0\]\.offset: cannot read value '2 mm'"
    ):
        load_model(
            {"actuator": {"effects": [{"kind": "offset", "offset": "2 mm"}]}}, control="force"
        )
    assert load_model(
        {"actuator": {"effects": [{"kind": "offset", "offset": "2 kN"}]}}, control="force"
    ).actuator.effects[0].params["offset"] == pytest.approx(2000.0)

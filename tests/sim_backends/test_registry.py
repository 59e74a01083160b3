"""The twins' registries: twin endpoints, actuator models and effects each found in one place;
the diagnosis derives its candidates and the physical chain from the effect classes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.effects import EFFECT_ORDER, EFFECTS, Effect
from rths_hil.sim_backends.endpoints.base import TwinEndpoint
from rths_hil.sim_backends.modelfile import build_plant, load_model, load_plant
from rths_hil.sim_backends.models import BenchmarkServo, FirstOrderServo, Series, make_model
from rths_hil.sim_backends.plant import TwinPlant
from rths_hil.sim_backends.registry import MODELS, TWINS, model_class, twin_class
from rths_hil.sim_backends.twin import default_plant

from rths_hil.diagnose.candidates import _METHODS, CANDIDATES, REFITS, delta_bic
from rths_hil.errors import InputError

DT = 1.0 / 1024.0


def _command(n: int = 4096) -> np.ndarray:
    t = np.arange(n) * DT
    return 0.01 * np.sin(2 * np.pi * 1.3 * t) * np.sin(np.pi * t / t[-1])


def test_every_twin_entry_resolves_to_an_endpoint() -> None:
    assert set(TWINS) == {"can", "modbus", "serial", "canopen"}
    for name in TWINS:
        cls, entry = twin_class(name)
        assert issubclass(cls, TwinEndpoint)
        assert entry.seq_bits in (None, 16)
    with pytest.raises(InputError, match="no twin for driver 'profibus'"):
        twin_class("profibus")


def test_model_entries_build_their_class() -> None:
    assert model_class("delay_gain") is None
    assert model_class("servo_lag") is FirstOrderServo
    assert model_class("benchmark") is BenchmarkServo
    for name, entry in MODELS.items():
        required = {k: 0.01 for k, (default, _) in entry.params.items() if default is None}
        m = make_model(name, DT, delay=0.003, gain=0.97, **required)
        y = m.simulate(_command())
        assert np.all(np.isfinite(y)) and np.max(np.abs(y)) > 0


def test_old_model_name_reads_as_servo_lag() -> None:
    old = make_model("first_order", DT, delay=0.004, time_constant=0.01)
    new = make_model("servo_lag", DT, delay=0.004, time_constant=0.01)
    assert isinstance(old, Series)
    u = _command()
    np.testing.assert_array_equal(old.simulate(u), new.simulate(u))
    spec = load_model({"actuator": {"model": "first_order", "time_constant": 0.01}})
    assert spec.actuator.model == "servo_lag"
    with pytest.raises(InputError, match=r"actuator\.model: unknown actuator model 'second_order'"):
        load_model({"actuator": {"model": "second_order"}})


def test_build_plant_from_a_twin_section_equals_the_model_file_path(tmp_path) -> None:
    section = {
        "model": "",
        "actuator": {
            "model": "servo_lag",
            "time_constant": 0.02,
            "delay": 0.005,
            "effects": [{"kind": "backlash", "width": 2e-4}],
        },
        "specimen": {"stiffness": 2e6, "damping": 50.0},
        "sensor": {"displacement_noise": 1e-6, "seed": 3},
    }
    plant = build_plant(section, DT)
    assert isinstance(plant, TwinPlant)
    ref = load_plant({k: section[k] for k in ("actuator", "specimen", "sensor")}, DT)
    u = _command()
    for a, b in zip(plant.simulate(u), ref.simulate(u), strict=True):
        np.testing.assert_array_equal(a, b)
    path = tmp_path / "twin.toml"
    path.write_text(
        '[actuator]\nmodel = "servo_lag"\ntime_constant = 0.02\ndelay = 0.005\n'
        '[[actuator.effects]]\nkind = "backlash"\nwidth = 2e-4\n'
        "[specimen]\nstiffness = 2e6\ndamping = 50.0\n"
        "[sensor]\ndisplacement_noise = 1e-6\nseed = 3\n"
    )
    from_file = build_plant({"model": "twin.toml", "actuator": {}}, DT, base_dir=str(tmp_path))
    for a, b in zip(from_file.simulate(u), ref.simulate(u), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError, match="kind: unknown effect 'friction'"):
        build_plant({"actuator": {"effects": [{"kind": "friction"}]}}, DT)


def test_default_plant_is_the_spring_on_a_delay() -> None:
    k, delay, gain = 3.0e5, 0.0042, 1.05
    plant = default_plant(delay, gain, k, DT)
    n0 = round(delay / DT)
    u = np.zeros(64)
    u[0] = 1e-3
    disp, force = zip(*(plant.step(c) for c in u), strict=True)
    disp = np.array(disp)
    # the step arrives after the fractional delay, scaled by the gain (Lagrange taps sum to 1)
    assert np.all(disp[: n0 - 1] == 0)
    assert disp.sum() == pytest.approx(gain * 1e-3, rel=1e-12)
    np.testing.assert_allclose(force, k * disp, rtol=0, atol=1e-12)


def test_effect_classes_carry_what_the_diagnosis_needs() -> None:
    assert CANDIDATES[: len(REFITS)] == REFITS
    assert sorted(CANDIDATES[len(REFITS) :]) == sorted(EFFECTS)
    assert len({cls.PREFERENCE for cls in EFFECTS.values()}) == len(EFFECTS)
    assert len({cls.CHAIN for cls in EFFECTS.values()}) == len(EFFECTS)
    assert sorted(EFFECT_ORDER.values()) == list(range(len(EFFECTS)))
    for kind, cls in EFFECTS.items():
        assert issubclass(cls, Effect)
        assert cls.FIT.method in _METHODS, kind
        names = {p.name for p in cls.PARAMS}
        if cls.FIT.method in ("linear", "scalar"):
            assert cls.FIT.param in names, kind
        assert any(p.polish for p in cls.PARAMS), kind


def test_delta_bic_is_the_schwarz_difference() -> None:
    n, rss0, rss1, k = 1000, 2.0, 1.0, 3
    bic0 = n * math.log(rss0 / n)
    bic1 = n * math.log(rss1 / n) + k * math.log(n)
    assert delta_bic(n, rss0, rss1, k) == pytest.approx(bic0 - bic1, rel=1e-12)
    assert delta_bic(n, rss0, 0.0, k) == math.inf

"""Every key that names a position or a motion is held against the limits before anything moves,
and ``start.mode = "offset"`` watches the actuator's absolute stroke as well as the test's
relative displacement.

References are closed form: the band a relative displacement may take about a start position
``o`` inside a limit ``L`` is ``[max(−L, −L − o), min(L, L − o)]``.
"""

from __future__ import annotations

import numpy as np
import pytest

from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.safety import SafetyMonitor
from tests.helpers.cli import one_line_exit_2
from tests.helpers.loop import run_loop

MM = 1e-3
QUICK = ["loop.duration=0.05", "loop.console=0", "output.plot=false"]


# ----------------------------------------------------------------------------------------------
# refused at load, before anything moves


@pytest.mark.parametrize(
    ("over", "key", "shown"),
    [
        (["end.rest=position", "end.rest_position=1"], "end.rest_position", "+1000 mm"),
        (["end.rest=position", "end.rest_position=0.06"], "end.rest_position", "+60 mm"),
        (["end.rest=position", 'end.rest_position="-50mm"'], "end.rest_position", "-50 mm"),
    ],
)
def test_a_position_on_or_past_the_limit_is_refused_at_load(over, key, shown):
    with pytest.raises(InputError) as err:
        load_config(None, over)
    msg = str(err.value)
    assert f"{key}: {shown} is not inside the displacement limit ±50 mm" in msg
    assert "\n" not in msg


def test_a_channels_own_limit_is_the_one_that_counts(tmp_path):
    cfg = tmp_path / "two.toml"
    cfg.write_text(
        '[end]\nrest = "position"\nrest_position = "20mm"\n'
        '[[actuators]]\nname = "a"\n'
        '[[actuators]]\nname = "b"\nsafety = { displacement_limit = "10mm" }\n'
    )
    with pytest.raises(InputError, match=r"actuators\[1\] \(b\): end.rest_position: \+20 mm"):
        load_config(cfg, [])
    # the same rest inside both limits loads
    cfg.write_text(cfg.read_text().replace('"10mm"', '"30mm"'))
    load_config(cfg, [])


def test_inside_the_limit_or_with_the_limit_off_loads():
    load_config(None, ["end.rest=position", 'end.rest_position="-49.9mm"'])
    load_config(None, ["end.rest=position", "end.rest_position=1", "safety.displacement_limit=0"])
    load_config(None, ["end.rest_position=1"])  # end.rest = hold: the key is not used


def test_the_cli_refusal_is_one_line_exit_2(tmp_path, capsys):
    one_line_exit_2(
        ["run", "--lockstep", "--set", "end.rest=position", "--set", "end.rest_position=0.06",
         "--set", f"output.dir={tmp_path / 'r'}"],
        capsys,
        "end.rest_position: +60 mm is not inside the displacement limit",
    )  # fmt: skip
    assert not (tmp_path / "r").exists()  # refused before a run directory or a motion


# ----------------------------------------------------------------------------------------------
# offset mode: the absolute stroke


@pytest.mark.parametrize("offset", [0.0, 45 * MM, -45 * MM, 20 * MM])
def test_offset_band_is_the_closed_form(offset):
    lim = 50 * MM
    mon = SafetyMonitor(1e-3, displacement_limit=lim)
    mon.set_offset(offset)
    lo, hi = max(-lim, -lim - offset), min(lim, lim - offset)
    for rel in np.linspace(-0.12, 0.12, 481):
        m = SafetyMonitor(1e-3, displacement_limit=lim)
        m.set_offset(offset)
        trip = m.check_feedback(0.0, 0, True, 0, 0, 0, rel, rel, 0.0)
        assert (trip is None) == (lo <= rel <= hi), rel
        if trip is not None:
            assert trip.rule == "displacement"
            absolute_only = -lim <= rel <= lim
            assert ("absolute" in trip.reason) == absolute_only, trip.reason


def test_offset_start_near_the_limit_trips_on_the_absolute_stroke(tmp_path):
    """A start at 45 mm with a 50 mm limit: the test may add at most 5 mm. The record of the
    same test started at 0 shows it goes past 5 mm, so started at 45 mm it must trip there, on
    the absolute position, and never be commanded past the limit."""
    over = ["loop.duration=4", "ground_motion.pga=1.0", "fei.enabled=false",
            "kalman.enabled=false", "safety.velocity_limit=0", "safety.force_limit=0"]  # fmt: skip
    ref = run_loop(tmp_path / "ref", None, *over, mode="lockstep")
    assert ref.result.status == "completed"
    peak = float(np.max(ref.run.record["command"]))
    assert 5 * MM < peak < 45 * MM  # the reference leaves the 5 mm of stroke left at 45 mm
    r = run_loop(
        tmp_path / "off", None, *over, 'twin.initial_position="45mm"', "start.mode=offset",
        mode="lockstep",
    )  # fmt: skip
    assert r.result.status == "trip"
    (trip,) = [e for e in r.run.events if e["kind"] == "trip"]
    assert trip["rule"] == "displacement" and "absolute" in trip["reason"]
    absolute = r.run.record["command"] + 45 * MM
    assert np.max(absolute) <= 50 * MM  # never commanded past the stroke limit


# ----------------------------------------------------------------------------------------------
# the documented "0 = off" of the rules' tolerances


@pytest.mark.parametrize("key", ["fei_delay_tol", "fei_amplitude_tol", "kf_delay_max"])
@pytest.mark.parametrize("value", ["0", '"0"', '"0 ms"'])
def test_zero_switches_a_tolerance_off(tmp_path, key, value):
    if key == "fei_amplitude_tol" and "ms" in value:
        value = "0.0"  # a ratio has no unit
    r = run_loop(tmp_path / "r", None, *QUICK, f"safety.{key}={value}", mode="lockstep")
    assert r.result.status == "completed"
    rules = r.loop.runner.channels[0].monitor
    if key.startswith("fei"):
        tol = rules.fei.delay_tol if key == "fei_delay_tol" else rules.fei.amplitude_tol
    else:
        tol = rules.kalman.delay_max
    assert tol == float("inf")


def test_a_tolerance_off_never_trips_on_its_own_part():
    from rths_hil.safety import FEIRule, KalmanRule

    rule = FEIRule(0.0, 0.005, consecutive=1)  # amplitude part off
    assert rule.check(5.0, 0.001, True) is None  # A far off, d inside: no trip
    assert rule.check(1.0, 0.010, True) is not None  # d outside: trips
    k = KalmanRule(0.5, 1.5, 0.0)
    assert k.check(1.0, 10.0) is None and k.check(2.0, 0.0) is not None
    with pytest.raises(InputError, match="FEI delay tolerance must be a finite number > 0"):
        FEIRule(0.1, -1.0)

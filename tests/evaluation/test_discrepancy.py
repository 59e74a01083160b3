"""Discrepancy workflow on records with hidden effects: names them, halves the gap, or says none.

Each record is an SDOF response to a bundled ground motion driving a twin (delay + gain actuator,
Kelvin-Voigt specimen, sensor noise 5-20 µm rms, 1 µm quantisation) with hidden effects of random
size drawn from EFFECT_RANGES (:func:`rths_hil.diagnose.synthetic.make_case`, seeded); the
workflow gets only the record (time, command, measured, force) and the base model. Scores are
against the hidden truth: the named effects, their parameters, and J2 against the *noiseless*
achieved displacement (the gap the model can close; the measured J2 also contains the noise).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.effects import EFFECT_RANGES, EFFECTS

from rths_hil.diagnose import diagnose
from rths_hil.diagnose.synthetic import make_case
from rths_hil.errors import InputError
from rths_hil.metrics import j2_nrms

#: Record length (s): the strong motion of each ground motion and at least 5 cycles of the
#: slowest drawn structure (the diagnosis refuses shorter records: 10.6 s for one of these
#: seeds). On 14 s records every fitted size is as close to the hidden one as on 20 s records
#: (within 2 %, against the 5 % asserted) and the noise estimate within 3 % (15 % asserted).
DURATION = 14.0

#: The parameter that sizes each effect, checked against the hidden value.
MAIN = {
    "offset": "offset",
    "drift": "rate",
    "backlash": "width",
    "velocity_limit": "limit",
    "stroke_limit": "limit",
    "servo_lag": "time_constant",
    "time_varying_delay": "amplitude",
    "force_feedback": "actuator_stiffness",
}


def _run(kinds, seed, with_model=True, **kw):
    case = make_case(kinds, seed, duration=DURATION)
    dx = diagnose(
        case.time,
        case.command,
        case.measured,
        case.force,
        model=case.base if with_model else None,
        **kw,
    )
    return case, dx


def _truth_gaps(case, dx):
    return j2_nrms(case.truth, dx.base_pred), j2_nrms(case.truth, dx.pred)


@pytest.mark.parametrize(
    "seed, kind", [(7100 + 10 * j + i, k) for j in range(2) for i, k in enumerate(EFFECTS)]
)
def test_one_hidden_effect_is_named_and_the_gap_halves(seed, kind):
    case, dx = _run([kind], seed)
    hidden = case.hidden[0].params
    # the drawn size is realistic (from the ranges), not chosen to be easy
    r = EFFECT_RANGES[kind][MAIN[kind]]
    if kind not in ("stroke_limit", "velocity_limit"):  # these are scaled to be reached
        assert r.low * 0.999 <= abs(hidden[MAIN[kind]]) <= r.high * 1.001
    assert dx.names == [kind], (dx.names, hidden, case.info)
    step = dx.steps[0]
    # the fitted size is the hidden one
    assert step.params[MAIN[kind]] == pytest.approx(hidden[MAIN[kind]], rel=0.05)
    truth_before, truth_after = _truth_gaps(case, dx)
    assert truth_after <= 0.5 * truth_before
    # the measured gap shrinks; it halves unless the noise dominates what the effect adds
    assert dx.after.j2 < dx.before.j2
    if case.info["effect_rms"][kind] > 2 * case.info["noise"]:
        assert dx.after.j2 <= 0.5 * dx.before.j2
    # the report's step gaps chain from the base to the final model
    assert step.before.j2 == pytest.approx(dx.before.j2)
    assert step.after.j2 == pytest.approx(dx.after.j2)
    assert step.delta_bic > dx.threshold
    # what is left is noise: the estimated noise level is the twin's
    assert dx.final.noise == pytest.approx(case.info["noise"], rel=0.15)
    # the effect acts somewhere and the report says where
    assert step.where["acts"]["fraction"] > 0
    assert step.where["when"]["intervals_s"]


@pytest.mark.parametrize("seed", [7200, 7201])
def test_no_hidden_effect_gives_none(seed):
    case, dx = _run([], seed)
    assert dx.names == []
    assert dx.answer == "none"
    assert dx.steps == []
    assert dx.stop["reason"] == "no significant candidate"
    assert dx.stop["delta_bic"] <= dx.threshold
    assert dx.after.j2 == dx.before.j2
    # the base model is exact: the gap is the noise, J2 = σ / rms(measured)
    noise_j2 = 100 * case.info["noise"] / np.sqrt(np.mean(case.measured**2))
    assert dx.before.j2 == pytest.approx(noise_j2, rel=0.05)
    assert dx.report()["effects"] == []


def test_no_hidden_effect_without_model_gives_none():
    case, dx = _run([], 7202, with_model=False)
    assert dx.names == []
    assert dx.base_source.startswith("fitted")
    assert dx.base.actuator.delay == pytest.approx(case.info["delay"], abs=2e-4)
    assert dx.base.actuator.gain == pytest.approx(case.info["gain"], rel=2e-3)


@pytest.mark.parametrize(
    "kinds, seed",
    [
        (("offset", "backlash"), 7300),  # transducer zero and play in the clevis
        (("servo_lag", "velocity_limit"), 7301),  # a slow position loop saturating the valve
    ],
)
def test_two_hidden_effects_are_both_named(kinds, seed):
    case, dx = _run(list(kinds), seed)
    assert sorted(dx.names) == sorted(kinds), (dx.names, [e.params for e in case.hidden])
    truth_before, truth_after = _truth_gaps(case, dx)
    assert truth_after <= 0.5 * truth_before
    assert dx.after.j2 <= 0.5 * dx.before.j2
    fitted = {s.name: s.params for s in dx.steps}
    for e in case.hidden:
        assert fitted[e.kind][MAIN[e.kind]] == pytest.approx(e.params[MAIN[e.kind]], rel=0.05)
    # consecutive steps chain: each starts where the previous ended
    assert dx.steps[1].before.j2 == pytest.approx(dx.steps[0].after.j2)


def test_hidden_effect_without_model_file():
    """No model file: delay and gain fitted to the record, re-fitted with the named effect."""
    case, dx = _run(["backlash"], 7400, with_model=False)
    assert dx.names == ["backlash"]
    assert dx.steps[0].params["width"] == pytest.approx(case.hidden[0].params["width"], rel=0.05)
    assert dx.model.actuator.delay == pytest.approx(case.info["delay"], abs=2e-4)
    truth_before, truth_after = _truth_gaps(case, dx)
    assert truth_after <= 0.5 * truth_before


def test_max_effects_and_threshold_are_honoured():
    case = make_case(["offset", "backlash"], 7300, duration=DURATION)
    dx = diagnose(
        case.time, case.command, case.measured, case.force, model=case.base, max_effects=1
    )
    assert len(dx.steps) == 1
    assert dx.stop["reason"].startswith("max_effects")
    # an absurd threshold leaves everything unnamed
    dx = diagnose(
        case.time, case.command, case.measured, case.force, model=case.base, threshold=1e12
    )
    assert dx.names == []


def test_augmented_model_reproduces_the_prediction_and_reported_gaps():
    case, dx = _run(["drift"], 7500)
    # the augmented spec, built by the twin itself, gives the same prediction
    plant = dx.model.build(1.0 / case.fs)
    again = plant.effects.simulate(plant.actuator.simulate(case.command))
    np.testing.assert_allclose(again, dx.pred, rtol=0, atol=1e-12)
    rep = dx.report("x.toml")
    assert rep["gap_before"] == pytest.approx(j2_nrms(case.measured, dx.base_pred))
    assert rep["gap_after"] == pytest.approx(j2_nrms(case.measured, dx.pred))
    eff = rep["effects"][0]
    assert set(eff) >= {"name", "parameters", "where", "gap_before", "gap_after"}
    assert eff["where"]["regime"]["dominant"] == "time"  # a drift is a trend in time
    assert math.isfinite(rep["fei_after"]["amplitude"])


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda t, u, y: (t, u, y[:-1]), "different lengths"),
        (lambda t, u, y: (t, u, np.where(np.arange(len(y)) == 100, np.nan, y)), "non-finite"),
        (lambda t, u, y: (t[:2048], u[:2048], y[:2048]), "too short to decide"),
        (lambda t, u, y: (t, np.zeros_like(u), y), "constant"),
        (lambda t, u, y: (t[:100], u[:100], y[:100]), "too short to decide"),
    ],
)
def test_bad_records_raise_one_clear_error(mutate, match):
    case = make_case([], 7600, duration=DURATION)
    t, u, y = mutate(case.time, case.command, case.measured)
    with pytest.raises(InputError, match=match):
        diagnose(t, u, y, model=case.base)


def test_bad_options_raise():
    case = make_case([], 7600, duration=DURATION)
    args = (case.time, case.command, case.measured)
    with pytest.raises(InputError, match="max_effects"):
        diagnose(*args, model=case.base, max_effects=-1)
    with pytest.raises(InputError, match="threshold"):
        diagnose(*args, model=case.base, threshold=float("nan"))
    with pytest.raises(InputError, match="unknown candidate"):
        diagnose(*args, model=case.base, candidates=("delay", "friction"))

"""Tuning of the inverse compensation: closed forms, the iteration, trials through the
loop on twins of known delay and gain, the sweep's zero crossing, and the ``tune`` CLI
(including the hardware path's refusal without confirmation)."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from rths_hil.cli import main as cli
from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.hybrid import build_ground_motion
from rths_hil.records.recorder import read_run
from rths_hil.tuning import (
    LoopTrials,
    Trial,
    balanced_alpha,
    compensator_response,
    residual_delay,
    sweep,
    tune,
    zero_crossing,
)

FS = 1024.0
DT = 1.0 / FS
# Fast settings for trials through the loop: serial transport (the fastest twin), 6 s trials
# of the bundled El Centro record on the default NEES-711 structure.
LOOP = ["driver.name=serial", "loop.console=0", "output.plot=false"]


# ----------------------------------------------------------------------------------------------
# closed forms


def test_compensator_response_is_the_fir_evaluated_on_the_unit_circle():
    alpha, f = 23.5, 1.3
    z = np.exp(1j * 2 * np.pi * f * DT)
    assert compensator_response(alpha, f, DT) == pytest.approx(alpha - (alpha - 1) / z)
    # a sampled sine through the FIR has that gain and phase
    n = np.arange(4096)
    x = np.sin(2 * np.pi * f * n * DT)
    y = alpha * x[1:] - (alpha - 1) * x[:-1]
    c = compensator_response(alpha, f, DT)
    ref = abs(c) * np.sin(2 * np.pi * f * n[1:] * DT + np.angle(c))
    np.testing.assert_allclose(y, ref, atol=1e-9)


@pytest.mark.parametrize("tau", [0.005, 0.020, 0.040])
@pytest.mark.parametrize("f", [0.3, 0.8, 2.0])
def test_balanced_alpha_solves_phase_balance_like_a_root_finder(tau, f):
    lag = 2 * np.pi * f * tau
    a0 = balanced_alpha(lag, f, DT)
    ref = brentq(lambda a: np.angle(compensator_response(a, f, DT)) - lag, 1.0, 500.0, xtol=1e-12)
    assert a0 == pytest.approx(ref, abs=1e-8)
    assert residual_delay(a0, f, DT, lag) == pytest.approx(0.0, abs=1e-12)
    # the FIR's lead grows like atan: balancing a pure delay needs slightly more than 1 + τ/Δt
    assert a0 > 1 + tau / DT
    assert a0 == pytest.approx(1 + math.tan(lag) / (2 * np.pi * f) / DT, rel=5e-3)


def test_balanced_alpha_rejects_a_lag_no_alpha_can_balance():
    with pytest.raises(InputError):
        balanced_alpha(math.pi / 2 + 0.1, 1.0, DT)


def test_zero_crossing_interpolates_linearly_and_skips_bad_points():
    a = [10, 15, 20, 25, 30]
    d = [0.012, 0.007, 0.002, -0.003, -0.008]  # d = 0.022 − α·1e-3: zero at 22
    assert zero_crossing(a, d) == pytest.approx(22.0)
    # nonlinear d: the crossing is the chord's zero between the bracketing points
    d2 = [0.02, 0.01, 0.004, -0.001, -0.01]
    assert zero_crossing(a, d2) == pytest.approx(20 + 5 * 0.004 / 0.005)
    # unsorted input, NaN points skipped, an exact zero returned as is
    assert zero_crossing([30, 10, 20, 25], [-0.008, 0.012, math.nan, -0.003]) == pytest.approx(
        10 + 15 * 0.012 / 0.015
    )
    assert zero_crossing([10, 20, 30], [0.01, 0.0, -0.01]) == 20.0
    assert zero_crossing([10, 20], [0.01, 0.005]) is None
    assert zero_crossing([10, 20], [-0.01, -0.02]) is None


# ----------------------------------------------------------------------------------------------
# the iteration against closed-form "trials"


class ModelTrials:
    """Trials in closed form: the compensator times an actuator of phase lag and gain at f.

    ``noise`` adds a random equivalent delay (s, uniform ±noise) to every trial.
    """

    def __init__(self, tau=0.025, gain=1.0, f=0.8, noise=0.0, valid=True, status="completed"):
        self.tau, self.gain, self.f = tau, gain, f
        self.noise = noise
        self.rng = np.random.default_rng(1)
        self.valid, self.status = valid, status
        self.calls = []

    def __call__(self, alpha, factor, index):
        self.calls.append((alpha, factor))
        w = 2 * np.pi * self.f
        h = (
            factor
            * compensator_response(alpha, self.f, DT)
            * self.gain
            * np.exp(-1j * w * self.tau)
        )
        d = -np.angle(h) / w + self.noise * self.rng.uniform(-1, 1)
        return Trial(index, alpha, factor, abs(h), d, self.f, self.valid, status=self.status)


@pytest.mark.parametrize("tau", [0.010, 0.025, 0.040])
@pytest.mark.parametrize("gain", [0.95, 1.05])
def test_tune_converges_to_the_balanced_alpha_and_the_inverse_gain(tau, gain):
    m = ModelTrials(tau, gain)
    res = tune(m, alpha0=5.0, dt=DT, tol_delay=1e-3, tol_amplitude=0.01)
    assert res.converged, res.reason
    assert res.iterations <= 3
    last = res.trials[-1]
    assert abs(last.delay) <= 1e-3 and abs(last.amplitude - 1) <= 0.01
    a0 = balanced_alpha(2 * np.pi * 0.8 * tau, 0.8, DT)
    assert res.alpha == pytest.approx(a0, abs=1e-3 * FS)
    # the factor undoes the gain and the compensator's own amplification there
    ref = 1 / (gain * abs(compensator_response(res.alpha, 0.8, DT)))
    assert res.factor == pytest.approx(ref, abs=0.011)
    # each trial applied α ← α + d/Δt to the previous one
    for prev, nxt in zip(res.trials, res.trials[1:], strict=False):
        assert nxt.alpha == pytest.approx(prev.alpha + prev.delay / DT)


def test_tune_alpha_only_stops_when_alpha_cannot_fix_the_amplitude():
    m = ModelTrials(0.02, gain=0.9)
    res = tune(m, alpha0=5.0, dt=DT, tune_amplitude=False)
    assert res.stop == "amplitude" and not res.converged
    assert "amplitude factor is not tuned" in res.reason
    assert all(f == 1.0 for _, f in m.calls)
    assert abs(res.trials[-1].delay) <= 1e-3


def test_tune_stops_when_noise_keeps_it_from_improving_and_keeps_the_best_trial():
    m = ModelTrials(0.02, 1.0, noise=0.004)  # ±4 ms of trial-to-trial scatter vs a 1 ms goal
    res = tune(m, alpha0=5.0, dt=DT, max_iterations=12)
    assert res.stop in ("stalled", "diverging"), res.reason
    assert "error" in res.reason and "tolerance" in res.reason
    errs = [t.error(1e-3, 0.01) for t in res.trials]
    # the recommendation is the verified trial with the smallest error, not the last update
    assert res.best == int(np.argmin(errs)) + 1
    assert res.alpha == res.trials[res.best - 1].alpha
    assert errs[-1] > 0.8 * min(errs[:-1])


def test_tune_stop_reasons_bound_invalid_trip_and_budget():
    res = tune(ModelTrials(0.2), alpha0=50.0, dt=DT, alpha_bounds=(1.0, 100.0))
    assert res.stop == "bound" and "outside [1, 100]" in res.reason
    assert res.trials[-1].alpha == 100.0
    res = tune(ModelTrials(valid=False), alpha0=5.0, dt=DT)
    assert res.stop == "invalid" and res.best == 0 and res.alpha == 5.0
    res = tune(ModelTrials(status="trip"), alpha0=5.0, dt=DT)
    assert res.stop == "trip" and res.iterations == 1
    res = tune(ModelTrials(0.03), alpha0=2.0, dt=DT, max_iterations=1)
    assert res.stop == "max_iterations" and "not converged after 1" in res.reason
    assert res.next_alpha == pytest.approx(2.0 + res.trials[0].delay / DT)
    with pytest.raises(InputError):
        tune(ModelTrials(), alpha0=0.5, dt=DT)
    with pytest.raises(InputError):
        tune(ModelTrials(), alpha0=5.0, dt=DT, max_iterations=0)


# ----------------------------------------------------------------------------------------------
# trials through the real-time loop on twins of known delay and gain


def _actuator(model, delay, gain, time_constant=None):
    tc = f", time_constant={time_constant}" if time_constant else ""
    return f"twin.actuator={{model='{model}', delay={delay}, gain={gain}{tc}}}"


def _plant_lag(f, delay, time_constant=None):
    """Phase lag (rad) of the twin's actuator at f: transport delay plus first-order lag."""
    w = 2 * np.pi * f
    return w * delay + (math.atan(w * time_constant) if time_constant else 0.0)


@pytest.mark.parametrize(
    ("model", "delay", "gain", "tc"),
    [
        ("delay_gain", 0.010, 0.95, None),
        ("delay_gain", 0.040, 1.05, None),
        ("servo_lag", 0.005, 0.98, 0.020),
    ],
)
def test_tuning_through_the_loop_converges_on_twins(tmp_path, model, delay, gain, tc):
    cfg = load_config(None, [*LOOP, _actuator(model, delay, gain, tc), "compensation.alpha=5"])
    runner = LoopTrials(cfg, tmp_path, duration=6.0)
    assert runner.mode == "lockstep" and not runner.hardware
    res = tune(runner, alpha0=5.0, dt=DT, max_iterations=4)
    assert res.converged, res.reason
    assert res.iterations <= 3
    last = res.trials[-1]
    assert abs(last.delay) <= 1e-3 and abs(last.amplitude - 1) <= 0.01
    # against the closed form at the trial's equivalent frequency
    a0 = balanced_alpha(_plant_lag(last.f_eq, delay, tc), last.f_eq, DT)
    assert res.alpha == pytest.approx(a0, abs=1.0)
    mag = 1 / math.hypot(1, 2 * np.pi * last.f_eq * tc) if tc else 1.0
    ref = 1 / (gain * mag * abs(compensator_response(res.alpha, last.f_eq, DT)))
    assert res.factor == pytest.approx(ref, abs=0.012)
    # every trial is a real run directory with the trial's α in its record
    run = read_run(last.run_dir)
    assert np.all(run.record["alpha"] == last.alpha)
    assert run.meta["config"]["compensation"]["amplitude"] == last.factor
    assert run.record.size == 6 * 1024


def test_sweep_zero_crossing_matches_the_twin_delay(tmp_path):
    tau = 0.020
    out = tmp_path / "sweep"
    code = cli(
        [
            "tune",
            *[f"--set={s}" for s in LOOP],
            f"--set={_actuator('delay_gain', tau, 1.0)}",
            "--sweep",
            "12:32:5",
            "--trial-duration",
            "6s",
            "--out",
            str(out),
            "-q",
        ]
    )
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())["sweep"]
    trials = summary["trials"]
    assert [t["alpha"] for t in trials] == [12, 17, 22, 27]
    f_eq = float(np.mean([t["f_eq"] for t in trials]))
    # each grid point against the closed form d(α) of compensator + pure delay at f_eq
    for t in trials:
        ref = residual_delay(t["alpha"], t["f_eq"], DT, 2 * np.pi * t["f_eq"] * tau)
        assert t["delay"] == pytest.approx(ref, abs=3e-4), t
    # the zero crossing is the twin's delay in steps: 1 + τ/Δt (+ the FIR's atan correction)
    assert summary["alpha"] == pytest.approx(
        balanced_alpha(2 * np.pi * f_eq * tau, f_eq, DT), abs=0.3
    )
    assert summary["alpha"] == pytest.approx(1 + tau / DT, abs=0.5)
    # the tuned config is loadable and carries the recommendation
    tuned = load_config(out / "tuned.toml")
    assert tuned["compensation"]["alpha"] == pytest.approx(summary["alpha"])
    assert tuned["compensation"]["amplitude"] == pytest.approx(summary["factor"])
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len((out / "sweep.csv").read_text().splitlines()) == 1 + 4
    # the CSV names its units: delay and J1 in s, f_eq in Hz, J2 in %
    import csv

    with (out / "sweep.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {"delay_s", "j1_s", "f_eq_Hz", "j2_percent", "pga_m_per_s2"} <= set(rows[0])
    for r, t in zip(rows, trials, strict=True):
        assert float(r["delay_s"]) == t["delay"] and float(r["j2_percent"]) == t["j2"]


def test_cli_tune_prints_the_table_and_writes_the_tuned_config(tmp_path, capsys):
    out = tmp_path / "tune"
    code = cli(
        [
            "tune",
            *[f"--set={s}" for s in LOOP],
            f"--set={_actuator('delay_gain', 0.015, 1.0)}",
            "--set=compensation.alpha=3",
            "--trial-duration=4s",
            "--tolerance-delay=2ms",
            "--tolerance-amplitude=2%",
            "--max-iterations=3",
            "--out",
            str(out),
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    lines = captured.out.splitlines()
    assert lines[0].split()[:7] == ["#", "alpha", "factor", "A", "d", "(ms)", "J1"]
    rows = [ln for ln in lines if ln.strip()[:1].isdigit()]
    assert len(rows) >= 2 and rows[0].split()[1] == "3.000"
    assert "tuned: α =" in captured.out and "converged at trial" in captured.err
    summary = json.loads((out / "summary.json").read_text())["tuning"]
    assert summary["converged"] and summary["stop"] == "converged"
    assert len(rows) == len(summary["trials"])
    tuned = tomllib.loads((out / "tuned.toml").read_text())
    assert tuned["compensation"]["alpha"] == pytest.approx(summary["alpha"])
    assert tuned["ground_motion"]["record"] == "default"
    assert (out / "tuning.png").stat().st_size > 10_000
    assert (out / "trial-01" / "record.npy").exists()


# ----------------------------------------------------------------------------------------------
# the hardware path


def _hardware_overrides(connection: dict) -> list[str]:
    conn = ", ".join(
        f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v}" for k, v in connection.items()
    )
    return [
        "twin.enabled=false",
        "driver.name=can",
        f"driver.connection={{{conn}}}",
        "loop.console=0",
    ]


def test_hardware_tuning_refuses_without_confirmation(tmp_path, capsys):
    out = tmp_path / "hw"
    over = _hardware_overrides({"interface": "virtual", "channel": "nobody-listens"})
    code = cli(["tune", *[f"--set={s}" for s in over], "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "--confirm-hardware" in err[0] and "twin.enabled = false" in err[0]
    assert not out.exists()  # nothing was run, nothing written


def test_hardware_tuning_prompt_answered_no_runs_nothing(tmp_path, capsys, monkeypatch):
    class TTY:
        def isatty(self):
            return True

    monkeypatch.setattr("sys.stdin", TTY())
    monkeypatch.setattr("builtins.input", lambda prompt="": "no")
    out = tmp_path / "hw"
    over = _hardware_overrides({"interface": "virtual", "channel": "nobody-listens"})
    code = cli(["tune", *[f"--set={s}" for s in over], "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "REAL actuator" in err and "not confirmed" in err
    assert not out.exists()


@pytest.mark.timing  # paced
def test_hardware_tuning_with_confirmation_runs_paced_at_reduced_amplitude(tmp_path, capsys):
    from rths_hil.sim_backends.twin import default_plant, start_twin

    out = tmp_path / "hw"
    with start_twin("can", default_plant(delay=0.02), interface="virtual") as twin:
        over = _hardware_overrides(twin.connection)
        code = cli(
            [
                "tune",
                *[f"--set={s}" for s in over],
                "--confirm-hardware",
                "--hardware-scale=20%",
                "--max-iterations=1",
                "--trial-duration=1s",
                "--out",
                str(out),
            ]
        )
    captured = capsys.readouterr()
    assert code in (0, 1), captured.err
    assert "confirmed" in captured.err and "20 %" in captured.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["hardware"] and summary["mode"] == "paced"
    assert summary["pga"] == pytest.approx(0.2 * 0.322)
    run = read_run(out / "trial-01")
    assert run.meta["mode"] == "paced"
    full = build_ground_motion(load_config(None))
    n = run.record.size
    assert n == 1024
    np.testing.assert_allclose(
        run.record["ground_accel"], 0.2 * np.asarray(full.accel[:n]), rtol=1e-9, atol=1e-12
    )
    # on hardware the online evaluators and their safety rules stay on
    assert run.meta["config"]["fei"]["enabled"] and run.meta["config"]["kalman"]["enabled"]
    assert np.isfinite(run.record["kf_gain"]).any()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--sweep", "a:b:c"], "--sweep"),
        (["--sweep", "0:3:1"], "α must be ≥ 1"),
        (["--tolerance-delay", "0ms"], "--tolerance-delay"),
        (["--tolerance-amplitude=-1%"], "--tolerance-amplitude"),
        (["--max-iterations", "0"], "--max-iterations"),
        (["--trial-duration=-2s"], "--trial-duration"),
        (["--set", "compensation.alpha=0.5"], "compensation.alpha"),
    ],
)
def test_cli_tune_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, needle):
    code = cli(["tune", *args, "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "x").exists()


def test_cli_tune_hardware_scale_out_of_range_is_rejected(tmp_path, capsys):
    over = _hardware_overrides({"interface": "virtual", "channel": "x"})
    code = cli(
        [
            "tune",
            *[f"--set={s}" for s in over],
            "--hardware-scale=150%",
            "--confirm-hardware",
            "--out",
            str(tmp_path / "x"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--hardware-scale" in err[0]


def test_loop_trials_validate_their_settings():
    cfg = load_config(None)
    with pytest.raises(InputError):
        LoopTrials(cfg, Path("x"), duration=-1.0)
    with pytest.raises(InputError):
        LoopTrials(cfg, Path("x"), scale=0.0)
    with pytest.raises(InputError):
        sweep(lambda a, f, i: None, [])

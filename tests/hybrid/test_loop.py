"""The real-time loop end to end in lockstep, over each driver and its twin."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rths_hil.sim_backends.modelfile import load_plant

from rths_hil import groundmotion
from rths_hil.compensators.inverse import InverseCompensator
from rths_hil.config import load_config
from rths_hil.fei import fei
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import read_run
from rths_hil.structures.sdof import BoucWenParams, CRStepper

FS = 1024.0
DELAY = 0.020  # the twin's pure transport delay (the FEI paper's Fig. 4.1 block model)
DRIVERS = ["can", "modbus", "serial"]
LSB = {
    "can": (1e-7, 0.5),  # DBC: feedback force 0.5 N per count
    "modbus": (1e-7, 1e-2),
    "serial": (None, None),
}


def run_lockstep(tmp_path, *overrides, plant=None, name="run"):
    cfg = load_config(
        None,
        [
            "loop.mode=lockstep",
            "loop.console=0",
            "output.plot=false",
            "twin.sensor={}",
            *overrides,
        ],
    )
    loop = RTHSLoop(cfg, tmp_path / name, plant=plant)
    result = loop.run()
    return loop, result, read_run(tmp_path / name)


def _twin(delay=DELAY):
    return f"twin.actuator={{model='delay_gain', delay={delay}, gain=1.0}}"


@pytest.mark.parametrize("driver", DRIVERS)
def test_ideal_compensation_cancels_the_twin_delay_and_none_leaves_it(tmp_path, driver):
    alpha = 1 + DELAY * FS
    # the FEI rule would (rightly) stop the uncompensated run: 20 ms > 15 ms default tolerance
    common = [f"driver.name={driver}", _twin(), "loop.duration=6", "safety.fei_delay_tol=0.1"]
    _, res_on, run_on = run_lockstep(tmp_path, *common, f"compensation.alpha={alpha}", name="on")
    _, res_off, run_off = run_lockstep(tmp_path, *common, "compensation.enabled=false", name="off")
    for res in (res_on, res_off):
        assert res.status == "completed" and res.steps == 6 * 1024
        assert res.missed_replies == 0
    on = fei(run_on.record["target"], run_on.record["measured"], FS)
    off = fei(run_off.record["target"], run_off.record["measured"], FS)
    assert abs(on.delay) < 1e-3, on.delay
    assert abs(off.delay - DELAY) < 1e-3, off.delay
    assert on.amplitude == pytest.approx(1.0, abs=0.01)
    # the online streaming estimate at the end agrees with the whole-record evaluation
    rec = run_off.record
    assert rec["fei_valid"][-1]
    assert abs(rec["fei_delay"][-1] - DELAY) < 1e-3
    # measured vs command is the actuator's own delay in both runs
    cmd = fei(run_on.record["command"], run_on.record["measured"], FS)
    assert abs(cmd.delay - DELAY) < 1e-3


def _offline_chain(cfg_over, n, driver):
    """The same chain as the loop, written independently without any transport."""
    cfg = load_config(None, cfg_over)
    s = cfg["structure"]
    gm = groundmotion.default_record().scaled(cfg["ground_motion"]["pga"]).resampled(FS)
    ag = np.asarray(gm.accel)[:n]
    k = s["mass"] * (2 * math.pi * s["fn"]) ** 2
    bw = BoucWenParams(
        x_y=s["x_y"], k_a=k, eta=s["eta"], beta=s["beta"], gamma=s["gamma"], q=s["q"]
    )
    st = CRStepper(
        s["mass"], s["damping"], k, 1 / FS, bouc_wen=bw, k_specimen=s["k_specimen"], ag0=ag[0]
    )
    comp = InverseCompensator(cfg["compensation"]["alpha"])
    plant = load_plant({"actuator": cfg["twin"]["actuator"]}, 1 / FS)
    qd, qf = LSB[driver]
    out = {key: np.empty(n) for key in ("target", "command", "measured", "force")}
    x = st.x
    comp.reset(x)
    c = comp.step(x)
    for i in range(n):
        cq = c if qd is None else round(c / qd) * qd
        m, f = plant.step(cq)
        if qd is not None:
            m, f = round(m / qd) * qd, round(f / qf) * qf
        out["target"][i], out["command"][i], out["measured"][i], out["force"][i] = x, c, m, f
        x = st.step(ag[i], f) if i > 0 else st.x_next
        c = comp.step(x)
    return out


@pytest.mark.parametrize("driver", DRIVERS)
def test_lockstep_record_equals_an_offline_simulation_of_the_chain(tmp_path, driver):
    over = [
        f"driver.name={driver}",
        "twin.actuator={model='first_order', time_constant=0.02, delay=0.005}",
        "loop.duration=3",
    ]
    _, res, run = run_lockstep(tmp_path, *over)
    ref = _offline_chain(over, res.steps, driver)
    rec = run.record
    for key in ("target", "command", "measured", "force"):
        np.testing.assert_allclose(rec[key], ref[key], rtol=0, atol=1e-9, err_msg=key)
    np.testing.assert_array_equal(rec["step"], np.arange(res.steps))
    np.testing.assert_allclose(rec["time"], np.arange(res.steps) / FS)
    assert rec["feedback_ok"].all() and (rec["lateness"] == 0).all()
    # the specimen force acts on the structure: a run without it gives a different response
    assert np.abs(rec["force"]).max() > 1e3


def test_record_columns_events_and_meta(tmp_path):
    loop, res, run = run_lockstep(tmp_path, "loop.duration=5", "fei.exact_hop=512")
    rec = run.record
    for col in (
        "time",
        "ground_accel",
        "target",
        "command",
        "measured",
        "force",
        "fei_amplitude",
        "fei_delay",
        "fei_valid",
        "kf_gain",
        "kf_delay",
        "lateness",
    ):
        assert col in rec.dtype.names
    # the streaming FEI needs one full window (3/fn = 3.9 s) before its first estimate
    n_win = round(3 / 0.77 * FS)
    assert not rec["fei_valid"][: n_win - 1].any()
    assert np.isnan(rec["fei_amplitude"][: n_win - 1]).all()
    # the exact cross-check agrees with the streaming estimate (within 1 %, 0.5 ms)
    ev = rec["fei_exact_valid"]
    assert ev.any()
    last = np.flatnonzero(ev)[-1]
    assert rec["fei_exact_delay"][last] == pytest.approx(rec["fei_delay"][last], abs=5e-4)
    assert rec["fei_exact_amplitude"][last] == pytest.approx(rec["fei_amplitude"][last], rel=0.01)
    # the Kalman estimator sees the actuator (command → measured): 20 ms lag + 5 ms delay
    assert rec["kf_delay"][-1] == pytest.approx(0.025, abs=0.002)
    assert rec["kf_gain"][-1] == pytest.approx(1.0, abs=0.02)
    kinds = [e["kind"] for e in run.events]
    assert kinds[0] == "start" and kinds[-1] == "end" and "trip" not in kinds
    assert run.events[-1]["status"] == "completed"
    # lockstep has no deadlines: no overrun of any cause
    assert run.events[-1]["overrun_causes"] == dict.fromkeys(
        ("machine", "machine_backlog", "work", "work_backlog", "machine_in_work"), 0
    )
    assert res.ready.size == 0
    assert run.meta["config"]["structure"]["mass"] == 503400.0
    assert run.meta["versions"]["numpy"] == np.__version__
    assert run.meta["mode"] == "lockstep"
    assert res.exit_code == 0 and loop.twin.stats.estops == 0


def test_adaptive_alpha_moves_towards_the_twin_delay(tmp_path):
    # start under-compensated (α = 6 ≈ 5 ms for a 20 ms twin); adaptation raises α
    _, res, run = run_lockstep(
        tmp_path,
        _twin(),
        "loop.duration=14",
        "compensation.alpha=6",
        "compensation.adaptive=true",
        "compensation.time_constant=3",
        "compensation.rate=20",
        "fei.window=2.5s",
        "safety.fei_delay_tol=0.1",
    )
    assert res.status == "completed"
    alpha = run.record["alpha"]
    assert alpha[0] == 6.0
    assert alpha[-1] == pytest.approx(1 + DELAY * FS, abs=1.5)  # the goal 1 + 20 ms · 1024 Hz
    assert abs(run.record["fei_delay"][-1]) < 1e-3
    assert alpha.max() <= 100.0
    assert np.all(np.abs(np.diff(alpha)) <= 20.0 / FS + 1e-9)  # the rate limit holds
    assert res.final_alpha == pytest.approx(alpha[-1], abs=20.0 / FS + 1e-9)

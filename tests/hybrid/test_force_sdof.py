"""A pure force-controlled SDOF test against its all-numerical model (issue #35).

The hybrid test: a linear SDOF frame (5 t, 2 Hz, 2 %) whose specimen (a 1.19 MN/m spring with a
114.6 N·s/m dashpot, the twin's) is loaded by a force-controlled actuator through the Modbus map
with a force set-point, on the force-controlled twin (5 ms delay, 20 ms valve lag, a 4.2 ms
closed force loop). The integrator assumes the specimen stiffness ``structure.k_specimen``
(docs/channels.md). The reference: ``m ü + (c + c_s) u̇ + (k + k_s) u = −m a_g`` solved exactly
for the record's ground acceleration taken as linear between samples (scipy's
``lsim`` with ``interp=True``: the matrix exponential of the state equation, first-order hold),
nothing of rths_hil in it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lsim

import rths_hil
from rths_hil.records.recorder import read_run

ROOT = Path(__file__).resolve().parents[2]
MAP = ROOT / "examples" / "controllers" / "column_axial_map.toml"

M, FN, ZETA = 5000.0, 2.0, 0.02  # the numerical frame
KS, CS = 1.19e6, 114.6  # the specimen (the twin's)

CONFIG = f"""
control = "force"
[structure]
kind = "sdof"
mass = {M}
fn = {FN}
damping = {ZETA}
bouc_wen = false
k_specimen = {KS}
[ground_motion]
pga = 1.0
[driver]
name = "modbus"
profile = "{MAP}"
connection = {{ transport = "tcp" }}
[twin]
specimen = {{ stiffness = {KS}, damping = {CS} }}
"""


def _reference(t: np.ndarray, ag: np.ndarray) -> np.ndarray:
    k = M * (2 * np.pi * FN) ** 2
    c = 2 * ZETA * np.sqrt(k * M)
    # x = [u, u̇]:  ẋ = A x + B a_g,  A = [[0, 1], [−(k + k_s)/m, −(c + c_s)/m]],  B = [0, −1]
    a = np.array([[0.0, 1.0], [-(k + KS) / M, -(c + CS) / M]])
    b = np.array([[0.0], [-1.0]])
    _, u, _ = lsim((a, b, np.array([[1.0, 0.0]]), np.zeros((1, 1))), ag, t, interp=True)
    return u


def _nrms(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - ref) ** 2)) / np.sqrt(np.mean(ref**2)))


@pytest.fixture(scope="module")
def force_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("force_sdof")
    cfg = d / "sdof.toml"
    cfg.write_text(CONFIG)
    out = d / "run"
    rths_hil.run(cfg, mode="lockstep", duration=8.0, run_dir=out)
    return out


def test_force_sdof_agrees_with_its_numerical_model(force_run):
    run = read_run(force_run)
    rec = run.record
    t, ag = np.asarray(rec["time"]), np.asarray(rec["ground_accel"])
    u = _reference(t, ag)
    trial = np.asarray(rec["trial"])  # the structure's displacement along the actuator
    assert np.max(np.abs(u)) > 5e-3  # a test that moves: ≈ 10 mm
    assert _nrms(trial, u) <= 0.01
    # the specimen's restoring force the structure received: F_m + k_s (d − x_m), against the
    # reference's spring and dashpot at the reference's motion
    v = np.gradient(u, t)
    r_ref = KS * u + CS * v
    r = np.asarray(rec["force"]) + KS * (trial - np.asarray(rec["measured"]))
    assert _nrms(r, r_ref) <= 0.01


def test_force_sdof_tracks_the_force_and_says_so(force_run):
    run = read_run(force_run)
    (ch,) = run.meta["channels"]
    assert (ch["control"], ch["tracked"], ch["tracked_unit"]) == ("force", "force", "N")
    units = {c["name"]: c["unit"] for c in run.meta["columns"]}
    assert units["target"] == units["command"] == units["force"] == "N"
    assert units["measured"] == units["trial"] == "m"
    summary = json.loads((force_run / "summary.json").read_text())
    assert (summary["control"], summary["tracked"], summary["unit"]) == ("force", "force", "N")
    # the FEI of the measured force against the target force: the force loop's lag left
    # after the 25 ms compensation of a 29 ms loop (5 ms delay, 20 ms valve, 4.2 ms force loop)
    f = summary["fei_target"]
    assert f["valid"] and 0.0 < f["delay"] < 0.01 and abs(f["amplitude"] - 1.0) < 0.1
    rec = run.record
    target, force = np.asarray(rec["target"]), np.asarray(rec["force"])
    np.testing.assert_allclose(target, KS * np.asarray(rec["trial"]), rtol=1e-12, atol=1e-9)
    assert np.max(np.abs(force)) == pytest.approx(np.max(np.abs(target)), rel=0.1)

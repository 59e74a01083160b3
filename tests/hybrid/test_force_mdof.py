"""A force-controlled channel between two floors of a shear building against the all-numerical
model of the same structure (issue #35).

Three storeys (20, 20, 15 t; 12, 10, 7 MN/m; Rayleigh C = 0.2·M + 0.002·K); the specimen, a
2 MN/m spring with a 114.6 N·s/m dashpot (the twin's), acts between floors 1 and 2 (the transform
row [-1, 1, 0]) through a force-controlled actuator (Modbus map with a force set-point, the
force twin). The reference: ``M ü + (C + c_s rrᵀ) u̇ + (K + k_s rrᵀ) u = −M·1·a_g`` built here
from the storeys and solved exactly for the record's ground acceleration taken as linear between
samples (scipy's ``lsim`` with ``interp=True``: the matrix exponential of the state equation,
first-order hold).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.signal import lsim

import rths_hil
from rths_hil.records.recorder import read_run

ROOT = Path(__file__).resolve().parents[2]
MAP = ROOT / "examples" / "controllers" / "column_axial_map.toml"
MASSES = [2.0e4, 2.0e4, 1.5e4]
STOREYS = [1.2e7, 1.0e7, 0.7e7]
ALPHA, BETA = 0.2, 0.002
KS, CS = 2.0e6, 114.6
ROW = [-1.0, 1.0, 0.0]

CONFIG = f"""
control = "force"
[structure]
kind = "shear_building"
masses = {MASSES}
stiffnesses = {STOREYS}
rayleigh = [{ALPHA}, {BETA}]
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
[[actuators]]
name = "brace"
transform = {ROW}
"""


def _reference(t: np.ndarray, ag: np.ndarray) -> np.ndarray:
    m = np.diag(MASSES)
    k1, k2, k3 = STOREYS
    k = np.array([[k1 + k2, -k2, 0.0], [-k2, k2 + k3, -k3], [0.0, -k3, k3]])
    c = ALPHA * m + BETA * k
    r = np.array(ROW)
    kt, ct = k + KS * np.outer(r, r), c + CS * np.outer(r, r)
    minv = np.linalg.inv(m)
    # x = [u, u̇]:  ẋ = [[0, I], [−M⁻¹K_t, −M⁻¹C_t]] x + [0, −1]ᵀ a_g  (M⁻¹·(−M·1) = −1)
    a = np.block([[np.zeros((3, 3)), np.eye(3)], [-minv @ kt, -minv @ ct]])
    b = np.concatenate([np.zeros(3), -np.ones(3)])[:, None]
    out = np.hstack([np.eye(3), np.zeros((3, 3))])
    _, u, _ = lsim((a, b, out, np.zeros((3, 1))), ag, t, interp=True)
    return u.T


def test_force_channel_between_floors_agrees_with_the_numerical_model(tmp_path):
    cfg = tmp_path / "mdof.toml"
    cfg.write_text(CONFIG)
    out = tmp_path / "run"
    rths_hil.run(cfg, mode="lockstep", duration=6.0, run_dir=out)
    rec = read_run(out).record
    t, ag = np.asarray(rec["time"]), np.asarray(rec["ground_accel"])
    ref = _reference(t, ag)
    u = np.array([np.asarray(rec[f"u_{i}"]) for i in (1, 2, 3)])
    assert np.max(np.abs(ref[0])) > 5e-3  # it moves: ≈ 16 mm at floor 1
    for i in range(3):
        nrms = np.sqrt(np.mean((u[i] - ref[i]) ** 2) / np.mean(ref[i] ** 2))
        assert nrms <= 0.01, (i + 1, nrms)
    # the channel's trial displacement is the storey drift it acts across
    np.testing.assert_allclose(np.asarray(rec["trial"]), u[1] - u[0], rtol=0, atol=1e-15)

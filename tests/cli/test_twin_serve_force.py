"""``rths-hil twin serve --control force``: a force-controlled twin as its own process.

The twin serves the force-controlled twin of a model file behind the Modbus map with a force
set-point (examples/controllers/column_axial_map.toml) or a CiA 402 drive in cyclic synchronous
torque; the bridge (in the test's process) runs a short lockstep force-controlled SDOF test
against it (``control = "force"``, ``twin.enabled = false``). The reference is the
all-numerical model of the same structure, ``m ü + (c + c_s) u̇ + (k + k_s) u = −m a_g``,
solved exactly by scipy (``lsim``): it only agrees when the served twin closed a force loop on
the model file's specimen.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lsim

from tests.helpers.cli import one_line_exit_2
from tests.helpers.procs import ROOT, ServedTwin, run_bridge

MAP = ROOT / "examples" / "controllers" / "column_axial_map.toml"
M, FN, ZETA = 5000.0, 2.0, 0.02  # the numerical frame
KS, CS = 1.19e6, 114.6  # the specimen (the served twin's)

MODEL = f"""
[actuator]
model = "servo_lag"
time_constant = "20ms"
delay = "5ms"

[specimen]
stiffness = {KS}
damping = {CS}
"""

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
record = "sine.csv"
pga = 0.0
"""
#: per family: the twin's options, the bridge's [driver] table (the connection is the twin's)
FAMILIES = {
    "modbus": (["--profile", str(MAP)], f'[driver]\nprofile = "{MAP}"\n'),
    "canopen": (["--interface", "serial"], ""),  # CiA 402 cyclic synchronous torque
}


def _reference(t: np.ndarray, ag: np.ndarray) -> np.ndarray:
    k = M * (2 * np.pi * FN) ** 2
    c = 2 * ZETA * np.sqrt(k * M)
    # x = [u, u̇]:  ẋ = A x + B a_g,  A = [[0, 1], [−(k + k_s)/m, −(c + c_s)/m]],  B = [0, −1]
    # (solved exactly with a_g linear between samples: lsim's first-order hold)
    a = np.array([[0.0, 1.0], [-(k + KS) / M, -(c + CS) / M]])
    b = np.array([[0.0], [-1.0]])
    _, u, _ = lsim((a, b, np.array([[1.0, 0.0]]), np.zeros((1, 1))), ag, t, interp=True)
    return u


@pytest.mark.parametrize("driver", sorted(FAMILIES))
def test_served_force_twin_runs_a_lockstep_force_channel(tmp_path: Path, driver: str) -> None:
    model = tmp_path / "force_twin.toml"
    model.write_text(MODEL, encoding="utf-8")
    # a 2.5 Hz ground acceleration of 1 m/s², faded in over 0.4 s (the record, as CSV)
    tg = np.arange(0.0, 2.0, 0.005)
    accel = np.sin(2 * np.pi * 2.5 * tg) * np.minimum(tg / 0.4, 1.0)
    rows = "".join(f"{a:.6f},{b:.9f}\n" for a, b in zip(tg, accel, strict=True))
    (tmp_path / "sine.csv").write_text("time_s,accel_ms2\n" + rows, encoding="utf-8")
    cfg = tmp_path / "sdof.toml"
    serve, table = FAMILIES[driver]
    cfg.write_text(CONFIG + table, encoding="utf-8")
    out = tmp_path / "run"
    twin = ServedTwin(
        "--driver", driver, *serve, "--model", str(model),
        "--control", "force", "--force-loop-gain", "2e-4", "--heartbeat-timeout", "0",
    )  # fmt: skip
    try:  # the bridge in this process: the twin's own process is the point
        res = run_bridge(driver, twin.connection, out, config=cfg, mode="lockstep", duration=1.0)
    finally:
        twin.stop()
    assert res.result.status == "completed", res.result.trip
    run = res.run
    (ch,) = run.meta["channels"]
    assert (ch["control"], ch["tracked"]) == ("force", "force")
    rec = run.record
    t, ag = np.asarray(rec["time"]), np.asarray(rec["ground_accel"])
    u = _reference(t, ag)
    trial = np.asarray(rec["trial"])
    assert np.max(np.abs(u)) > 3e-3  # a test that moves
    nrms = np.sqrt(np.mean((trial - u) ** 2)) / np.sqrt(np.mean(u**2))
    assert nrms <= 0.01
    # the served twin closed its loop on the model file's spring: force = k_s x + c_s ẋ
    x = np.asarray(rec["measured"])
    f_spring = KS * x + CS * np.gradient(x, t)
    f = np.asarray(rec["force"])
    assert np.max(np.abs(f - f_spring)) < 1e-3 * np.max(np.abs(f))
    # and it was stepped by the bridge's commands (lockstep): its own count, on its stderr
    assert twin.first("stopped after", timeout=5.0) is not None
    (line,) = [ln for _, ln in twin.lines if "stopped after" in ln]
    steps = int(line.split("stopped after ")[1].split()[0])
    assert steps >= len(t)


_MODBUS = ["twin", "serve", "--driver", "modbus"]


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--force-loop-gain", "1e-4"], "--force-loop-gain 1e-4: only with --control force"),
        (["--control", "force", "--force-loop-gain", "0"], "must be a number > 0 (m/s per N)"),
        (["--control", "force", "--force-loop-gain", "fast"], "must be a number > 0"),
        (["--control", "force"], "roles.force_setpoint is missing"),  # the plain map has none
        (["--profile", str(MAP), "--control", "force"], "a force-controlled twin does not take"),
    ],
)
def test_force_options_are_refused_in_one_line(tmp_path, capsys, argv, needle):
    if "--profile" not in argv:
        argv = [*argv, "--profile", str(ROOT / "examples" / "controllers" / "modbus_map.toml")]
    if needle.startswith("a force-controlled"):  # a model file with an effect it refuses
        model = tmp_path / "m.toml"
        model.write_text("[actuator]\n[[actuator.effects]]\nkind = 'backlash'\nwidth = 1e-3\n")
        argv = [*argv, "--model", str(model)]
    one_line_exit_2([*_MODBUS, *argv], capsys, needle)

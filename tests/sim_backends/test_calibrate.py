"""Twin calibration from a record: recovers a known twin; the CLI writes a loadable model file."""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.modelfile import load_model, load_plant
from scipy import signal

from rths_hil.cli import main
from rths_hil.errors import InputError
from rths_hil.estimation import calibrate
from rths_hil.records.csvfiles import read_record, write_record
from tests.helpers.twin_signals import FS, sdof_response


def _twin_record(model: dict, u: np.ndarray) -> np.ndarray:
    return load_plant(model, 1 / FS).simulate(u)[0]


def test_recovers_delay_gain_noise_and_resolution():
    t, u = sdof_response(fn=1.0, peak=0.02)
    true = {
        "actuator": {"delay": 0.0137, "gain": 0.962},
        "sensor": {"displacement_noise": 2e-5, "displacement_resolution": 1e-6, "seed": 5},
    }
    y = _twin_record(true, u)
    spec, info = calibrate(t, u, y, return_info=True)
    a = spec.actuator
    assert a.model == "delay_gain" and a.effects == []
    assert a.delay == pytest.approx(0.0137, abs=5e-5)
    assert a.gain == pytest.approx(0.962, rel=1e-3)
    assert spec.sensor.displacement_resolution == 1e-6
    assert spec.sensor.displacement_noise == pytest.approx(2e-5, rel=0.05)
    assert info.fs == pytest.approx(FS)
    # the initial cross-correlation guess is within a sample
    assert abs(info.initial_delay - 0.0137) <= 1 / FS
    # the calibrated twin reproduces the record to the noise level
    again = spec.build(1 / FS).simulate(u)[0]
    assert np.std(again - y) == pytest.approx(np.sqrt(2) * 2e-5, rel=0.1)


def test_recovers_servo_lag_and_offset_from_broadband_excitation():
    rng = np.random.default_rng(2)
    n = int(20 * FS)
    u = signal.sosfilt(signal.butter(4, 20.0, fs=FS, output="sos"), rng.standard_normal(n))
    u *= 0.005 / np.std(u)
    t = np.arange(n) / FS
    true = {
        "actuator": {
            "delay": 0.005,
            "gain": 0.99,
            "model": "servo_lag",
            "time_constant": 0.010,
            "effects": [{"kind": "offset", "offset": 3e-4}],
        },
        "sensor": {"displacement_noise": 1e-5},
    }
    y = _twin_record(true, u)
    spec = calibrate(t, u, y, servo_lag=True)
    a = spec.actuator
    assert a.model == "servo_lag"
    assert a.params["time_constant"] == pytest.approx(0.010, rel=0.02)
    assert a.delay == pytest.approx(0.005, abs=1e-4)
    assert a.gain == pytest.approx(0.99, rel=2e-3)
    assert [e.kind for e in a.effects] == ["offset"]
    assert a.effects[0].params["offset"] == pytest.approx(3e-4, abs=1e-6)
    assert spec.sensor.displacement_resolution == 0.0


def test_pure_delay_twin_without_offset_has_no_offset_effect():
    t, u = sdof_response("kobe_1995_nishi_akashi_NIS000", fn=2.0, peak=0.01)
    y = _twin_record(
        {"actuator": {"delay": 0.02, "gain": 1.0}, "sensor": {"displacement_noise": 1e-5}}, u
    )
    spec = calibrate(t, u, y)
    assert spec.actuator.effects == []
    assert spec.actuator.delay == pytest.approx(0.02, abs=1e-4)


def test_bad_records():
    t = np.arange(100) / FS
    u = np.sin(t)
    with pytest.raises(InputError, match="measured: non-finite value at sample 3"):
        y = u.copy()
        y[3] = np.nan
        calibrate(t, u, y)
    with pytest.raises(InputError, match="input: constant signal"):
        calibrate(t, np.zeros(100), u)
    with pytest.raises(InputError, match="time: non-uniform"):
        t2 = t.copy()
        t2[50:] += 0.3 / FS
        calibrate(t2, u, u)
    with pytest.raises(InputError, match="equal length"):
        calibrate(t, u, u[:-1])
    with pytest.raises(InputError, match="at least 16"):
        calibrate(t[:5], u[:5], u[:5])


# -- CLI --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def record_csv(tmp_path_factory):
    t, u = sdof_response(fn=1.0, peak=0.02, duration=15.0)
    true = {"actuator": {"delay": 0.011, "gain": 1.03}, "sensor": {"displacement_noise": 1e-5}}
    y = _twin_record(true, u)
    path = tmp_path_factory.mktemp("rec") / "test.csv"
    write_record(path, {"time": t, "command": u, "target": 0.5 * u, "measured": y})
    return path


def test_cli_writes_loadable_model(record_csv, tmp_path, capsys):
    out = tmp_path / "twin.toml"
    track = tmp_path / "track.csv"
    rc = main(["twin", "calibrate", str(record_csv), "--out", str(out), "--track", str(track)])
    assert rc == 0
    stdout = capsys.readouterr().out
    assert "delay 11.0" in stdout and f"wrote {out}" in stdout
    spec = load_model(out)
    # 'command' is preferred over 'target' (which is half the command here)
    assert spec.actuator.delay == pytest.approx(0.011, abs=1e-4)
    assert spec.actuator.gain == pytest.approx(1.03, rel=2e-3)
    assert out.read_text().startswith("# twin calibrated by rths-hil twin calibrate from ")
    rec = read_record(track, required=("time", "gain", "delay"))
    assert rec["delay"][-1] == pytest.approx(0.011, abs=1e-3)
    # explicit target column: gain doubles
    out2 = tmp_path / "t2.toml"
    assert (
        main(["twin", "calibrate", str(record_csv), "--input-column", "target", "--out", str(out2)])
        == 0
    )
    assert load_model(out2).actuator.gain == pytest.approx(2.06, rel=2e-3)


def test_cli_prints_toml_without_out(record_csv, capsys):
    assert main(["twin", "calibrate", str(record_csv), "--no-offset"]) == 0
    captured = capsys.readouterr()
    assert "[actuator]" in captured.out and "gain " in captured.err


def test_cli_errors_are_one_line_exit_2(record_csv, tmp_path, capsys):
    out = tmp_path / "exists.toml"
    out.write_text("keep me")
    assert main(["twin", "calibrate", str(record_csv), "--out", str(out)]) == 2
    assert out.read_text() == "keep me"
    err = capsys.readouterr().err
    assert "exists (use --force" in err and err.count("\n") == 1
    assert main(["twin", "calibrate", str(record_csv), "--out", str(out), "--force"]) == 0
    capsys.readouterr()
    bad = tmp_path / "bad.csv"
    write_record(bad, {"time": np.arange(50) / FS, "measured": np.zeros(50)})
    assert main(["twin", "calibrate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "missing column command or target" in err and err.count("\n") == 1
    assert main(["twin", "calibrate", str(record_csv), "--max-delay=-5ms"]) == 2
    assert "--max-delay" in capsys.readouterr().err

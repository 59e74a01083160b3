"""``rths-hil diagnose``: report.json, augmented model file, PNG, console; one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rths_hil.sim_backends.modelfile import dump_model, load_model

from rths_hil.cli import main
from rths_hil.diagnose.synthetic import make_case
from rths_hil.metrics import j2_nrms
from rths_hil.records.csvfiles import write_record


def _write_case(tmp_path, kinds, seed, duration=20.0, force=True):
    case = make_case(kinds, seed, duration=duration)
    cols = {"time": case.time, "command": case.command, "measured": case.measured}
    if force:
        cols["force"] = case.force
    rec = tmp_path / "record.csv"
    write_record(rec, cols, fmt="%.12g")
    model = tmp_path / "twin.toml"
    dump_model(case.base, model)
    return case, rec, model


def _rc(argv: list[str]) -> int:
    """Exit code of the CLI, whether returned or raised by argparse."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_cli_names_the_hidden_effect_and_writes_everything(tmp_path, capsys):
    case, rec, model = _write_case(tmp_path, ["stroke_limit"], 7700)
    out = tmp_path / "out"
    rc = main(["diagnose", str(rec), "--model", str(model), "--out", str(out)])
    printed = capsys.readouterr().out
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert [e["name"] for e in report["effects"]] == ["stroke_limit"]
    eff = report["effects"][0]
    assert set(eff) >= {"name", "parameters", "where", "gap_before", "gap_after"}
    assert set(eff["where"]) >= {"when", "frequency", "regime", "acts"}
    assert eff["parameters"]["limit"] == pytest.approx(case.hidden[0].params["limit"], rel=0.02)
    assert report["gap_after"] <= 0.5 * report["gap_before"]
    assert report["model"] == str(out / "model.toml")
    # the augmented model file loads and, simulated by the twin, gives the reported gap
    spec = load_model(report["model"])
    assert [e.kind for e in spec.actuator.effects] == ["stroke_limit"]
    plant = spec.build(1.0 / case.fs)
    pred = plant.effects.simulate(plant.actuator.simulate(case.command))
    assert j2_nrms(case.measured, pred) == pytest.approx(report["gap_after"], rel=1e-6)
    png = (out / "diagnose.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # the console says the same in a few lines
    assert "stroke_limit" in printed
    assert len(printed.strip().splitlines()) <= 6
    assert f"{report['gap_after']:.3g} %" in printed


def test_cli_without_model_on_a_clean_record_answers_none(tmp_path, capsys):
    _, rec, _ = _write_case(tmp_path, [], 7701, force=False)
    out = tmp_path / "out"
    rc = main(["diagnose", str(rec), "--out", str(out), "--no-plot"])
    assert rc == 0
    report = json.loads((out / "report.json").read_text())
    assert report["effects"] == []
    assert report["answer"] == "none"
    assert report["gap_after"] == report["gap_before"]
    base = load_model(out / "base_model.toml")  # the delay + gain fitted to the record
    assert base.actuator.effects == []
    assert load_model(out / "model.toml").actuator.delay == base.actuator.delay
    assert not (out / "diagnose.png").exists()
    assert "answer: none" in capsys.readouterr().out


def _csv_lines(path):
    return path.read_text().splitlines()


def test_cli_mismatched_lengths(tmp_path, capsys):
    _, rec, model = _write_case(tmp_path, [], 7702, duration=8.0, force=False)
    lines = _csv_lines(rec)
    lines[500] = ",".join(lines[500].split(",")[:2])  # a row without its measured value
    rec.write_text("\n".join(lines) + "\n")
    rc = main(["diagnose", str(rec), "--model", str(model), "--out", str(tmp_path / "o")])
    assert rc == 2
    line = _one_line_error(capsys)
    assert "record.csv:501" in line and "expected 3 values" in line


def test_cli_nan_in_measured(tmp_path, capsys):
    _, rec, model = _write_case(tmp_path, [], 7702, duration=8.0, force=False)
    lines = _csv_lines(rec)
    parts = lines[300].split(",")
    parts[2] = "nan"
    lines[300] = ",".join(parts)
    rec.write_text("\n".join(lines) + "\n")
    rc = main(["diagnose", str(rec), "--model", str(model), "--out", str(tmp_path / "o")])
    assert rc == 2
    line = _one_line_error(capsys)
    assert "record.csv:301" in line and "measured" in line


def test_cli_model_file_with_unknown_effect(tmp_path, capsys):
    _, rec, model = _write_case(tmp_path, [], 7702, duration=8.0, force=False)
    model.write_text(
        model.read_text() + '\n[[actuator.effects]]\nkind = "friction"\nforce = 10.0\n'
    )
    rc = main(["diagnose", str(rec), "--model", str(model), "--out", str(tmp_path / "o")])
    assert rc == 2
    line = _one_line_error(capsys)
    assert "actuator.effects[0].kind" in line and "friction" in line


def test_cli_record_too_short_to_decide(tmp_path, capsys):
    case, rec, model = _write_case(tmp_path, [], 7702, duration=8.0, force=False)
    n = 4 * 1024  # 4 s
    write_record(
        rec, {"time": case.time[:n], "command": case.command[:n], "measured": case.measured[:n]}
    )
    rc = main(["diagnose", str(rec), "--model", str(model), "--out", str(tmp_path / "o")])
    assert rc == 2
    line = _one_line_error(capsys)
    assert "too short to decide" in line and "record.csv" in line
    assert not (tmp_path / "o" / "report.json").exists()


@pytest.mark.parametrize(
    "args, match",
    [
        (["--max-effects", "-1"], "--max-effects"),
        (["--threshold", "ten"], "--threshold"),
        (["--threshold", "-5"], "--threshold"),
        (["--candidates", "offset,friction"], "friction"),
    ],
)
def test_cli_bad_options(tmp_path, capsys, args, match):
    _, rec, _model = _write_case(tmp_path, [], 7702, duration=8.0, force=False)
    rc = _rc(["diagnose", str(rec), "--out", str(tmp_path / "o"), *args])
    assert rc == 2
    assert match in _one_line_error(capsys)


def test_cli_missing_command_column(tmp_path, capsys):
    rec = tmp_path / "r.csv"
    t = np.arange(8192) / 1024
    write_record(rec, {"time": t, "target": np.sin(t), "measured": np.sin(t)})
    rc = main(["diagnose", str(rec), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "missing column(s) command" in _one_line_error(capsys)

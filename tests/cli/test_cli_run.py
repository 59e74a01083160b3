"""``rths-hil run`` and ``rths-hil export``: exit codes, one-line errors, files written."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.config import load_config
from rths_hil.records.recorder import read_run

# in-process, in lockstep: no test here depends on the wall clock (they run with the parallel
# tests, not under the "timing" marker)

QUICK = ["--lockstep", "--set", "loop.console=0"]


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--set", "loop.fs=abc"], ["--set loop.fs=abc", "loop.fs"]),
        (["--set", "loop.fss=1"], ["loop.fss", "unknown key"]),
        (["--set", "driver.name=nope"], ["driver", "unknown driver 'nope'"]),
        (["--set", "twin.actuator.model=warp"], ["twin.", "warp"]),
        (["--set", "ground_motion.record=missing.at2"], ["ground_motion.record", "missing.at2"]),
        (["--duration", "-1"], ["--duration"]),
        (["--duration", "5 parsecs"], ["--duration"]),
        (["--lockstep", "--paced"], ["exclude"]),
        (["--set", "loop.cpu=4096"], ["loop.cpu = 4096", "may run on CPUs"]),
        (["--set", "loop.cpu=-2"], ["loop.cpu"]),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, needles):
    code = main(["run", *args, "--out", str(tmp_path / "r"), "-q"])
    assert code == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("rths-hil run: error:")
    for needle in needles:
        assert needle in line
    assert not (tmp_path / "r" / "record.npy").exists()


def test_config_file_error_names_file_and_key(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[safety]\nfei_delay_tol = true\n")
    assert main(["run", str(p), "-q"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(p) in line and "safety.fei_delay_tol" in line


def test_show_config_prints_loadable_toml(tmp_path, capsys):
    assert main(["run", "--show-config", "--set", "loop.fs=2048"]) == 0
    text = capsys.readouterr().out
    assert tomllib.loads(text)["loop"]["fs"] == 2048.0
    p = tmp_path / "shown.toml"
    p.write_text(text)
    assert load_config(p).as_dict() == load_config(None, ["loop.fs=2048"]).as_dict()


def test_lockstep_run_writes_the_run_directory_and_summary(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", *QUICK, "--duration", "5", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    for name in ("record.npy", "events.jsonl", "meta.json", "summary.json", "report.png"):
        assert (out / name).is_file(), name
    assert "FEI measured vs target" in captured.out and "J1 =" in captured.out
    assert "e-stop: none" in captured.out
    assert len(read_run(out).record) == 5 * 1024
    # the link budget at start-up: one line per link, on the console
    link = [ln for ln in captured.err.splitlines() if ln.startswith("rths-hil run: link ")]
    assert len(link) == 1 and "can virtual" in link[0] and "no limit" in link[0], captured.err


def test_safety_trip_exits_3_with_one_clear_line(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(
        ["run", *QUICK, "--duration", "4", "--out", str(out), "-q", "--set", "twin.faults=nan=1200"]
    )
    assert code == 3
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("rths-hil run: e-stop: nan:") and "step 1200" in line
    assert str(out) in line
    assert len(read_run(out).record) == 1201


def test_export_csv_columns_and_errors(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", *QUICK, "--duration", "2", "--out", str(out), "-q"]) == 0
    assert main(["export", str(out), "--csv"]) == 0
    header = (out / "record.csv").read_text().splitlines()[0].split(",")
    required = [
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
    ]
    assert all(c in header for c in required) and header[0] == "time"
    data = np.genfromtxt(out / "record.csv", delimiter=",", names=True)
    rec = read_run(out).record
    np.testing.assert_allclose(data["measured"], rec["measured"], rtol=1e-9, atol=1e-15)
    sub = tmp_path / "sub"
    assert main(["export", str(out), "--columns", "target,measured", "--out", str(sub)]) == 0
    assert (sub / "record.csv").read_text().splitlines()[0] == "time,target,measured"
    capsys.readouterr()
    assert main(["export", str(tmp_path)]) == 2
    assert "not a run directory" in _one_line(capsys.readouterr().err)
    assert main(["export", str(out), "--columns", "nope"]) == 2


def test_export_mat_reads_back_in_scipy(tmp_path, capsys):
    """record.mat: a struct of column vectors equal to the record, units, meta as JSON."""
    import json

    from scipy.io import loadmat

    out = tmp_path / "run"
    assert main(["run", *QUICK, "--duration", "1", "--out", str(out), "-q"]) == 0
    assert main(["export", str(out), "--mat"]) == 0
    assert capsys.readouterr().out.strip() == str(out / "record.mat")
    assert not (out / "record.csv").exists()  # --mat alone: no CSV
    m = loadmat(out / "record.mat", squeeze_me=False, struct_as_record=False)
    rec = read_run(out).record
    r, units = m["record"][0, 0], m["units"][0, 0]
    for name in ("time", "target", "measured", "force", "fei_valid", "step"):
        col = getattr(r, name)
        assert col.shape == (len(rec), 1) and col.dtype == np.float64
        np.testing.assert_array_equal(col[:, 0], rec[name].astype(float))
    assert str(units.measured[0]) == "m" and str(units.force[0]) == "N"
    meta = json.loads(str(m["meta"][0]))
    assert meta["fs"] == 1024 and len(json.loads(str(m["events"][0]))) >= 2
    sub = tmp_path / "sub"
    assert (
        main(["export", str(out), "--mat", "--csv", "--columns", "measured", "--out", str(sub)])
        == 0
    )
    assert sorted(p.name for p in sub.iterdir()) == ["record.csv", "record.mat"]
    assert sorted(loadmat(sub / "record.mat")["record"].dtype.names) == ["measured", "time"]


def test_dbc_path_is_relative_to_the_config_file(tmp_path, capsys, monkeypatch):
    """driver.connection.dbc: a lab's DBC next to its config; a wrong one is one line."""
    import shutil

    from rths_hil.drivers.can.codec import DBC_PATH

    lab = tmp_path / "lab"
    lab.mkdir()
    # the lab's DBC: the shipped one with the Command message moved to identifier 0x120
    text = DBC_PATH.read_text()
    assert "BO_ 256 Command" in text
    (lab / "ours.dbc").write_text(text.replace("BO_ 256 Command", "BO_ 288 Command"))
    cfg = lab / "test.toml"
    cfg.write_text(
        '[driver]\nname = "can"\nconnection = { interface = "virtual", dbc = "ours.dbc" }\n'
    )
    monkeypatch.chdir(tmp_path)  # not the config's folder: read from the cwd, it would not load
    out = tmp_path / "run"
    assert main(["run", str(cfg), *QUICK, "--duration", "0.5", "--out", str(out), "-q"]) == 0
    stats = read_run(out).meta["config"]["driver"]["connection"]
    assert stats["dbc"] == "ours.dbc"
    shutil.copy(lab / "ours.dbc", lab / "bad.dbc")
    (lab / "bad.dbc").write_text(text.replace("Feedback", "Feedbak"))
    cfg.write_text(cfg.read_text().replace("ours.dbc", "bad.dbc"))
    capsys.readouterr()
    assert main(["run", str(cfg), *QUICK, "--duration", "0.5", "--out", str(tmp_path / "r2")]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "bad.dbc" in line and "message Feedback is missing" in line


def test_live_line_content_and_terminal_behaviour():
    import io

    from rths_hil.report import LiveLine, format_live

    status = {
        "t": 12.5,
        "k": 12800,
        "n": 30720,
        "rate": 1024.0,
        "p99_lateness": 8.2e-5,
        "overruns": 3,
        "amplitude": 1.0031,
        "delay": 0.00042,
        "valid": True,
        "peak_displacement": 0.01127,
        "margin": ("displacement", 0.7746),
        "alpha": 26.6,
        "mode": "paced",
    }
    line = format_live(status)
    for part in (
        "12.50 s",
        "1024 steps/s",
        "p99 late 0.082 ms",
        "overruns 3",
        "A 1.0031",
        "d +0.42 ms",
        "peak 11.27 mm",
        "margin: displacement limit 77 % left",
        "( 42 %)",
        "α 26.60",
    ):
        assert part in line, part
    assert "\n" not in line
    # an OpenSees site has no planned end: no percentage of the cap; compensation off: no α
    site = format_live(dict(status, open_ended=True, compensation=False))
    assert "%)" not in site and "α" not in site and "compensation off" in site
    assert "12.50 s |" in site
    invalid = format_live(dict(status, amplitude=float("nan"), delay=float("nan")))
    assert "A — d — ms" in invalid

    class Tty(io.StringIO):
        def isatty(self):
            return True

    tty = Tty()
    live = LiveLine(tty)
    live(status)
    live(dict(status, t=13.0))
    live.finish()
    out = tty.getvalue()
    assert out.count("\r") == 2 and out.endswith("\n") and out.count("\n") == 1
    log = io.StringIO()
    live = LiveLine(log, every=10)
    for _ in range(25):
        live(status)
    assert log.getvalue().count("\n") == 3  # statuses 0, 10, 20

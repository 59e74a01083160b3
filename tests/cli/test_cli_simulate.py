"""``rths-hil simulate``: record written, readable by records.read_record, errors one line."""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay

from rths_hil.cli import main
from rths_hil.fei import fei
from rths_hil.groundmotion import default_record
from rths_hil.records.csvfiles import read_record
from rths_hil.structures.sdof import simulate_sdof
from rths_hil.units import G


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("bouc_wen", [False, True])
def test_simulate_writes_the_seed_block_diagram_record(tmp_path, capsys, bouc_wen):
    out = tmp_path / "sim.csv"
    argv = ["simulate", "--pga", "0.0528g", "--fn", "1.0", "--gain", "1.1", "--delay", "5ms"]
    argv += ["--fs", "256", "--out", str(out)] + (["--bouc-wen"] if bouc_wen else [])
    code, stdout, err = _run(capsys, *argv)
    assert code == 0, err
    assert "wrote" in stdout
    rec = read_record(out, required=("time", "target", "measured", "ground_accel", "force"))
    assert rec.names == ["time", "target", "measured", "ground_accel", "force"]
    assert rec.fs == pytest.approx(256.0)
    ag = rec["ground_accel"]
    assert np.max(np.abs(ag)) == pytest.approx(0.0528 * G, rel=1e-9)
    # independent reconstruction of the chain: record → SDOF → delay·gain
    ref_ag = default_record().resampled(256.0).scaled("0.0528g").accel
    np.testing.assert_allclose(ag, ref_ag, rtol=1e-9, atol=1e-12)
    x = simulate_sdof(ref_ag, 256.0, 1.0, 0.02, bouc_wen=bouc_wen or None)
    np.testing.assert_allclose(rec["target"], x, rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(
        rec["measured"], 1.1 * fractional_delay(x, 5e-3, 256.0), rtol=1e-9, atol=1e-13
    )
    # what `evaluate` will compute: A = 1.1 and d = 5 ms over the whole record
    res = fei(rec["target"], rec["measured"], rec.fs)
    assert res.amplitude == pytest.approx(1.1, rel=2e-3)
    assert res.delay == pytest.approx(5e-3, rel=2e-2)
    force = rec["force"]
    if bouc_wen:
        assert np.max(np.abs(x)) > 0.01  # beyond x_y: the structure yields
        assert np.max(np.abs(force)) <= 1.1765e7 * 0.01 * (1 + 1e-9)
    else:
        np.testing.assert_allclose(force, 1.1765e7 * rec["target"], rtol=1e-9, atol=1e-6)


def test_simulate_plot_and_bundled_record_name(tmp_path, capsys):
    out = tmp_path / "k.csv"
    code, _, err = _run(
        capsys,
        "simulate",
        "--record",
        "kobe_1995_nishi_akashi_NIS000",
        "--fn",
        "2",
        "--fs",
        "128",
        "--out",
        str(out),
        "--plot",
    )
    assert code == 0, err
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert read_record(out).fs == pytest.approx(128.0)


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--fn", "-1"], "--fn"),
        (["--fn", "0"], "--fn"),
        (["--fn", "abc"], "--fn"),
        (["--fn", "600"], "Nyquist"),
        (["--fn", "1", "--zeta", "-0.1"], "--zeta"),
        (["--fn", "1", "--gain", "0"], "--gain"),
        (["--fn", "1", "--delay=-5ms"], "--delay"),
        (["--fn", "1", "--delay", "5 parsecs"], "delay"),
        (["--fn", "1", "--pga", "0.3 furlong"], "PGA"),
        (["--fn", "1", "--record", "/nonexistent/elc.AT2"], "no such ground-motion file"),
        (["--fn", "1", "--fs", "-2"], "--fs"),
    ],
)
def test_simulate_bad_arguments_one_line_exit_2(tmp_path, capsys, extra, needle):
    code, _, err = _run(capsys, "simulate", "--out", str(tmp_path / "o.csv"), *extra)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("rths-hil simulate: error:")
    assert needle.lower() in lines[0].lower()
    assert "Traceback" not in err
    assert not (tmp_path / "o.csv").exists()


def test_simulate_unknown_record_format_and_bad_out_dir(tmp_path, capsys):
    bad = tmp_path / "rec.dat"
    bad.write_text("some text\n1 2 3\n")
    code, _, err = _run(capsys, "simulate", "--record", str(bad), "--fn", "1", "--out", "x.csv")
    assert code == 2 and "unknown ground-motion format" in err and len(err.splitlines()) == 1
    trunc = tmp_path / "t.AT2"
    lines = open(default_record().source).read().splitlines()
    trunc.write_text("\n".join(lines[:100]))
    code, _, err = _run(capsys, "simulate", "--record", str(trunc), "--fn", "1", "--out", "x.csv")
    assert code == 2 and "truncated" in err and len(err.splitlines()) == 1
    code, _, err = _run(capsys, "simulate", "--fn", "1", "--out", str(tmp_path / "nodir" / "x.csv"))
    assert code == 2 and "does not exist" in err and len(err.splitlines()) == 1


def test_simulate_missing_required_argument_is_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--out", "x.csv"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--fn" in err and len(err.strip().splitlines()) == 1

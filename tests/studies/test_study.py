"""The FEI paper's computational study: criterion, window search, accuracy table, CLI."""

from __future__ import annotations

import csv
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from rths_hil import studies as study
from rths_hil.cli import main
from rths_hil.errors import InputError
from rths_hil.fei import MovingFEIResult
from rths_hil.groundmotion import bundled_path, default_record, load

FS = 1024.0


@pytest.fixture(scope="module")
def elcentro():
    return default_record().resampled(FS).scaled("0.0528g")


@pytest.fixture(scope="module")
def chopra():
    return load(bundled_path("el_centro_1940_NS_chopra_0p02.csv")).resampled(FS).scaled("0.0528g")


def _fake(delays, levels, valid=None):
    n = len(delays)
    d = np.asarray(delays, float)
    return MovingFEIResult(
        np.arange(n, dtype=float),
        np.ones(n),
        np.zeros(n),
        np.ones(n),
        d,
        np.ones(n, bool) if valid is None else np.asarray(valid),
        np.asarray(levels, float),
    )


def test_criterion_counts_and_statistics():
    res = _fake(
        [1.0e-3, 1.5e-3, 1.01e-3, 2e-3, 1.002e-3],
        [0.5, 0.01, 1.0, 0.2, 0.3],
        valid=[True, True, True, False, True],
    )
    crit = study.WindowCriterion(tolerance=0.01, statistic="max", min_level=0.1)
    np.testing.assert_array_equal(crit.counted(res), [True, False, True, False, True])
    err, n = crit.delay_error(res, 1e-3)
    assert n == 3 and err == pytest.approx(0.01)
    all_valid = study.WindowCriterion(statistic="max", min_level=0.0)
    assert all_valid.delay_error(res, 1e-3)[0] == pytest.approx(0.5)  # the low-level window
    p50 = study.WindowCriterion(statistic="p50", min_level=0.0)
    assert p50.delay_error(res, 1e-3)[0] == pytest.approx(np.percentile([0, 0.5, 0.01, 0.002], 50))
    for bad in ({"statistic": "mean"}, {"statistic": "p0"}, {"tolerance": 0}, {"min_level": 1.0}):
        with pytest.raises(InputError):
            study.WindowCriterion(**bad)


def test_auto_decimation_keeps_64_samples_per_period():
    assert study.auto_decimation(1024, 0.2) == 8
    assert study.auto_decimation(1024, 4.0) == 4
    assert study.auto_decimation(1024, 5.1) == 2
    assert study.auto_decimation(1024, 10.0) == 1
    for fn in (0.2, 1.0, 3.3, 5.1):
        q = study.auto_decimation(1024, fn)
        assert 1024 / q >= 64 * fn


def test_window_search_is_the_first_passing_multiple_of_tenths(elcentro):
    crit = study.WindowCriterion()
    r = study.window_size_for(elcentro, 2.0, criterion=crit)
    assert r.window_periods == pytest.approx(round(r.window_periods, 1))
    assert r.delay_error_pct <= 1.0
    assert r.tried == round((r.window_periods - 1.0) / 0.1) + 1
    # one step shorter does not pass (first passing window)
    shorter = study.window_size_for(
        elcentro,
        2.0,
        criterion=crit,
        start_periods=r.window_periods - 0.1,
        max_periods=r.window_periods - 0.1,
    )
    assert math.isnan(shorter.window_s) and shorter.delay_error_pct > 1.0


def test_seed_findings_window_size(elcentro):
    """The FEI paper's Section 4: lower fn needs a longer window; 2–3 (here ≤ 5) periods suffice for
    a linear structure; a nonlinear structure needs at least as long as a linear one."""
    lin = study.window_size_study(
        [elcentro], [0.5, 2.0, 1.0], executor=study.SerialExecutor(), progress=False
    )
    by_fn = {r.fn_hz: r for r in lin}
    assert by_fn[0.5].window_s > by_fn[1.0].window_s > by_fn[2.0].window_s
    for r in lin:
        assert 2.0 <= r.window_periods <= 5.0
        assert r.structure == "linear"
    bw = study.window_size_for(elcentro, 1.0, bouc_wen=True)
    assert bw.structure == "bouc-wen"
    assert bw.window_s >= by_fn[1.0].window_s


def test_executors_are_pluggable(chopra):
    kw = {"progress": False, "max_periods": 2.5}
    fns = [1.0, 2.0]
    serial = study.window_size_study([chopra], fns, executor=study.SerialExecutor(), **kw)
    with ThreadPoolExecutor(max_workers=2) as ex:
        threaded = study.window_size_study([chopra], fns, executor=ex, **kw)
    pooled = study.window_size_study([chopra], fns, **kw)  # default: 2 processes
    key = [(r.fn_hz, r.window_s, r.delay_error_pct, r.tried) for r in serial]
    assert [r.fn_hz for r in serial] == fns
    for other in (threaded, pooled):
        got = [(r.fn_hz, r.window_s, r.delay_error_pct, r.tried) for r in other]
        np.testing.assert_array_equal(np.array(got, float), np.array(key, float))


def test_seed_findings_accuracy(chopra):
    """The FEI paper's Table 4.1: amplitude errors below 1 %; delay errors larger for the nonlinear
    structure than for the linear one at the same frequency."""
    rows = study.accuracy_study(
        chopra, (0.5, 0.7, 1.0), executor=study.SerialExecutor(), progress=False, hop=4
    )
    assert [(r.fn_hz, r.structure) for r in rows] == [
        (f, s) for f in (0.5, 0.7, 1.0) for s in ("linear", "bouc-wen")
    ]
    for r in rows:
        assert r.window_s == pytest.approx(3.0 / r.fn_hz)
        assert 0 < r.max_err_amplitude_pct < 1.0
        assert r.counted.sum() > 100
        if r.structure == "bouc-wen":
            assert r.peak_displacement_m > 0.01  # yields (x_y = 10 mm)
    for lin, nl in zip(rows[::2], rows[1::2], strict=True):
        assert nl.max_err_delay_pct > lin.max_err_delay_pct
    # the maxima are the maxima of the histories over the counted windows
    r = rows[0]
    a = np.abs(r.amplitude[r.counted] - 1.1) / 1.1 * 100
    assert r.max_err_amplitude_pct == pytest.approx(a.max())


def test_accuracy_rejects_window_longer_than_record(chopra):
    with pytest.raises(InputError, match="longer than the record"):
        study.accuracy_study(chopra, (0.05,), executor=study.SerialExecutor(), progress=False)
    with pytest.raises(InputError, match="natural frequency"):
        study.accuracy_study(chopra, (-1.0,), executor=study.SerialExecutor(), progress=False)


# ----------------------------------------------------------------------------- CLI


def test_cli_window_size_writes_csv_and_figure(tmp_path, capsys):
    out = tmp_path / "ws"
    code = main(
        [
            "study",
            "window-size",
            "--record",
            "el_centro_1940_NS_chopra_0p02",
            "--fn",
            "2,3",
            "--workers",
            "1",
            "--no-progress",
            "--max-periods",
            "5",
            "--out",
            str(out),
        ]
    )
    stdout, err = capsys.readouterr()
    assert code == 0, err
    with open(out / "window_size.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["fn_hz"]) for r in rows] == [2.0, 3.0]
    for r in rows:
        assert float(r["window_s"]) == pytest.approx(float(r["window_periods"]) / float(r["fn_hz"]))
    assert (out / "window_size.png").read_bytes()[:4] == b"\x89PNG"
    assert "window_size.csv" in stdout


def test_cli_accuracy_csv_columns(tmp_path, capsys):
    out = tmp_path / "acc"
    code = main(
        [
            "study",
            "accuracy",
            "--record",
            "el_centro_1940_NS_chopra_0p02",
            "--pga",
            "0.0528g",
            "--fn",
            "1.0",
            "--window",
            "3T",
            "--hop",
            "16",
            "--workers",
            "1",
            "--no-progress",
            "--out",
            str(out),
        ]
    )
    _, err = capsys.readouterr()
    assert code == 0, err
    with open(out / "accuracy.csv", newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader)
        rows = list(reader)
    assert header[:5] == [
        "fn_hz",
        "structure",
        "window_s",
        "max_err_amplitude_pct",
        "max_err_delay_pct",
    ]
    assert [r[1] for r in rows] == ["linear", "bouc-wen"]
    assert float(rows[0][2]) == pytest.approx(3.0)
    assert (out / "accuracy.png").exists()


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["accuracy", "--window", "100s"], "longer than the record"),
        (["accuracy", "--fn=-0.5"], "> 0"),
        (["accuracy", "--window=-3T"], "--window"),
        (["window-size", "--fn", "0.2:0.1:0.1"], "--fn"),
        (["window-size", "--fn=-1,2"], "> 0"),
        (["window-size", "--statistic", "mean", "--fn", "2"], "statistic"),
        (["window-size", "--criterion", "0%", "--fn", "2"], "tolerance"),
        (["window-size", "--fn", "0.01"], "shorter than two periods"),
        (["accuracy", "--record", "nowhere.AT2"], "no such ground-motion file"),
        (["accuracy", "--delay", "0"], "--delay"),
    ],
)
def test_cli_study_bad_arguments(tmp_path, capsys, argv, needle):
    code = main(["study", *argv, "--workers", "1", "--no-progress", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("rths-hil study: error:") and needle in err
    assert "Traceback" not in err


def test_cli_unknown_record_format(tmp_path, capsys):
    bad = tmp_path / "r.xyz"
    bad.write_text("nothing to see\n")
    code = main(["study", "accuracy", "--record", str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "unknown ground-motion format" in err and len(err.splitlines()) == 1

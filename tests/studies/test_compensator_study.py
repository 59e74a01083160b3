"""``study compensators``: every method on the same draws, rows equal to the robustness study's."""

from __future__ import annotations

import csv
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from rths_hil import studies as study
from rths_hil.cli import main
from rths_hil.config import load_config
from rths_hil.studies.compensators import compensator_study, write_comparison

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def comparison():
    cfg = load_config(None, ["twin.sensor={}"])
    perts = [study.parse_vary("twin.actuator.delay=3ms:8ms", cfg)]
    with ThreadPoolExecutor(1) as ex:
        res = compensator_study(
            cfg, ["inverse", "ats"], perts, 2, seed=5, duration=6.0, executor=ex, progress=False
        )
        ref = study.robustness_study(
            cfg, perts, 2, seed=5, duration=6.0, executor=ex, progress=False
        )
    return res, ref


def test_every_method_runs_on_the_same_draws_and_inverse_equals_the_robustness_study(comparison):
    res, ref = comparison
    assert [r["method"] for r in res.rows] == ["inverse"] * 2 + ["ats"] * 2
    key = "twin.actuator.delay"
    inv = [r for r in res.rows if r["method"] == "inverse"]
    ats = [r for r in res.rows if r["method"] == "ats"]
    assert [r[key] for r in inv] == [r[key] for r in ats] == [r[key] for r in ref.rows]
    for a, b in zip(inv, ref.rows, strict=True):  # lockstep: the same run, the same figures
        for m in ("fei_delay", "fei_amplitude", "J2", "bench_J2"):
            assert a[m] == b[m]
    # ats differs from inverse on the same plant (the comparison can fail)
    assert all(a["J2"] != b["J2"] for a, b in zip(inv, ats, strict=True))


def test_comparison_files_hold_the_medians_of_the_rows(comparison, tmp_path):
    res, _ = comparison
    written = write_comparison(tmp_path, res, plot=True)
    assert written == ["trials.csv", "comparison.csv", "comparison.md", "compensators_box.png"]
    with (tmp_path / "comparison.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    for m in ("inverse", "ats"):
        got = next(r for r in rows if r["method"] == m and r["metric"] == "J2")
        want = np.median([r["J2"] for r in res.rows if r["method"] == m])
        assert float(got["median"]) == pytest.approx(want, rel=1e-12)
    md = (tmp_path / "comparison.md").read_text()
    assert "inverse median" in md and "ats 95 %" in md and "`bench_J9`" in md
    with (tmp_path / "trials.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 4


def test_unknown_method_is_one_line_exit_2(tmp_path, capsys):
    code = main(
        ["study", "compensators", str(ROOT / "examples" / "can.toml"), "--methods",
         "inverse,atss", "--trials", "1", "--out", str(tmp_path / "o")]
    )  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "atss" in err and "Traceback" not in err

"""The chunked summary of long records equals the in-memory one (memory).

``summarize`` evaluates records longer than ``lean_rows`` rows in chunks (whole-record FEI from
chunked spectral sums, J1–J3 and TI from running sums, J1's correlation block by block). Here
the same record is summarised both ways (``lean_rows`` forced below its length), and the
chunked FEI is also checked against the closed form of a delayed, scaled sine.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rths_hil.records.recorder import COLUMNS, Recorder
from rths_hil.report import figure, plot_report, summarize
from rths_hil.report import summary as report_summary

FS = 512.0
DELAY = 0.0123
GAIN = 0.97


CHUNK = 4096  # rows per chunk in these tests (the module's is 2**18)


@pytest.fixture(autouse=True)
def small_chunks(monkeypatch):
    monkeypatch.setattr(report_summary, "_CHUNK", CHUNK)
    monkeypatch.setattr(figure, "_CHUNK", CHUNK)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A run directory of 3 chunks and a bit: a sine sweep measured with delay and gain."""
    n = 3 * CHUNK + 1234
    t = np.arange(n) / FS
    f = 0.8 + 0.4 * np.sin(2 * np.pi * t / 10.0)  # slowly varying frequency
    x = 0.01 * np.sin(2 * np.pi * np.cumsum(f) / FS)
    y = GAIN * np.interp(np.arange(n) - DELAY * FS, np.arange(n), x)
    names = [c[0] for c in COLUMNS]
    d = tmp_path_factory.mktemp("chunked") / "run"
    rec = Recorder(d, FS, extra_meta={"mode": "lockstep"})
    for k in range(n):
        row = dict.fromkeys(names, 0.0)
        row.update(
            time=t[k], step=k, target=x[k], command=x[k], measured=y[k], force=1e6 * y[k],
            fei_amplitude=GAIN, fei_delay=DELAY, fei_valid=True, fei_exact_valid=False,
            feedback_ok=True, seq=k,
        )  # fmt: skip
        rec.append(*(row[c] for c in names))
    rec.event("end", n / FS, n, status="completed", wall_duration=1.5)
    rec.close()
    return d


def test_chunked_summary_equals_the_in_memory_one(run_dir):
    full = summarize(run_dir, write=False)
    lean = summarize(run_dir, write=False, lean_rows=1000)
    for key in ("fei_target", "fei_command"):
        # the chunked FEI transforms in single precision (sums in double): ≈ 1e-7 relative
        for q in ("amplitude", "delay", "f_eq"):
            assert lean[key][q] == pytest.approx(full[key][q], rel=2e-6, abs=1e-12)
            assert lean[key][q] != full[key][q] or q == "f_eq"  # it is the chunked path
        assert lean[key]["valid"] == full[key]["valid"] is True
    for q, v in full["metrics"].items():
        assert lean["metrics"][q] == pytest.approx(v, rel=1e-9, abs=1e-15), q
    assert lean["online"] == full["online"] and lean["peak"] == full["peak"]
    assert full["wall_time"] == 1.5  # the end event's wall_duration


def test_chunked_fei_finds_the_imposed_delay_and_gain(run_dir):
    s = summarize(run_dir, write=False, lean_rows=1000)
    assert s["fei_target"]["amplitude"] == pytest.approx(GAIN, abs=2e-3)
    assert s["fei_target"]["delay"] == pytest.approx(DELAY, abs=5e-4)
    assert s["metrics"]["j1_delay"] == pytest.approx(DELAY, abs=1.0 / FS)
    assert math.isfinite(s["metrics"]["tracking_indicator"])


def test_report_of_a_long_record_is_an_envelope(run_dir, tmp_path):
    png = plot_report(run_dir, tmp_path / "r.png", max_points=2000)
    assert png.stat().st_size > 10_000

"""``rths_hil.report.summarize`` / ``format_summary``: the end event's overrun causes."""

from __future__ import annotations

import json

import numpy as np

from rths_hil.records.recorder import COLUMNS, Recorder
from rths_hil.report import format_summary, summarize


def _run(path, end_fields: dict, n: int = 64, fs: float = 1024.0) -> None:
    """A paced run directory with ``n`` rows and an ``end`` event carrying ``end_fields``."""
    late = np.linspace(0.0, 4e-4, n)  # the last steps are more than ½ period late
    with Recorder(path, fs, extra_meta={"mode": "paced", "driver": "can"}) as rec:
        for k in range(n):
            row = []
            for name, code, _, _ in COLUMNS:
                if name == "time":
                    row.append(k / fs)
                elif name == "lateness":
                    row.append(float(late[k]))
                elif code == "<i8":
                    row.append(k)
                elif code == "|b1":
                    row.append(True)
                else:
                    row.append(1e-3 * np.sin(0.1 * k))
            rec.append(*row)
        rec.event("end", time=n / fs, step=n - 1, status="completed", **end_fields)


def test_overrun_causes_reach_summary_json_and_the_printed_summary(tmp_path):
    causes = {
        "machine": 3,
        "machine_backlog": 1,
        "work": 7,
        "work_backlog": 2,
        "machine_in_work": 4,
    }
    _run(tmp_path / "r", {"lateness": {"overruns": 13}, "overrun_causes": causes})
    s = summarize(tmp_path / "r")
    assert s["overrun_causes"] == causes
    on_disk = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert on_disk["overrun_causes"] == causes
    assert on_disk["lateness"]["overruns"] == 13
    text = format_summary(s)
    line = next(ln for ln in text.splitlines() if "by cause" in ln)
    assert "machine 3 (+1 catch-up)" in line and "work 7 (+2 catch-up)" in line
    assert "machine inside the work 4" in line


def test_a_run_recorded_before_overrun_causes_has_none(tmp_path):
    _run(tmp_path / "r", {"lateness": {"overruns": 2}})
    s = summarize(tmp_path / "r")
    assert "overrun_causes" not in s
    assert "overrun_causes" not in json.loads((tmp_path / "r" / "summary.json").read_text())
    assert "by cause" not in format_summary(s)


def test_too_short_rule():
    from rths_hil.report.summary import _too_short

    fs = 1024.0
    # shorter than one FEI window (3.9 s) → too short; the window decides when longer than 1 s
    assert "3.90 s" in _too_short(round(3.8 * fs), fs, 3.9)
    assert _too_short(round(3.9 * fs), fs, 3.9) is None
    # a window shorter than 1 s: the 1 s floor decides
    assert "< 1 s" in _too_short(round(0.9 * fs), fs, 0.5)
    assert _too_short(round(1.0 * fs), fs, 0.5) is None
    assert "< 1 s" in _too_short(38, fs, None)


def test_short_run_says_too_short_instead_of_j1_j3(tmp_path):
    # 64 rows at 1024 Hz (62 ms): J2 of a fraction of a cycle is meaningless
    _run(tmp_path / "r", {})
    s = summarize(tmp_path / "r")
    assert "too short" in s["too_short"]
    assert "j2_nrms" in s["metrics"]  # still computed and kept in summary.json
    text = format_summary(s)
    assert "run too short for the whole-record FEI and J1–J3 (0.06 s < 1 s)" in text
    assert "J2 =" not in text and "FEI measured vs" not in text


def test_long_run_prints_fei_with_its_legend(tmp_path):
    _run(tmp_path / "r", {}, n=2048)  # 2 s, no FEI window in the meta: 1 s floor
    text = format_summary(summarize(tmp_path / "r"))
    assert "too short" not in text and "J2 =" in text
    assert "FEI measured vs target: the tracking quality" in text
    assert "measured vs command: the actuator's raw lag" in text


def test_report_panels_units_and_trip_label(tmp_path):
    """report.png: ground motion, tracking error in mm, force–displacement in mm/kN, the
    summary text and a labelled trip marker."""
    import matplotlib.pyplot as plt

    from rths_hil.config import load_config
    from rths_hil.hybrid import RTHSLoop
    from rths_hil.records.recorder import read_run
    from rths_hil.report import plot_report

    cfg = load_config(None, ["loop.console=0", "safety.displacement_limit=0.004"])
    res = RTHSLoop(cfg, tmp_path / "r", mode="lockstep", duration=4.0).run()
    assert res.status == "trip"
    summarize(tmp_path / "r")
    fig = plot_report(tmp_path / "r", keep_figure=True)
    rec = read_run(tmp_path / "r").record
    titles = [a.get_title() for a in fig.axes] + [a.get_title("left") for a in fig.axes]
    for part in ("ground motion", "tracking error", "force–displacement", "summary"):
        assert any(part in t for t in titles), (part, titles)
    err_ax = next(a for a in fig.axes if "tracking error" in a.get_title())
    y = err_ax.lines[0].get_ydata()
    np.testing.assert_allclose(y, (rec["measured"] - rec["target"]) * 1e3)
    fd_ax = next(a for a in fig.axes if a.get_title() == "force–displacement")
    x, f = fd_ax.lines[0].get_data()
    np.testing.assert_allclose(x, rec["measured"] * 1e3)
    np.testing.assert_allclose(f, rec["force"] / 1e3)
    labels = [t.get_text() for a in fig.axes for t in a.texts]
    trip_t = res.trip.time
    assert f"e-stop: displacement at {trip_t:.3f} s" in labels
    assert any("e-stop: displacement" in t and "run too short" in t for t in labels)
    plt.close(fig)

"""``rths_hil.report.summarize`` / ``format_summary``: the end event's overrun causes."""

from __future__ import annotations

import json

import numpy as np

from rths_hil.recorder import COLUMNS, Recorder
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
    causes = {"machine": 3, "machine_backlog": 1, "work": 7, "work_backlog": 2}
    _run(tmp_path / "r", {"lateness": {"overruns": 13}, "overrun_causes": causes})
    s = summarize(tmp_path / "r")
    assert s["overrun_causes"] == causes
    on_disk = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert on_disk["overrun_causes"] == causes
    assert on_disk["lateness"]["overruns"] == 13
    text = format_summary(s)
    line = next(ln for ln in text.splitlines() if "by cause" in ln)
    assert "machine 3 (+1 catch-up)" in line and "work 7 (+2 catch-up)" in line


def test_a_run_recorded_before_overrun_causes_has_none(tmp_path):
    _run(tmp_path / "r", {"lateness": {"overruns": 2}})
    s = summarize(tmp_path / "r")
    assert "overrun_causes" not in s
    assert "overrun_causes" not in json.loads((tmp_path / "r" / "summary.json").read_text())
    assert "by cause" not in format_summary(s)

"""Tracking of every compensator on the shipped examples, lockstep on the twins.

For each configuration and method: the FEI amplitude A and equivalent delay d of measured vs
target over the whole record (the FEI paper's Eq. 2.3 and 2.5), per channel; for the default
configuration also at 2048 and 4096 Hz (the compensation is configured in time, so the figures
must not move). Deterministic (lockstep, seeded sensor noise): the table is the same on every
machine; only the run time differs.

Run: ``.venv/bin/python benchmarks/compare_compensators.py`` (about 5 minutes).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from _results import markdown_table, write_results

from rths_hil.config import load_config
from rths_hil.fei import fei
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import read_run

ROOT = Path(__file__).resolve().parents[1]
TWO = ROOT / "examples" / "two_actuators.toml"
DURATION = 20
METHODS = ("inverse", "polynomial", "ats", "model")


def run(path, *sets) -> list[tuple[str, float, float, str]]:
    """(channel, A, d, status) of one lockstep run."""
    cfg = load_config(
        path,
        [
            "loop.mode=lockstep",
            "loop.console=0",
            "output.plot=false",
            f"loop.duration={DURATION}",
            *sets,
        ],
    )
    with tempfile.TemporaryDirectory() as tmp:
        res = RTHSLoop(cfg, Path(tmp) / "run").run()
        rec = read_run(Path(tmp) / "run").record
    fs = cfg["loop"]["fs"]
    out = []
    for name in rec.dtype.names:
        if name.startswith("target"):
            sfx = name[len("target") :]
            r = fei(rec[name], rec["measured" + sfx], fs)
            out.append((sfx.lstrip("_") or "-", r.amplitude, r.delay, res.status))
    return out


def main() -> None:
    rows = []
    default_model = [
        "compensation.model_time_constant=20ms",
        "compensation.delay=5ms",
    ]
    cases = [("default, 1024 Hz", None, m, []) for m in METHODS]
    cases += [
        ("default, 2048 Hz", None, "inverse", ["loop.fs=2048"]),
        ("default, 4096 Hz", None, "inverse", ["loop.fs=4096"]),
    ]
    cases += [("two_actuators.toml", TWO, m, []) for m in METHODS]
    for label, path, method, sets in cases:
        extra = default_model if (method == "model" and path is None) else []
        for ch, a, d, status in run(path, f"compensation.method={method}", *extra, *sets):
            rows.append([label, f"`{method}`", ch, f"{a:.4f}", f"{d * 1e3:+.3f}", status])
            print(rows[-1], flush=True)
    table = markdown_table(["configuration", "method", "channel", "A", "d (ms)", "status"], rows)
    write_results(
        "compare_compensators",
        table,
        title="Tracking of the compensators on the examples (lockstep)",
        goals=(
            "`two_actuators.toml` with the best method: every channel |A − 1| ≤ 1 % and "
            "|d| ≤ 0.5 ms. The default configuration at 2048 and 4096 Hz within 0.5 ms of its "
            "1024 Hz d."
        ),
        notes=(
            f"{DURATION} s of each record, lockstep, default keys of each method (`model` on the "
            "default configuration is given the twin's first-order servo, "
            "`model_time_constant = 20 ms`, `delay = 5 ms`; on `two_actuators.toml` the twins "
            "are pure delays and the channels' `delay` is the model). A and d: FEI of the "
            "whole record, measured vs target."
        ),
    )


if __name__ == "__main__":
    main()

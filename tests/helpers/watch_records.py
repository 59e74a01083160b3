"""Synthetic run directories written through the real :class:`rths_hil.records.recorder.Recorder`.

A single-channel record has the columns (:data:`rths_hil.records.recorder.COLUMNS`); a
multi-channel record suffixes each per-channel column with ``_<channel>`` and adds ``u_1 …
u_n`` (the layout of multi-actuator tests). The signals are known sines, so a test can check
what the watcher reads and shows against what was written.
"""

from __future__ import annotations

import inspect
import math
from pathlib import Path

import numpy as np

from rths_hil.config import load_config
from rths_hil.records import recorder
from rths_hil.records.recorder import COLUMNS, Recorder
from rths_hil.watch.source import CHANNEL_COLUMNS

AMPLITUDE = {"": 0.004, "left": 0.004, "right": 0.002}

#: The ``stability`` column a run adds after :data:`COLUMNS` (the energy stability indicator S).
STABILITY = ("stability", "<f8", "-", "energy stability indicator S")


def stability_value(t: float, ch: str) -> float:
    """The synthetic ``S`` of channel ``ch`` at loop time ``t`` (NaN: not valid, the first
    second): a slow sine about 0.5, opposite on the channel ``right``."""
    sign = -1.0 if ch == "right" else 1.0
    return 0.5 + sign * 0.4 * math.sin(2 * math.pi * 0.1 * t) if t >= 1.0 else math.nan


def columns_for(channels: list[str], n_dof: int = 1) -> list[tuple[str, str, str, str]]:
    """Record columns for ``channels`` (``[""]``: the single-channel columns)."""
    if channels == [""]:
        return [*COLUMNS, STABILITY]
    per = [c for c in COLUMNS if c[0] in CHANNEL_COLUMNS and c[0] != "seq"] + [STABILITY]
    shared = [c for c in COLUMNS if c[0] not in CHANNEL_COLUMNS or c[0] == "seq"]
    cols = shared[:3]
    for ch in channels:
        cols += [(f"{n}_{ch}", code, u, d) for n, code, u, d in per]
    cols += shared[3:]
    cols += [(f"u_{i + 1}", "<f8", "m", f"displacement of DOF {i + 1}") for i in range(n_dof)]
    return cols


def _recorder(run_dir: Path, fs: float, cols, monkeypatch, **kw) -> Recorder:
    if "columns" in inspect.signature(Recorder).parameters:
        return Recorder(run_dir, fs, columns=cols, **kw)
    # a Recorder without a ``columns`` argument writes its module's COLUMNS
    monkeypatch.setattr(recorder, "COLUMNS", tuple(cols))
    dt = np.dtype([(n, c) for n, c, _, _ in cols])
    monkeypatch.setattr(recorder, "record_dtype", lambda columns=None: dt)
    return Recorder(run_dir, fs, **kw)


def split(name: str) -> tuple[str, str]:
    """``("measured", "left")`` for ``measured_left``; ``("time", "")`` for a shared column."""
    if name in CHANNEL_COLUMNS:
        return name, ""
    for base in sorted(CHANNEL_COLUMNS, key=len, reverse=True):
        if name.startswith(base + "_"):
            return base, name[len(base) + 1 :]
    return name, ""


def row_values(cols, k: int, fs: float) -> list:
    """Row ``k`` of the synthetic test: each channel a 1 Hz sine, measured 5 ms late."""
    t = k / fs
    out: list = []
    for name, code, _, _ in cols:
        base, ch = split(name)
        a = AMPLITUDE.get(ch, 0.003)
        on = k >= fs  # the FEI and Kalman estimates are valid after the first second
        if name == "time":
            v = t
        elif base in ("step", "seq"):
            v = k
        elif base == "target" or name.startswith("u_"):
            v = a * math.sin(2 * math.pi * t)
        elif base == "command":
            v = 1.02 * a * math.sin(2 * math.pi * (t + 0.005))
        elif base == "measured":
            v = a * math.sin(2 * math.pi * (t - 0.005))
        elif base == "force":
            v = 2.0e5 * a * math.sin(2 * math.pi * (t - 0.005))
        elif base in ("fei_amplitude", "fei_exact_amplitude", "kf_gain"):
            v = 1.0 if on else math.nan
        elif base in ("fei_delay", "fei_exact_delay", "kf_delay"):
            v = 0.005 if on else math.nan
        elif base in ("fei_valid", "fei_exact_valid"):
            v = on
        elif base == "feedback_ok":
            v = True
        elif base == "stability":
            v = stability_value(t, ch)
        else:
            v = False if code == "|b1" else 0.0
        out.append(v)
    return out


def write_run(
    run_dir: Path,
    monkeypatch,
    channels: list[str],
    seconds: float = 12.0,
    fs: float = 256.0,
    end: str | None = "completed",
    trip: dict | None = None,
) -> Path:
    """Write a whole synthetic run (``end=None``: no end event, as after ``kill -9``)."""
    cols = columns_for(channels, n_dof=2 if channels != [""] else 1)
    n = round(seconds * fs)
    cfg = load_config(None, ["loop.fs=256"]).as_dict()
    meta = {"mode": "lockstep", "planned_steps": n, "driver": "can", "window_s": 3.0}
    with _recorder(run_dir, fs, cols, monkeypatch, config=cfg, extra_meta=meta) as rec:
        rec.event("start", 0.0, 0, mode="lockstep", fs=fs, steps=n, rules=[])
        rec.event("clock", 0.0, 0, wall_t0=0.0)
        for k in range(n):
            rec.append(*row_values(cols, k, fs))
        if trip is not None:
            rec.event("trip", **trip)
        if end is not None:
            rec.event("end", n / fs, n, status=end)
    return run_dir

"""``rths-hil evaluate RECORD.csv``: whole-record FEI, J1–J3, TI and moving-window statistics."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from .. import fei as F
from .. import metrics
from ..errors import InputError
from ..records.csvfiles import read_record, write_record
from ..units import parse_window
from .options import add_command


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``evaluate`` to the top-level parser."""
    p = add_command(
        sub,
        "evaluate",
        (
            "Evaluate actuator tracking of a record CSV with columns time,target,measured "
            "(SI units): whole-record FEI (FEI paper, Eq. 2.1–2.5), J1–J3, TI, and the "
            "moving-window FEI with overlap (the FEI paper's Section 3–4)."
        ),
        run,
        help="FEI (whole record and moving windows), J1–J3 and TI of a target/measured record",
    )
    p.add_argument("record", help="record CSV (header with time,target,measured; SI units)")
    p.add_argument(
        "--window",
        default=None,
        help="window length: '3s', '3000ms' or '3T' (natural periods, needs --fn); default 3T "
        "with --fn, else 4s",
    )
    p.add_argument("--fn", type=float, default=None, help="natural frequency (Hz) for 'T' windows")
    p.add_argument("--hop", type=int, default=1, help="samples between windows (1 = MWO, N = MW)")
    p.add_argument("--method", choices=("exact", "streaming"), default="exact")
    p.add_argument("--decimate", type=int, default=1, help="decimation factor before windowing")
    p.add_argument(
        "--pair",
        choices=("target", "command"),
        default="target",
        help="evaluate measured against target (default) or against command",
    )
    p.add_argument(
        "--abs-floor",
        type=float,
        default=F.ABS_FLOOR,
        help=f"window validity floor on target level, m (default {F.ABS_FLOOR:g})",
    )
    p.add_argument(
        "--rel-floor",
        type=float,
        default=F.REL_FLOOR,
        help=f"validity floor relative to the running peak level (default {F.REL_FLOOR:g})",
    )
    p.add_argument("--out", default=None, help="write per-window results to this CSV")
    p.add_argument("--plot", default=None, help="write a Fig. 5.2-style PNG here")


def _stats(values: np.ndarray, valid: np.ndarray) -> tuple[float, float, float, float]:
    v = values[valid]
    if v.size == 0:
        return (math.nan,) * 4
    return float(np.mean(v)), float(np.std(v)), float(np.min(v)), float(np.max(v))


def run(args: argparse.Namespace) -> int:
    """Evaluate a record; print the summary; write the optional CSV and PNG."""
    if args.fn is not None and not (math.isfinite(args.fn) and args.fn > 0):
        raise InputError(f"--fn must be a positive frequency in Hz, got {args.fn}")
    if args.hop < 1:
        raise InputError(f"--hop must be a positive number of samples, got {args.hop}")
    if args.decimate < 1:
        raise InputError(f"--decimate must be a positive integer, got {args.decimate}")
    window_text = args.window or ("3T" if args.fn else "4s")
    window_s = parse_window(window_text, args.fn)
    if window_s <= 0:
        raise InputError(f"--window must be positive, got {window_text!r}")
    for flag, target in (("--out", args.out), ("--plot", args.plot)):
        if target:
            parent = Path(target).expanduser().resolve().parent
            if not parent.is_dir():
                raise InputError(f"{flag} {target}: directory {parent} does not exist")
    ref_col = args.pair
    rec = read_record(
        args.record, required=("time", ref_col, "measured"), optional=(), min_samples=8
    )
    fs = rec.fs
    n_win = round(window_s * fs / args.decimate)
    if n_win > len(rec) // args.decimate:
        raise InputError(
            f"{args.record}: {len(rec)} samples ({len(rec) / fs:.3g} s) is shorter than one "
            f"window of {window_s:g} s"
        )
    x = rec[ref_col]
    y = rec["measured"]
    whole = F.fei(x, y, fs, abs_floor=args.abs_floor)
    res = F.moving_fei(
        x,
        y,
        fs,
        window_s,
        hop=args.hop,
        method=args.method,
        decimate=args.decimate,
        abs_floor=args.abs_floor,
        rel_floor=args.rel_floor,
    )
    j1 = metrics.j1_delay(x, y, fs)
    j2 = metrics.j2_nrms(x, y)
    j3 = metrics.j3_peak(x, y)
    ti = metrics.tracking_indicator(x, y)
    print(f"record      {args.record}: {len(rec)} samples at {fs:g} Hz ({len(rec) / fs:.2f} s)")
    print(f"pair        measured vs {ref_col}")
    if whole.valid:
        print(
            f"FEI         A = {whole.amplitude:.4f}  d = {1e3 * whole.delay:+.3f} ms  "
            f"f_eq = {whole.f_eq:.3f} Hz"
        )
    else:
        print("FEI         invalid: the reference signal has (near) zero variance")
    print(f"J1 = {1e3 * j1:+.3f} ms   J2 = {j2:.3f} %   J3 = {j3:.3f} %   TI = {ti:.4g} m²")
    nvalid = int(res.valid.sum())
    print(
        f"windows     {window_s:g} s ({round(window_s * fs / args.decimate)} samples), "
        f"hop {args.hop}, {args.method}: {len(res)} windows, {nvalid} valid"
    )
    a_mean, a_std, a_min, a_max = _stats(res.amplitude, res.valid)
    d_mean, d_std, d_min, d_max = _stats(res.delay, res.valid)
    print(f"  A         mean {a_mean:.4f}  std {a_std:.4f}  min {a_min:.4f}  max {a_max:.4f}")
    print(
        f"  d (ms)    mean {1e3 * d_mean:+.3f}  std {1e3 * d_std:.3f}  "
        f"min {1e3 * d_min:+.3f}  max {1e3 * d_max:+.3f}"
    )
    t0 = float(rec.time[0])
    try:
        _write_outputs(args, rec, res, whole, x, y, window_s, t0)
    except OSError as exc:
        raise InputError(f"cannot write {exc.filename or 'output'}: {exc.strerror}") from None
    return 0


def _write_outputs(args, rec, res, whole, x, y, window_s: float, t0: float) -> None:
    """Write ``--out`` (per-window CSV) and ``--plot`` (PNG) when asked."""
    if args.out:
        write_record(
            args.out,
            {
                "t_end": res.t_end + t0,
                "amplitude": res.amplitude,
                "phase": res.phase,
                "f_eq": res.f_eq,
                "delay": res.delay,
                "valid": res.valid.astype(float),
                "level": res.level,
            },
        )
        print(f"wrote       {args.out}")
    if args.plot:
        from ..plotting import plot_moving_fei

        plot_moving_fei(
            rec.time,
            x,
            y,
            res,
            args.plot,
            title=f"{Path(args.record).name}: A = {whole.amplitude:.4f}, "
            f"d = {1e3 * whole.delay:+.2f} ms (window {window_s:g} s)",
        )
        print(f"wrote       {args.plot}")

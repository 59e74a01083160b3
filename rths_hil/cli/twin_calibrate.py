"""``rths-hil twin calibrate RECORD.csv --out twin.toml``: fit a twin model to a recorded test.

The record needs ``time`` and ``measured`` and either ``command`` or ``target`` (``command`` is
preferred: it is what the actuator received). The fit (delay, gain, optionally a first-order
servo lag, an offset, the sensor noise and quantisation) is
:func:`rths_hil.estimation.calibrate`; the result is a model file for ``twin serve --model``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from rths_hil.sim_backends.modelfile import dump_model, model_to_toml

from ..errors import InputError
from ..records.csvfiles import read_record, write_record
from ..units import parse_time
from .options import add_command


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``twin calibrate`` to the ``twin`` sub-parsers."""
    p = add_command(
        sub,
        "calibrate",
        __doc__,
        run,
        help="fit a twin model file to a recorded test",
    )
    p.add_argument("record", help="record CSV with time, command or target, measured (m)")
    p.add_argument("--out", help="model file to write (TOML); default: print it")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument(
        "--input-column",
        choices=("command", "target"),
        help="input signal column (default: command if present, else target)",
    )
    p.add_argument("--servo-lag", action="store_true", help="also fit a first-order servo lag")
    p.add_argument("--no-offset", action="store_true", help="do not fit a displacement offset")
    p.add_argument("--max-delay", default="200ms", help="largest delay searched (default 200ms)")
    p.add_argument(
        "--track",
        metavar="CSV",
        help="also run the online Kalman estimator and write its gain/delay history here",
    )


def run(args: argparse.Namespace) -> int:
    """Execute ``twin calibrate``; return the exit code."""
    # here, not at registration: ``twin serve`` shares the parser and does without the
    # estimators' scipy.stats, scipy.signal and filterpy (seconds of its start-up)
    from ..estimation import DelayGainEstimator, calibrate

    max_delay = parse_time(args.max_delay, "--max-delay")
    if max_delay <= 0:
        raise InputError(f"--max-delay: must be > 0, got {args.max_delay!r}")
    out = Path(args.out) if args.out else None
    if out is not None and out.exists() and not args.force:
        raise InputError(f"{out}: exists (use --force to overwrite)")
    rec = read_record(args.record, required=("time", "measured"), optional=("command", "target"))
    column = args.input_column
    if column is None:
        column = "command" if "command" in rec else "target" if "target" in rec else None
    if column is None or column not in rec:
        want = column or "command or target"
        raise InputError(
            f"{args.record}:1: missing column {want} (header has: {', '.join(rec.names)})"
        )
    u = rec[column]
    y = rec["measured"]
    spec, info = calibrate(
        rec.time,
        u,
        y,
        servo_lag=args.servo_lag,
        fit_offset=not args.no_offset,
        delay_range=(0.0, max_delay),
        return_info=True,
    )
    header = (
        f"twin calibrated by rths-hil twin calibrate from {args.record} ({column} → measured)\n"
        f"{len(rec)} samples at {info.fs:.6g} Hz; residual RMS {info.residual_rms:.3g} m "
        f"(NRMSE {100 * info.nrmse:.3g} %)"
    )
    summary = (
        f"gain {info.gain:.5f}, delay {1e3 * info.delay:.3f} ms"
        + (
            f", servo lag {1e3 * info.time_constant:.3f} ms"
            if info.time_constant is not None
            else ""
        )
        + f", offset {1e3 * info.offset:.4f} mm, residual RMS {1e3 * info.residual_rms:.4f} mm"
        + f" (NRMSE {100 * info.nrmse:.3g} %)"
    )
    if args.track:
        hi = max(0.1, max_delay)
        est = DelayGainEstimator(
            info.fs, delay0=min(info.initial_delay, hi), delay_range=(-0.02, hi)
        )
        gains, delays = est.run(u, y)
        write_record(
            args.track,
            {"time": rec.time - est.latency, "gain": gains, "delay": delays},
        )
        tail = slice(len(gains) // 2, None)
        summary += (
            f"\nKalman: final gain {gains[-1]:.5f}, delay {1e3 * delays[-1]:.3f} ms; second half "
            f"delay {1e3 * np.median(delays[tail]):.3f} ms median → {args.track}"
        )
    if out is None:
        sys.stdout.write(model_to_toml(spec, header))
        print(summary, file=sys.stderr)
    else:
        dump_model(spec, out, header)
        print(f"{summary}\nwrote {out}")
    return 0

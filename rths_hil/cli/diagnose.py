"""``rths-hil diagnose RECORD.csv [--model twin.toml] --out DIR``: name what the model misses.

The record has ``time,command,measured`` (SI: s, m, m) and optionally ``target`` and ``force``
(N). The model file is the twin's (``docs/models.md``); without ``--model`` the workflow starts
from a delay + gain model fitted to the record. It simulates the model with the record's
command, localises where the residual leaves its noise band (time, frequency, regime), fits every
effect of the catalogue (and a delay/gain re-fit), names the most significant by BIC, adds it
and repeats (:func:`rths_hil.diagnose.diagnose`, ``docs/diagnose.md``). ``DIR`` receives
``report.json``, the augmented ``model.toml`` and ``diagnose.png``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from rths_hil.sim_backends.modelfile import load_model

from ..diagnose import (
    CANDIDATES,
    DEFAULT_THRESHOLD,
    diagnose,
    summary_lines,
    write_outputs,
)
from ..errors import InputError
from ..records.csvfiles import read_record
from .options import add_command


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer ≥ 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be an integer ≥ 0, got {text!r}")
    return v


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``diagnose`` sub-command."""
    p = add_command(
        sub,
        "diagnose",
        __doc__,
        run,
        help="find where the twin and a record disagree, name and add the missing effect",
    )
    p.add_argument("record", help="record CSV: time, command, measured (m) [, target, force (N)]")
    p.add_argument("--model", help="base model file (TOML); default: delay + gain fitted to it")
    p.add_argument(
        "--max-effects",
        type=_positive_int,
        default=3,
        help="name at most this many effects (default 3)",
    )
    p.add_argument("--out", required=True, help="output directory (created if needed)")
    p.add_argument(
        "--threshold",
        default=str(DEFAULT_THRESHOLD),
        help=f"BIC improvement a candidate needs to be named (default {DEFAULT_THRESHOLD:g})",
    )
    p.add_argument(
        "--candidates",
        default=None,
        help=f"comma-separated subset of: {', '.join(CANDIDATES)} (default: all)",
    )
    p.add_argument("--no-plot", action="store_true", help="do not write diagnose.png")


def run(args: argparse.Namespace) -> int:
    """Execute ``diagnose``; return the exit code."""
    try:
        threshold = float(args.threshold)
    except ValueError:
        raise InputError(f"--threshold: not a number: {args.threshold!r}") from None
    if not (math.isfinite(threshold) and threshold >= 0):
        raise InputError(f"--threshold: must be a finite number ≥ 0, got {args.threshold!r}")
    candidates = CANDIDATES
    if args.candidates:
        candidates = tuple(c.strip() for c in args.candidates.split(",") if c.strip())
        bad = [c for c in candidates if c not in CANDIDATES]
        if bad or not candidates:
            raise InputError(
                f"--candidates: unknown candidate {bad[0] if bad else ''!r} "
                f"(known: {', '.join(CANDIDATES)})"
            )
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} exists and is not a directory")
    model = load_model(args.model) if args.model else None
    rec = read_record(
        args.record, required=("time", "command", "measured"), optional=("target", "force")
    )
    force = rec["force"] if "force" in rec else None
    try:
        dx = diagnose(
            rec.time,
            rec["command"],
            rec["measured"],
            force,
            model=model,
            max_effects=args.max_effects,
            threshold=threshold,
            candidates=candidates,
        )
    except InputError as exc:
        raise InputError(f"{args.record}: {exc}") from None
    paths = write_outputs(dx, out, record=args.record, plot=not args.no_plot)
    for line in summary_lines(dx, str(paths["model"])):
        print(line)
    written = ", ".join(str(p) for k, p in paths.items() if k != "model")
    print(f"wrote {written} ({dx.runtime_s:.1f} s)")
    return 0

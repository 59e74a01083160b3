"""``rths-hil tune``: tune the inverse compensation (α, amplitude factor) from trial tests.

``rths-hil tune [CONFIG.toml] [--set key=value]... [--tolerance-delay 1ms]
[--tolerance-amplitude 1%] [--max-iterations 6] [--sweep 10:50:5] [--trial-duration 15s]
[--alpha-only] [--out DIR] [--confirm-hardware] [--hardware-scale 25%]``

Runs short trial tests of the configured RTHS (lockstep against the configured twin; paced
against real hardware, only after the operator's explicit confirmation and at a reduced
amplitude), evaluates the FEI of each (the FEI paper's Eq. 2.1–2.5) and updates ``α ← α + d/Δt`` and
the amplitude factor ``a ← a/A`` until ``|d|`` and ``|A − 1|`` are within tolerance, or says why it
stopped (see :mod:`rths_hil.tuning`). ``--sweep START:STOP:STEP`` (stop exclusive) runs the α
grid instead and recommends the zero crossing of d(α).

Writes to ``--out`` (default ``runs/tune-<timestamp>``): one run directory per trial,
``tuning.csv``/``sweep.csv`` (the table), ``tuning.png``/``sweep.png`` (d and A against
iteration or α), ``tuned.toml`` (the configuration with the recommended α and factor) and
``summary.json``. Exit codes: 0 converged (sweep: zero crossing found), 1 stopped without
converging (the reason is printed), 2 bad input or no confirmation for hardware, 3 a trial was
stopped by a safety rule, 130 operator stop.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError
from ..formats import json_text
from ..units import parse_fraction, parse_range, parse_time
from .options import (
    add_command,
    add_config_arguments,
    add_confirm_hardware,
    add_out_dir,
    config_from_args,
    out_dir,
)

if TYPE_CHECKING:
    from ..config import Config
    from ..tuning import SweepResult, TuneResult


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``tune`` to the top-level parser."""
    p = add_command(
        sub,
        "tune",
        __doc__,
        main,
        help="tune inverse compensation (α, amplitude factor) from trial tests or an α sweep",
    )
    add_config_arguments(p, "compensation.alpha=15")
    p.add_argument(
        "--tolerance-delay", default="1ms", metavar="T", help="tolerance on |d| (default 1ms)"
    )
    p.add_argument(
        "--tolerance-amplitude",
        default="1%",
        metavar="F",
        help="tolerance on |A - 1| (default 1%%)",
    )
    p.add_argument(
        "--max-iterations", type=int, default=6, metavar="N", help="most trials (default 6)"
    )
    p.add_argument(
        "--sweep",
        metavar="START:STOP:STEP",
        help="run an α grid instead (stop exclusive, or a,b,c) and recommend the zero crossing",
    )
    p.add_argument(
        "--trial-duration",
        default="15s",
        metavar="S",
        help="seconds of the record per trial (default 15s; 0 = loop.duration)",
    )
    p.add_argument(
        "--alpha-only", action="store_true", help="tune α only (keep the amplitude factor)"
    )
    add_out_dir(p, "output", "runs/tune-{timestamp}")
    p.add_argument(
        "--paced",
        action="store_true",
        help="run twin trials in real time (default lockstep; hardware trials are always paced)",
    )
    add_confirm_hardware(p, "the trials")
    p.add_argument(
        "--hardware-scale",
        default="25%",
        metavar="F",
        help="ground-motion scale of hardware trials, fraction of the configured PGA "
        "(default 25%%)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="local|ADDRESS",
        help="run the --sweep trials in parallel on Dask: 'local' (two worker processes on "
        "127.0.0.1) or a scheduler address, e.g. tcp://host:8786 (twin only)",
    )
    p.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the result line")


def _confirm(n_trials: int, pga: float, scale: float, cfg, flag: bool) -> None:
    """Refuse hardware trials unless the operator confirmed (flag or typed 'yes')."""
    what = (
        f"{n_trials} trial test(s) on the REAL actuator through driver "
        f"{cfg['driver']['name']!r} at {100 * scale:g} % of the configured ground motion "
        f"(PGA {pga:.4g} m/s²)"
    )
    if flag:
        print(f"rths-hil tune: confirmed: {what}", file=sys.stderr)
        return
    if sys.stdin is not None and sys.stdin.isatty():
        print(f"rths-hil tune: about to run {what}.", file=sys.stderr)
        try:
            answer = input("Type 'yes' to start: ")
        except EOFError:
            answer = ""
        if answer.strip().lower() == "yes":
            return
        raise InputError("hardware trials not confirmed by the operator; nothing was run")
    raise InputError(
        "the configuration drives real hardware (twin.enabled = false): refusing to run "
        "trials without the operator's confirmation; pass --confirm-hardware (or run "
        "interactively and answer the prompt)"
    )


def _checked_options(
    args: argparse.Namespace, cfg: Config
) -> tuple[float, float, float, list[float] | None, bool, float]:
    """The checked numbers of the command line: delay and amplitude tolerances, trial
    duration, the ``--sweep`` grid (None: tune), whether a channel is on hardware, and the
    hardware trials' scale."""
    tol_d = parse_time(args.tolerance_delay, "--tolerance-delay")
    tol_a = parse_fraction(args.tolerance_amplitude, "--tolerance-amplitude")
    if not (math.isfinite(tol_d) and tol_d > 0):
        raise InputError(f"--tolerance-delay must be > 0, got {args.tolerance_delay!r}")
    if not (math.isfinite(tol_a) and tol_a > 0):
        raise InputError(f"--tolerance-amplitude must be > 0, got {args.tolerance_amplitude!r}")
    if args.max_iterations < 1:
        raise InputError(f"--max-iterations must be ≥ 1, got {args.max_iterations}")
    duration = parse_time(args.trial_duration, "--trial-duration")
    if not (math.isfinite(duration) and duration >= 0):
        raise InputError(f"--trial-duration must be ≥ 0 s, got {args.trial_duration!r}")
    grid = parse_range(args.sweep, "--sweep") if args.sweep else None
    if grid is not None and any(not (math.isfinite(a) and a >= 1) for a in grid):
        raise InputError(f"--sweep: every α must be ≥ 1, got {args.sweep!r}")
    hardware = any(not ch.config["twin"]["enabled"] for ch in cfg.channels())
    if args.scheduler is not None and grid is None:
        raise InputError("--scheduler runs the trials of a --sweep in parallel; give --sweep")
    if args.scheduler is not None and hardware:
        raise InputError("--scheduler: hardware trials share one actuator and run one by one")
    scale = 1.0
    if hardware:
        scale = parse_fraction(args.hardware_scale, "--hardware-scale")
        if not (math.isfinite(scale) and 0 < scale <= 1):
            raise InputError(f"--hardware-scale must be in (0, 1], got {args.hardware_scale!r}")
    return tol_d, tol_a, duration, grid, hardware, scale


def _finish_sweep(
    res: SweepResult,
    cfg: Config,
    out: Path,
    summary: dict,
    no_plot: bool,
    tol_d: float,
    tol_a: float,
) -> int:
    """Write the sweep's table, tuned configuration, figure and summary; its exit code."""
    from ..tuning_output import plot_sweep, write_table_csv, write_tuned_config

    write_table_csv(res.trials, out / "sweep.csv")
    summary["sweep"] = res.as_dict()
    if res.found:
        write_tuned_config(
            cfg, out / "tuned.toml", res.alpha, res.factor, note=f"sweep: {res.reason}"
        )
    if not no_plot:
        plot_sweep(res, out / "sweep.png", tol_d, tol_a)
    (out / "summary.json").write_text(json_text(summary), encoding="utf-8")
    if res.found:
        print(
            f"recommended α = {res.alpha:.2f} (zero crossing of d(α)), amplitude factor "
            f"{res.factor:.4f}; {res.reason}; tuned config {out / 'tuned.toml'}"
        )
    else:
        print(f"rths-hil tune: no recommendation: {res.reason}", file=sys.stderr)
    stopped = [t for t in res.trials if t.status == "operator_stop"]
    if stopped:
        return 130
    return 0 if res.found else 1


def _finish_tune(
    res: TuneResult, cfg: Config, out: Path, summary: dict, no_plot: bool, quiet: bool
) -> int:
    """Write the tuning's table, tuned configuration, figure and summary; its exit code."""
    from ..tuning_output import plot_tuning, write_table_csv, write_tuned_config

    write_table_csv(res.trials, out / "tuning.csv")
    summary["tuning"] = res.as_dict()
    if res.best:
        write_tuned_config(
            cfg,
            out / "tuned.toml",
            res.alpha,
            res.factor,
            note=f"{res.stop}: {res.reason}\nbest verified trial: {res.best}",
        )
    if not no_plot and res.trials:
        plot_tuning(res, out / "tuning.png")
    (out / "summary.json").write_text(json_text(summary), encoding="utf-8")
    if not quiet:
        print(f"rths-hil tune: {res.reason}", file=sys.stderr)
    if res.best:
        print(
            f"{'tuned' if res.converged else 'best so far'}: α = {res.alpha:.3f}, amplitude "
            f"factor {res.factor:.4f} (trial {res.best} of {res.iterations}); "
            f"config {out / 'tuned.toml'}"
        )
    else:
        print(f"rths-hil tune: no usable trial: {res.reason}", file=sys.stderr)
    if res.stop == "trip":
        return 3
    if res.stop == "operator_stop":
        return 130
    return 0 if res.converged else 1


def main(args: argparse.Namespace) -> int:
    """Run the tuning (or the sweep); return the exit code."""
    from ..tuning import LoopTrials, sweep, tune
    from ..tuning_output import format_table

    cfg = config_from_args(args)
    tol_d, tol_a, duration, grid, hardware, scale = _checked_options(args, cfg)
    c = cfg["compensation"]
    lo, hi = c["alpha_min"], c["alpha_max"]
    if grid is None and not (lo <= c["alpha"] <= hi):
        raise InputError(
            f"compensation.alpha = {c['alpha']:g} is outside [alpha_min, alpha_max] = "
            f"[{lo:g}, {hi:g}]"
        )
    out = out_dir(args, empty=True)
    mode = "paced" if (hardware or args.paced) else "lockstep"
    quiet = args.quiet

    def on_trial(t) -> None:
        if quiet:
            return
        row = format_table([t]).splitlines()[-1]
        print(row, flush=True)

    runner = LoopTrials(
        cfg,
        out,
        duration=duration,
        scale=scale,
        mode=mode,
        prefix="sweep" if grid is not None else "trial",
        on_trial=on_trial,
    )
    if hardware:
        _confirm(
            len(grid) if grid else args.max_iterations,
            runner.pga,
            scale,
            cfg,
            args.confirm_hardware or cfg["loop"]["confirm_hardware"],
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output directory {out}: {exc.strerror}") from None
    trial_s = runner.duration if runner.duration > 0 else math.nan
    if not quiet:
        target = "hardware" if hardware else "twin"
        what = f"sweep of {len(grid)} α" if grid else f"up to {args.max_iterations} trials"
        print(
            f"rths-hil tune: {what}, {trial_s:g} s each, {mode} on the {target}, "
            f"PGA {runner.pga:.4g} m/s², Δt = {runner.dt * 1e3:.4f} ms; output in {out}",
            file=sys.stderr,
        )
        print(format_table([]), flush=True)

    summary: dict = {
        "config": cfg.source,
        "overrides": list(args.set),
        "hardware": hardware,
        "mode": mode,
        "trial_duration": runner.duration,
        "pga": runner.pga,
        "dt": runner.dt,
        "tolerance_delay": tol_d,
        "tolerance_amplitude": tol_a,
    }
    if grid is not None and args.scheduler is not None:
        res = _parallel_sweep(runner, grid, c["amplitude"], args.scheduler, on_trial)
    elif grid is not None:
        res = sweep(runner, grid, factor=c["amplitude"], stop_on_trip=hardware)
    if grid is not None:
        return _finish_sweep(res, cfg, out, summary, args.no_plot, tol_d, tol_a)

    res = tune(
        runner,
        alpha0=c["alpha"],
        dt=runner.dt,
        factor0=c["amplitude"],
        tol_delay=tol_d,
        tol_amplitude=tol_a,
        max_iterations=args.max_iterations,
        tune_amplitude=not args.alpha_only,
        alpha_bounds=(lo, hi),
    )
    return _finish_tune(res, cfg, out, summary, args.no_plot, quiet)


def _parallel_sweep(runner, grid: list[float], factor: float, scheduler: str, on_trial):
    """The sweep's twin trials submitted at once to a Dask executor, evaluated in grid order.

    The trials run where the workers are (their run directories are written there: give an
    absolute ``--out`` on a shared file system for a remote cluster); the table rows are
    printed here as the results arrive in order.
    """
    import copy

    from ..studies import open_executor
    from ..tuning import Trial, sweep

    remote = copy.copy(runner)
    remote.on_trial = None  # printing happens here, not on the workers
    remote.out_dir = runner.out_dir.resolve()
    with open_executor(scheduler, 2) as ex:
        futures = {i: ex.submit(remote, a, factor, i) for i, a in enumerate(grid, 1)}

        def run_trial(alpha: float, factor: float, index: int) -> Trial:
            trial = futures[index].result()
            on_trial(trial)
            return trial

        return sweep(run_trial, grid, factor=factor, stop_on_trip=False)

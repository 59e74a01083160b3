"""``rths-hil study``: the FEI paper's computational study (Section 4) and robustness studies.

* ``study window-size``: smallest moving window meeting a delay-error criterion for each record
  and natural frequency (the FEI paper's Fig. 4.2); writes ``window_size.csv`` and
  ``window_size.png``.
* ``study accuracy``: maximum amplitude and delay errors of the moving-window FEI for linear and
  Bouc-Wen structures (Table 4.1, Fig. 4.6); writes ``accuracy.csv`` and ``accuracy.png``.
* ``study robustness CONFIG``: perturbed twins run in lockstep through the full chain; writes
  ``trials.csv``, ``summary.csv``, ``summary.json`` and plots (``docs/studies.md``).

The first two run their cases on a process pool (``--workers``, default 2) or, with
``--scheduler local|ADDRESS``, on Dask; ``robustness`` runs on Dask (default a local cluster on
127.0.0.1). All show a progress bar on stderr. The window-size and accuracy procedures are
described in ``docs/simulation.md``.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import InputError
from ..records.columns import column_name
from ..resources import MAX_TRIALS, check_count, check_memory, max_workers
from ..stopping import interrupting
from ..units import parse_fraction, parse_range, parse_time, positive_number
from .options import add_ground_motion_argument, add_simulation_arguments, simulation_from_args


def _check_workers(workers: int) -> None:
    """Refuse fewer than one worker or more than the machine can hold (before starting any)."""
    if workers < 1:
        raise InputError(f"--workers must be ≥ 1, got {workers}")
    check_count(
        workers,
        max_workers(),
        "--workers",
        f"four processes per CPU; this machine has {os.cpu_count() or 1}",
    )


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``study window-size`` and ``study accuracy``."""
    parser = sub.add_parser(
        "study", help="the FEI paper's window-size and accuracy studies (Section 4), robustness"
    )
    st = parser.add_subparsers(dest="study_command", metavar="STUDY")

    def common(p: argparse.ArgumentParser, gain: str, delay: str) -> None:
        add_simulation_arguments(p, gain, delay)
        p.add_argument(
            "--min-level",
            default="0.1",
            help="count windows whose target level is ≥ this fraction of the record's largest "
            "(default 0.1; 0 counts every valid window)",
        )
        p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
        p.add_argument(
            "--scheduler",
            default=None,
            metavar="local|ADDRESS",
            help="run the cases on Dask: 'local' (a cluster of --workers processes on "
            "127.0.0.1) or a scheduler address, e.g. tcp://host:8786 (default: a local "
            "process pool)",
        )
        p.add_argument("--no-progress", action="store_true", help="no progress bar")
        p.add_argument("--out", required=True, help="output directory (created if missing)")

    ws = st.add_parser(
        "window-size",
        help="window size needed per natural frequency (the FEI paper's Fig. 4.2)",
        description=(
            "FEI paper, Fig. 4.2: t_w from 1·Tn upwards by 0.1·Tn until the criterion holds."
        ),
    )
    add_ground_motion_argument(ws, "all bundled", several=True)
    ws.add_argument("--fn", default="0.2:5.1:0.1", help="frequencies start:stop:step or a,b,c (Hz)")
    ws.add_argument("--criterion", default="1%", help="tolerance on |d − τ|/τ (default 1%%)")
    ws.add_argument(
        "--statistic",
        default="p95",
        help="statistic of the window errors: max or pNN percentile (default p95)",
    )
    ws.add_argument("--bouc-wen", action="store_true", help="Bouc-Wen structure (Eq. 4.1-4.2)")
    ws.add_argument("--max-periods", default="10", help="largest window tried, in Tn (default 10)")
    common(ws, "1", "1ms")
    ws.set_defaults(func=_stoppable(run_window_size))

    acc = st.add_parser(
        "accuracy",
        help="max FEI errors, linear and Bouc-Wen (the FEI paper's Table 4.1, Fig. 4.6)",
        description="The FEI paper's Table 4.1 / Fig. 4.6 for linear and Bouc-Wen SDOF structures.",
    )
    add_ground_motion_argument(acc, "bundled El Centro 1940", several=False)
    acc.add_argument("--fn", default="0.5,0.7,1.0", help="frequencies a,b,c (Hz)")
    acc.add_argument("--window", default="3T", help="window: 3T (periods) or seconds (3s)")
    acc.add_argument("--hop", type=int, default=1, help="samples between windows (default 1)")
    common(acc, "1.1", "5ms")
    acc.set_defaults(func=_stoppable(run_accuracy))

    rb = st.add_parser(
        "robustness",
        help="perturbed-twin trials in lockstep: J1–J9, FEI, trips (docs/studies.md)",
        description="Draw perturbed twins over the named keys, run each in lockstep through the "
        "full chain on Dask, collect J1–J9 (paper and benchmark script), the whole-record FEI, "
        "the MWO extremes and the safety trips; write trials.csv, summary.csv and plots.",
    )
    _trial_arguments(
        rb,
        trials=200,
        vary_help="vary a key uniformly (or normally, ±2σ = LOW:HIGH), e.g. "
        "twin.actuator.delay=15ms:35ms (repeatable; default: benchmark-style spreads)",
    )
    rb.add_argument(
        "--alpha",
        default=None,
        metavar="A,B,C",
        help="run every twin with each α (e.g. 15,20,29) and chart robustness against α",
    )
    rb.set_defaults(func=run_robustness)

    cp = st.add_parser(
        "compensators",
        help="every compensator on the same perturbed twins: J1–J9, FEI, trips "
        "(docs/compensation.md)",
        description="Draw perturbed twins as the robustness study does, run every method on "
        "every draw in lockstep, compare J1–J9 (paper and benchmark script), the whole-record "
        "FEI and the trips; write trials.csv, comparison.csv, comparison.md and box plots.",
    )
    _trial_arguments(
        cp,
        trials=100,
        vary_help="vary a key as in study robustness (repeatable; default: benchmark-style "
        "spreads)",
    )
    cp.add_argument(
        "--methods",
        default="inverse,polynomial,ats,model",
        metavar="A,B",
        help="compensators to compare (default inverse,polynomial,ats,model)",
    )
    cp.set_defaults(func=run_compensators)
    parser.set_defaults(func=lambda args: _no_study(parser))


def _trial_arguments(p: argparse.ArgumentParser, trials: int, vary_help: str) -> None:
    """The arguments of the studies over perturbed twins (robustness, compensators)."""
    p.add_argument("config", metavar="CONFIG", help="TOML configuration of the test (a twin)")
    p.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override a configuration key before drawing (repeatable)",
    )
    p.add_argument("--trials", type=int, default=trials, help=f"perturbed twins (default {trials})")
    p.add_argument(
        "--vary", metavar="KEY=LOW:HIGH[:normal]", action="append", default=None, help=vary_help
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    p.add_argument(
        "--scheduler",
        default="local",
        metavar="local|ADDRESS",
        help="'local' (default: a Dask cluster of --workers processes on 127.0.0.1) or a "
        "Dask scheduler address, e.g. tcp://host:8786",
    )
    p.add_argument(
        "--workers", type=int, default=2, help="worker processes of a local cluster (default 2)"
    )
    p.add_argument(
        "--duration", default=None, help="seconds of the record per trial (default: the config's)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-plot", action="store_true", help="do not write the PNGs")
    p.add_argument("--out", required=True, help="output directory (created if missing)")


def _stoppable(run):
    """``run(args)`` with SIGTERM and SIGHUP taken as Ctrl-C (exit 130, not 143 or 129)."""

    def wrapped(args: argparse.Namespace) -> int:
        with interrupting():
            return run(args)

    wrapped.__doc__ = run.__doc__
    return wrapped


def _signal(got: list[str]) -> str:
    """The stop signal's name (Ctrl-C when it came as a KeyboardInterrupt of its own)."""
    return got[0] if got else "SIGINT"


def _no_study(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def _fns(text: str) -> list[float]:
    fns = parse_range(text, "--fn")
    if not fns:
        raise InputError(f"--fn {text!r}: no frequencies")
    for f in fns:
        if not (math.isfinite(f) and f > 0):
            raise InputError(f"--fn: natural frequencies must be > 0 Hz, got {f:g}")
    return fns


def _common(args: argparse.Namespace) -> dict:
    sim = simulation_from_args(args)
    if sim.delay == 0:
        raise InputError(f"--delay must be > 0 (errors are relative to it), got {args.delay}")
    min_level = parse_fraction(args.min_level, "--min-level")
    if not 0 <= min_level < 1:
        raise InputError(f"--min-level must lie in [0, 1), got {args.min_level}")
    _check_workers(args.workers)
    return {**sim._asdict(), "min_level": min_level}


def _records(specs: list[str] | None, fs: float, pga: float | None):
    from ..groundmotion import bundled_records, default_record, load, resolve

    if specs is None:
        gms = [load(p) for p in bundled_records()]
    elif specs == ["default"]:
        gms = [default_record()]
    else:
        gms = [resolve(s) for s in specs]
    out = []
    for gm in gms:
        gm = gm.resampled(fs)
        out.append(gm.scaled(pga) if pga is not None else gm)
    return out


def _paper_study(args: argparse.Namespace, c: dict, run: Callable[..., Any], *pos, **kw) -> Any:
    """``run(*pos, **kw)``, a study of the FEI paper: its cases on the executor of
    ``--scheduler`` and ``--workers``, the structure's ζ and the actuator's gain and delay
    from ``c`` (:func:`_common`)."""
    from .. import studies as study

    with study.open_executor(args.scheduler, args.workers) as ex:
        return run(
            *pos,
            **kw,
            executor=ex,
            progress=not args.no_progress,
            zeta=c["zeta"],
            gain=c["gain"],
            delay=c["delay"],
        )


def _outdir(text: str) -> Path:
    out = Path(text)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: cannot create directory {text!r} ({exc.strerror})") from None
    return out


def run_window_size(args: argparse.Namespace) -> int:
    """``study window-size``."""
    from .. import studies as study

    c = _common(args)
    fns = _fns(args.fn)
    crit = study.WindowCriterion(
        tolerance=parse_fraction(args.criterion, "--criterion"),
        statistic=args.statistic,
        min_level=c["min_level"],
    )
    max_periods = positive_number(args.max_periods, "--max-periods")
    if max_periods < 1:
        raise InputError(f"--max-periods must be ≥ 1, got {args.max_periods}")
    for f in fns:
        if f >= c["fs"] / 2:
            raise InputError(f"--fn {f:g} Hz is not below the Nyquist frequency")
    gms = _records(args.record, c["fs"], c["pga"])
    for gm in gms:
        if 1.0 / min(fns) > 0.5 * gm.duration:
            raise InputError(
                f"record {gm.name!r} ({gm.duration:g} s) is shorter than two periods of "
                f"{min(fns):g} Hz: the window search cannot start"
            )
    out = _outdir(args.out)
    rows = _paper_study(
        args,
        c,
        study.window_size_study,
        gms,
        fns,
        criterion=crit,
        bouc_wen=True if args.bouc_wen else None,
        max_periods=max_periods,
    )
    study.write_window_size_csv(out / "window_size.csv", rows)
    study.plot_window_size(out / "window_size.png", rows)
    print(f"{'record':<34}{'fn (Hz)':>8}{'t_w (s)':>9}{'t_w/Tn':>8}{'err %':>8}")
    for r in rows:
        print(
            f"{r.record[:33]:<34}{r.fn_hz:>8.3g}{r.window_s:>9.3g}{r.window_periods:>8.3g}"
            f"{r.delay_error_pct:>8.3f}"
        )
    failed = sum(math.isnan(r.window_s) for r in rows)
    print(
        f"wrote {out / 'window_size.csv'} and {out / 'window_size.png'} "
        f"({len(rows)} cases, {failed} without a passing window up to {max_periods:g}·Tn)"
    )
    return 0


_WINDOW_T = re.compile(r"^\s*([0-9.eE+-]+)\s*T\s*$")


def run_accuracy(args: argparse.Namespace) -> int:
    """``study accuracy``."""
    from .. import studies as study

    c = _common(args)
    fns = _fns(args.fn)
    m = _WINDOW_T.match(args.window)
    if m:
        periods = positive_number(m.group(1), "--window")
        window_s = None
    else:
        periods = None
        window_s = parse_time(args.window, "--window")
        if not (math.isfinite(window_s) and window_s > 0):
            raise InputError(f"--window must be > 0, got {args.window}")
    if args.hop < 1:
        raise InputError(f"--hop must be ≥ 1, got {args.hop}")
    for f in fns:
        if f >= c["fs"] / 2:
            raise InputError(f"--fn {f:g} Hz is not below the Nyquist frequency")
    gm = _records(["default"] if args.record is None else [args.record], c["fs"], c["pga"])[0]
    out = _outdir(args.out)
    rows = _paper_study(
        args,
        c,
        study.accuracy_study,
        gm,
        fns,
        window_periods=periods,
        window_s=window_s,
        hop=args.hop,
        min_level=c["min_level"],
    )
    study.write_accuracy_csv(out / "accuracy.csv", rows)
    study.plot_accuracy(out / "accuracy.png", rows, c["gain"], c["delay"])
    print(
        f"record {gm.name}, PGA {gm.pga:.4g} m/s², gain {c['gain']:g}, "
        f"delay {c['delay'] * 1e3:g} ms"
    )
    print(
        f"{'fn (Hz)':>8}{'structure':>10}{'t_w (s)':>9}{'A err %':>9}{'d err %':>9}{'peak mm':>9}"
    )
    for r in rows:
        print(
            f"{r.fn_hz:>8.3g}{r.structure:>10}{r.window_s:>9.3g}{r.max_err_amplitude_pct:>9.3f}"
            f"{r.max_err_delay_pct:>9.3f}{1e3 * r.peak_displacement_m:>9.2f}"
        )
    print(f"wrote {out / 'accuracy.csv'} and {out / 'accuracy.png'}")
    return 0


def _trial_inputs(args: argparse.Namespace) -> tuple[Any, Any, list, float | None]:
    """A study over perturbed twins: the configuration, its inline twin, the perturbations and
    the duration per trial (``None``: the configuration's), every argument checked."""
    from .. import studies as study
    from ..config import load_config

    cfg = load_config(args.config, args.set)
    base = study.inline_twin(cfg)
    if args.trials < 1:
        raise InputError(f"--trials must be ≥ 1, got {args.trials}")
    check_count(args.trials, MAX_TRIALS, "--trials", "each trial is a whole lockstep run")
    _check_workers(args.workers)
    if args.seed < 0:
        raise InputError(f"--seed must be an integer ≥ 0, got {args.seed}")
    if args.vary:
        perts = [study.parse_vary(text, base) for text in args.vary]
    else:
        perts = study.default_perturbations(base)
    duration = None
    if args.duration is not None:
        duration = parse_time(args.duration, "--duration")
        if not (math.isfinite(duration) and duration > 0):
            raise InputError(f"--duration must be > 0 s, got {args.duration!r}")
        fs = float(cfg["loop"]["fs"])
        check_memory(
            4 * 8 * duration * fs * min(args.workers, args.trials),
            f"--duration {duration:g} s at {fs:g} Hz on {min(args.workers, args.trials)} workers",
        )
    return cfg, base, perts, duration


def _study_dir(
    args: argparse.Namespace, base: Any, duration: float | None, name: str, runs: str, perts: list
) -> Path:
    """The checked output directory of a study over perturbed twins (after its preflight);
    says on stderr what runs (``runs``) where."""
    import sys

    from .. import studies as study

    study.preflight(base, duration)
    out = _outdir(args.out)
    if (out / "trials.csv").exists():
        raise InputError(f"--out {out}: already holds a study (trials.csv); choose a new one")
    if args.scheduler is not None:  # before anything starts
        from ..errors import require

        require("studies", f"a Dask scheduler (--scheduler, study {name})")
    where = "a local Dask cluster" if args.scheduler == "local" else args.scheduler
    print(
        f"rths-hil study {name}: {runs} on {where}; varying " + ", ".join(p.text for p in perts),
        file=sys.stderr,
    )
    return out


def _run_trials(
    args: argparse.Namespace,
    name: str,
    total: int,
    partial: Callable[[list[dict], Path], None],
    out: Path,
    run: Callable[..., Any],
    *pos: Any,
    **kw: Any,
) -> tuple[Any, float] | None:
    """``run(*pos, **kw)`` on the study's executor (with ``seed``, ``executor``, ``progress``
    and ``on_row`` from ``args``): its result and wall time (s).

    An operator stop (Ctrl-C, SIGTERM, SIGHUP) writes the runs that finished with
    ``partial(rows, out / "trials.partial.csv")``, says so and returns None (exit 130).
    """
    import sys
    import time

    from .. import studies as study

    t0 = time.perf_counter()
    done: list[dict] = []
    got: list[str] = []
    try:
        with interrupting() as got, study.open_executor(args.scheduler, args.workers) as ex:
            res = run(
                *pos,
                **kw,
                seed=args.seed,
                executor=ex,
                progress=not args.no_progress,
                on_row=done.append,
            )
    except KeyboardInterrupt:
        partial(done, out / "trials.partial.csv")
        print(
            f"rths-hil study {name}: operator stop ({_signal(got)}); the {len(done)} of "
            f"{total} runs that finished are in {out / 'trials.partial.csv'}",
            file=sys.stderr,
        )
        return None
    return res, time.perf_counter() - t0


def run_robustness(args: argparse.Namespace) -> int:
    """``study robustness``."""
    import json

    from .. import studies as study

    cfg, base, perts, duration = _trial_inputs(args)
    alphas = None
    if args.alpha is not None:
        alphas = parse_range(args.alpha, "--alpha")
        if not alphas:
            raise InputError(f"--alpha {args.alpha!r}: no values")
    specs = study.plan_trials(base, perts, args.trials, args.seed, alphas, duration)
    runs = f"{args.trials} twins × {len({s.alpha for s in specs})} α = {len(specs)} lockstep runs"
    out = _study_dir(args, base, duration, "robustness", runs, perts)

    def partial(done: list[dict], path: Path) -> None:
        order = {a: i for i, a in enumerate(dict.fromkeys(s.alpha for s in specs))}
        done.sort(key=lambda r: (order.get(r["alpha"], 0), r["trial"]))
        suffixes = study.channel_suffixes(base)
        res = study.RobustnessResult(
            done, perts, list(order), args.seed, [p.key for p in perts], suffixes
        )
        study.write_trials_csv(path, res)

    ran = _run_trials(
        args,
        "robustness",
        len(specs),
        partial,
        out,
        study.robustness_study,
        base,
        perts,
        args.trials,
        alphas=alphas,
        duration=duration,
    )
    if ran is None:
        return 130
    res, wall = ran
    study.write_trials_csv(out / "trials.csv", res)
    study.write_summary(out / "summary.csv", res)
    summary = {
        "config": cfg.source,
        "overrides": list(args.set),
        "trials": args.trials,
        "seed": args.seed,
        "alphas": res.alphas,
        "perturbations": [vars(p) for p in perts],
        "duration": duration,
        "scheduler": args.scheduler,
        "wall_time_s": wall,
        "summary": res.summary(),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    written = ["trials.csv", "summary.csv", "summary.json"]
    if not args.no_plot:
        written += [p.name for p in study.plot_robustness(out, res)]
    multi = res.suffixes != [""]
    print(
        f"{'alpha':>6} {'channel':>10} " * multi
        + f"{'alpha':>6} " * (not multi)
        + f"{'tripped':>8} {'d median (ms)':>14} {'d 5-95 % (ms)':>18} "
        f"{'J2 median':>10} {'J2 95 %':>8}"
    )
    for a in res.alphas:
        s = {r["metric"]: r for r in res.summary() if r["alpha"] == a}
        for ch in (sfx[1:] for sfx in res.suffixes):  # the channel of suffix ``_<ch>``
            d, j2 = s[column_name("fei_delay", ch)], s[column_name("J2", ch)]
            rows = res.by_alpha(a)
            a_ch = rows[0].get(column_name("alpha", ch), a) if rows else a  # the channel's own α
            head = f"{a_ch:>6g} {ch:>10} " if multi else f"{a:>6g} "
            print(
                f"{head}{100 * d['share_tripped']:>7.1f}% {1e3 * d['median']:>14.2f} "
                f"{1e3 * d['p5']:>8.2f} … {1e3 * d['p95']:<7.2f} {j2['median']:>10.2f} "
                f"{j2['p95']:>8.2f}"
            )
    print(f"wrote {', '.join(written)} to {out} ({len(res.rows)} runs in {wall:.1f} s)")
    return 0


def run_compensators(args: argparse.Namespace) -> int:
    """``study compensators``."""

    from .. import studies as study
    from ..studies import compensators as cs

    _, base, perts, duration = _trial_inputs(args)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    cases = cs.plan_method_trials(base, methods, perts, args.trials, args.seed, duration)
    runs = f"{args.trials} twins × {len(methods)} methods = {len(cases)} lockstep runs"
    out = _study_dir(args, base, duration, "compensators", runs, perts)

    def partial(done: list[dict], path: Path) -> None:
        done.sort(key=lambda r: (methods.index(r["method"]), r["trial"]))
        suffixes = study.channel_suffixes(base)
        res = cs.CompensatorComparison(done, methods, [p.key for p in perts], suffixes, args.seed)
        study.write_trials_csv(path, res)

    ran = _run_trials(
        args,
        "compensators",
        len(cases),
        partial,
        out,
        cs.compensator_study,
        base,
        methods,
        perts,
        args.trials,
        duration=duration,
    )
    if ran is None:
        return 130
    res, wall = ran
    written = cs.write_comparison(out, res, plot=not args.no_plot)
    summ = {(r["method"], r["metric"]): r for r in res.summary()}
    for ch in (sfx[1:] for sfx in res.suffixes):  # the channel of suffix ``_<ch>``
        if ch:
            print(f"channel {ch}")
        print(
            f"{'method':>12} {'tripped':>8} {'A median':>9} {'d median (ms)':>14} "
            f"{'J2 median':>10} {'bench J2 median':>16} {'bench J2 95 %':>14}"
        )
        for m in methods:
            a = summ[(m, column_name("fei_amplitude", ch))]
            d = summ[(m, column_name("fei_delay", ch))]
            j2 = summ[(m, column_name("J2", ch))]
            b2 = summ[(m, column_name("bench_J2", ch))]
            print(
                f"{m:>12} {100 * a['share_tripped']:>7.1f}% {a['median']:>9.4f} "
                f"{1e3 * d['median']:>14.3f} {j2['median']:>10.3f} {b2['median']:>16.3f} "
                f"{b2['p95']:>14.3f}"
            )
    print(f"wrote {', '.join(written)} to {out} ({len(res.rows)} runs in {wall:.1f} s)")
    return 0

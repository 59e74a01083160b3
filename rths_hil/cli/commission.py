"""``rths-hil commission``: check each actuator channel and its controller before a test.

``rths-hil commission [CONFIG.toml] [--yes] [--confirm-hardware] [--out DIR] [--set k=v]...``

Per channel: identify (position, force, status), round-trip latency at the loop rate with the
actuator disabled, the enable/disable edge, a small ramp–hold–ramp (``commission.amplitude``,
``commission.velocity``) with the tracking delay and gain from the FEI and the Kalman
estimator, a chirp fitted with the delayed first-order model (the channel's delay, lag and
gain), the e-stop (latch, hold, acknowledge, re-enable), the controller's heartbeat watchdog
and the hand-back (disabled, not latched, read back) (:mod:`rths_hil.commission`). Writes
``commission/<timestamp>/report.md`` and one PNG per channel, and ``tuned.toml``, the
identified plants as a configuration fragment for ``include``. Exit codes: 0 every step
passed or was skipped, 1 a step failed, 2 bad input or no confirmation for hardware, 130
operator stop (Ctrl-C, SIGTERM or SIGHUP, as ``run``: the step under way ends, each
controller is held, disabled and handed back, the report is written).

Against hardware (a channel with ``twin.enabled = false``) it needs ``--confirm-hardware`` (or
``loop.confirm_hardware = true``) and asks the operator before it enables or moves an actuator
(``--yes`` answers for twins only).
"""

from __future__ import annotations

import argparse
import sys

from .options import add_command, add_config_arguments, add_confirm_hardware, add_out_dir, out_dir


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``commission`` to the top-level parser."""
    p = add_command(
        sub,
        "commission",
        __doc__,
        main,
        help="check each channel's controller (latency, enable, motion, e-stop, watchdog) "
        "and identify its plant for the compensation",
    )
    add_config_arguments(p)
    p.add_argument("--yes", action="store_true", help="answer the prompts (twins only)")
    add_confirm_hardware(p, "commissioning")
    add_out_dir(p, "report", "commission/{timestamp}")


def main(args: argparse.Namespace) -> int:
    """Commission every channel; return the exit code."""
    from ..stopping import OperatorStop

    with OperatorStop() as stop:  # from the start: nothing is left enabled by a signal
        return _main(args, stop)


def _main(args: argparse.Namespace, stop) -> int:
    from ..commission import commission
    from ..config import load_config
    from ..errors import InputError
    from ..hybrid.phases import hardware_channels, require_confirmation
    from ..hybrid.plan import build_plan

    cfg = load_config(args.config, args.set)
    out = out_dir(args, empty=True)
    plan = build_plan(cfg, out, mode="paced")
    hardware = bool(hardware_channels(plan))
    require_confirmation(plan, args.confirm_hardware, "commission")
    if hardware and args.yes:
        raise InputError("--yes answers for twins only: on hardware the operator answers")
    interactive = sys.stdin is not None and sys.stdin.isatty()
    if hardware and not interactive:
        raise InputError(
            "commissioning hardware asks the operator before each motion: run it interactively"
        )
    if stop.stopped:
        print(
            f"rths-hil commission: operator stop ({stop.signal}) before any step", file=sys.stderr
        )
        return 130

    def confirm(what: str) -> bool:
        if args.yes or not interactive:
            return True
        print(f"rths-hil commission: {what}.", file=sys.stderr)
        try:
            return input("Type 'yes' to go on: ").strip().lower() == "yes"
        except EOFError:
            return False

    def progress(what: str) -> None:
        print(f"rths-hil commission: {what} …", file=sys.stderr, flush=True)

    reports = commission(cfg, out, confirm=confirm, plan=plan, stop=stop, progress=progress)
    failed = [(r.name or "actuator", s) for r in reports for s in r.failed]
    for r in reports:
        for s in r.steps:
            why = f": {s.reason}" if s.reason else ""
            print(f"rths-hil commission: {r.name or 'actuator'}: {s.name}: {s.status}{why}")
    tuned = out / "tuned.toml"
    if tuned.exists():
        print(f"rths-hil commission: tuned fragment in {tuned}", file=sys.stderr)
    if stop.stopped:
        print(
            f"rths-hil commission: operator stop ({stop.signal}); controllers handed back; "
            f"report in {out / 'report.md'}",
            file=sys.stderr,
        )
        return 130
    print(
        f"rths-hil commission: {'FAILED' if failed else 'passed'}; report in {out / 'report.md'}",
        file=sys.stderr,
    )
    return 1 if failed else 0

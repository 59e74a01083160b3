"""``rths-hil twin serve``: run a virtual servo-hydraulic twin as its own process.

For a lab's dry run: the twin speaks the chosen driver's real protocol on a real transport and
prints, on one line, where it listens and the driver connection settings (JSON) that reach it
(one line per unit when the protocol serves several controllers behind one endpoint, each its
own controller, plant, faults and watchdog). Ctrl-C (SIGINT) or SIGTERM stops it cleanly with
exit code 0.

Each protocol package declares its own options (its descriptor's ``serve_options``,
:mod:`rths_hil.drivers.protocol`) and its twin endpoint turns them into its settings
(``connection_from_args``), which an option may check (its action's ``check_served``: a
device to serve must exist); the command lines of every shipped protocol are in
``docs/protocols.md`` ("Twins, faults and ``twin serve``")::

    rths-hil twin serve --driver NAME [--transport T] [--port P] [--profile FILE] [--model FILE]

``--control force`` serves the force-controlled twin (:mod:`rths_hil.sim_backends.force`): the
set-point is a force (N) on the profile's force role, closed through a force loop of gain
``--force-loop-gain`` (m/s per N) on the model file's specimen.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
from typing import TYPE_CHECKING, Any

from ..errors import InputError
from ..units import parse_length, parse_time

if TYPE_CHECKING:
    from collections.abc import Callable

    from rths_hil.sim_backends.base import Plant
    from rths_hil.sim_backends.endpoints.base import TwinEndpoint

DEFAULT_DT = 1.0 / 1024.0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``serve`` to the ``twin`` sub-command group."""
    from rths_hil.sim_backends.registry import available_twins

    p = sub.add_parser(
        "serve",
        help="run a virtual actuator twin behind its protocol's endpoint",
        description=__doc__.splitlines()[0] if __doc__ else None,
    )
    p.add_argument("--driver", required=True, choices=sorted(available_twins()))
    p.add_argument(
        "--profile",
        default=None,
        help="controller profile (TOML: the lab's own controller description, "
        "docs/profiles.md); the twin speaks it",
    )
    p.add_argument(
        "--model",
        help="twin model file (TOML); default: 20 ms delay, gain 1, spring (force: 5 ms delay, "
        "gain 1, the RTHS benchmark's 1.19 MN/m spring)",
    )
    p.add_argument(
        "--control",
        choices=("displacement", "force"),
        default="displacement",
        help="the twin's control mode: displacement (default) or force (the set-point is a "
        "force in N; the profile needs a force set-point role)",
    )
    p.add_argument(
        "--force-loop-gain",
        default=None,
        help="force control: the force loop's gain K_f in m/s per N (default 2e-4: a 4.2 ms "
        "loop on 1.19 MN/m)",
    )
    p.add_argument("--dt", default=None, help="twin step, e.g. 1ms (default 1/1024 s)")
    p.add_argument(
        "--transport",
        help="the twin's transport, the first the default: "
        + "; ".join(f"{name}: {' or '.join(t)}" for name, t in _transports().items()),
    )
    p.add_argument("--host", default="127.0.0.1", help="TCP bind address (default 127.0.0.1)")
    p.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a --host other than loopback (the twin becomes reachable from the network)",
    )
    p.add_argument(
        "--port", type=int, default=None, help="TCP port (default 0: any free port, printed)"
    )
    p.add_argument("--faults", default=None, help='fault plan, e.g. "drop=5,9; p_corrupt=0.01"')
    p.add_argument(
        "--heartbeat-timeout",
        default="0.5s",
        help="controller-side watchdog: no command or heartbeat for this long while enabled → "
        "hold and latch the e-stop (default 0.5s; 0 = off)",
    )
    p.add_argument(
        "--initial-position",
        default="0",
        help="where the actuator sits at rest, e.g. 3mm (an off-centre actuator; default 0)",
    )
    _protocol_options(p)
    p.set_defaults(func=run)


def _transports() -> dict[str, tuple[str, ...]]:
    """The transports each built-in twin offers (``--transport``), the default first."""
    from rths_hil.sim_backends.registry import TWINS

    return {name: entry.transports for name, entry in TWINS.items() if entry.transports}


def _protocol_options(p: argparse.ArgumentParser) -> None:
    """Add each protocol's own options (its descriptor's ``serve_options``), one group per
    function: protocols sharing one kind of line share its options."""
    from rths_hil.drivers.registry import available, protocol
    from rths_hil.sim_backends.registry import available_twins

    drivers = available()
    users: dict[Callable[[argparse._ArgumentGroup], None], list[str]] = {}
    for name in sorted(available_twins()):
        if name not in drivers:
            continue
        try:
            add = protocol(name).serve_options
        except InputError:  # a broken plug-in is refused with its own line when served
            continue
        if add is not None:
            users.setdefault(add, []).append(name)
    owned: list[tuple[tuple[str, ...], list[argparse.Action]]] = []
    for add, names in users.items():
        group = p.add_argument_group(f"{', '.join(names)} options")
        add(group)
        owned.append((tuple(names), list(group._group_actions)))
    p.set_defaults(protocol_options=owned)  # (checked against --driver: _check_owned)


def _check_owned(args: argparse.Namespace) -> None:
    """Refuse, in one line, an option of another protocol than ``--driver``'s (it would be
    ignored: ``--bitrate`` given to a Modbus twin)."""
    for names, actions in getattr(args, "protocol_options", ()):
        if args.driver in names:
            continue
        for action in actions:
            if getattr(args, action.dest, action.default) != action.default:
                raise InputError(
                    f"{action.option_strings[0]}: an option of the {' and '.join(names)} "
                    f"twins; --driver {args.driver} does not take it"
                )


def _endpoint(args: argparse.Namespace) -> type[TwinEndpoint]:
    """The twin endpoint class of ``--driver`` (built-in or from an entry point)."""
    from rths_hil.sim_backends.registry import twin_class

    return twin_class(args.driver)[0]


def _connection(args: argparse.Namespace) -> dict[str, Any]:
    """The endpoint settings the options give (the endpoint class maps them)."""
    conn = _endpoint(args).connection_from_args(args)
    if args.profile:
        from pathlib import Path

        from rths_hil.drivers.profile import load_profile

        try:
            path = str(Path(args.profile).expanduser().resolve())
            load_profile(path)
        except InputError as exc:
            raise InputError(f"--profile: {exc}") from None
        except (RuntimeError, OSError) as exc:  # a symlink loop (RuntimeError before 3.13)
            raise InputError(f"--profile {args.profile}: cannot be resolved: {exc}") from None
        conn["profile"] = path
    _check_served(args, conn)
    _check_owned(args)
    return conn


def _check_served(args: argparse.Namespace, conn: dict[str, Any]) -> None:
    """Let each protocol option given check the connection it serves: an option whose action
    has a ``check_served(value, args, conn)`` (a device to serve that must exist) refuses, in
    one line, what the twin cannot serve."""
    for _, actions in getattr(args, "protocol_options", ()):
        for action in actions:
            check = getattr(action, "check_served", None)
            value = getattr(args, action.dest, action.default)
            if check is not None and value != action.default:
                check(value, args, conn)


def _loop_gain(args: argparse.Namespace) -> float | None:
    """``--force-loop-gain`` as a number > 0 (m/s per N), or None when not given."""
    text = args.force_loop_gain
    if text is None:
        return None
    if args.control != "force":
        raise InputError(f"--force-loop-gain {text}: only with --control force")
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"--force-loop-gain {text}: must be a number > 0 (m/s per N)")
    return value


def _plant_factory(args: argparse.Namespace, dt: float) -> Callable[[], Plant]:
    """What builds each unit's plant: ``--model`` or the default, of ``--control``'s twin."""
    from rths_hil.sim_backends.twin import default_force_plant, default_plant

    loop_gain = _loop_gain(args)

    def plant() -> Plant:
        if args.control == "force":
            from rths_hil.sim_backends.force import DEFAULT_LOOP_GAIN, force_plant

            if args.model:
                try:
                    return force_plant(args.model, dt, loop_gain or DEFAULT_LOOP_GAIN)
                except InputError as exc:  # a message naming the file already says which
                    if str(exc).startswith(str(args.model)):
                        raise
                    raise InputError(f"--model {args.model}: {exc}") from None
            return default_force_plant(loop_gain=loop_gain, dt=dt)
        if args.model:
            from rths_hil.sim_backends.modelfile import build_plant

            return build_plant(args.model, dt)
        return default_plant(dt=dt)

    plant()  # a bad model file is refused before anything listens
    return plant


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT/SIGTERM; return 0."""
    from rths_hil.sim_backends.faults import Faults
    from rths_hil.sim_backends.twin import start_twin

    dt = DEFAULT_DT if args.dt is None else parse_time(args.dt, "--dt")
    if not dt > 0:
        raise InputError(f"--dt {args.dt}: the step must be > 0")

    plant = _plant_factory(args, dt)

    hb = parse_time(args.heartbeat_timeout, "--heartbeat-timeout")
    if not hb >= 0:
        raise InputError(f"--heartbeat-timeout {args.heartbeat_timeout}: must be >= 0 s")
    heartbeat_timeout: float | None = hb or None
    home = parse_length(args.initial_position, "--initial-position")
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        endpoint = _endpoint(args)
        conn = _connection(args)
        units = endpoint.serve_units(args)
        twins: list[Any] = []
        try:
            for unit in units:
                if twins:  # the next unit of the first one's endpoint
                    conn = endpoint.unit_connection(twins[0].connection, unit, args)
                twin = start_twin(
                    args.driver,
                    plant(),
                    faults=Faults.parse(args.faults) if args.faults else None,
                    heartbeat_timeout=heartbeat_timeout,
                    initial_position=home,
                    **conn,
                )
                twins.append(twin)
                print(
                    f"rths-hil twin serve: {args.driver} twin listening on {twin.where} "
                    f"connection {json.dumps(twin.connection)}",
                    flush=True,
                )
            while not stop.wait(0.2):
                for twin in twins:
                    if twin.error is not None:
                        raise InputError(f"twin endpoint stopped: {twin.error}")
        finally:
            for twin in reversed(twins):
                twin.stop()
        for twin in twins:
            s = twin.stats
            who = f"unit {twin.device_id}: " if len(twins) > 1 else ""
            print(
                f"rths-hil twin serve: {who}stopped after {s.steps} steps "
                f"({s.commands} commands, {s.estops} e-stops, {s.malformed} malformed)",
                file=sys.stderr,
            )
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0

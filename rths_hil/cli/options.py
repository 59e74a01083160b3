"""Command-line options several sub-commands share.

:func:`add_command` adds a sub-command with its help, description and function;
:func:`add_config_arguments` adds the optional ``CONFIG.toml`` and the repeatable
``--set KEY=VALUE`` of ``run``, ``commission``, ``tune`` and ``check-host``, and
:func:`add_confirm_hardware` the ``--confirm-hardware`` of the first three;
:func:`config_from_args` loads the configuration they name (:func:`rths_hil.config.load_config`);
:func:`add_simulation_arguments` and :func:`simulation_from_args` are the damping, actuator, PGA
and rate options of ``simulate`` and of the FEI paper's studies, with
:func:`add_ground_motion_argument` their ``--record``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from ..errors import InputError
from ..units import parse_accel, parse_fraction, parse_time, positive_number

if TYPE_CHECKING:
    from ..config import Config

__all__ = [
    "Simulation",
    "add_command",
    "add_config_arguments",
    "add_confirm_hardware",
    "add_ground_motion_argument",
    "add_out_dir",
    "add_simulation_arguments",
    "config_from_args",
    "out_dir",
    "simulation_from_args",
]


def add_command(
    sub: argparse._SubParsersAction,
    name: str,
    doc: str | None,
    func: Callable[[argparse.Namespace], int],
    help: str,
) -> argparse.ArgumentParser:
    """Add the sub-command ``name`` to ``sub`` and return its parser.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers to add it to.
    name : str
        The sub-command.
    doc : str
        Its description: the first line of it (the module's docstring, whose first line says
        what the command does).
    func : callable
        Runs the command with the parsed arguments; returns the exit code.
    help : str
        Its line in the parent's list of commands.
    """
    first = (doc or "").strip().splitlines()
    parser = sub.add_parser(name, help=help, description=first[0] if first else None)
    parser.set_defaults(func=func)
    return parser


def add_config_arguments(parser: argparse.ArgumentParser, set_example: str = "") -> None:
    """Add ``config`` (optional, default the embedded NEES-711 setup) and ``--set`` to ``parser``.

    ``set_example`` (e.g. ``"loop.fs=2048"``) is quoted in the help of ``--set``.
    """
    parser.add_argument("config", nargs="?", help="TOML configuration (default: embedded NEES-711)")
    example = f", e.g. --set {set_example}" if set_example else ""
    parser.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help=f"override a configuration key{example} (repeatable)",
    )


def add_confirm_hardware(parser: argparse.ArgumentParser, what: str) -> None:
    """Add ``--confirm-hardware``, the operator's consent that ``what`` may drive real hardware.

    Read by :func:`rths_hil.hybrid.phases.require_confirmation` (``run``, ``commission``) and
    ``tune``; ``loop.confirm_hardware = true`` in the configuration consents as well.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    what : str
        What may drive the hardware, e.g. ``"the run"``.
    """
    parser.add_argument(
        "--confirm-hardware",
        action="store_true",
        help=f"confirm that {what} may drive real hardware (a channel with twin.enabled = false; "
        "or loop.confirm_hardware = true in the configuration)",
    )


def add_out_dir(parser: argparse.ArgumentParser, what: str, default: str) -> None:
    """Add ``--out DIR``, the directory a command writes (see :func:`out_dir`).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    what : str
        What the directory holds, e.g. ``"run"``.
    default : str
        The directory without ``--out``: a pattern such as ``commission/{timestamp}``
        (:func:`out_dir` reads it), or the configuration key that holds one (for the help; the
        command passes the key's value to :func:`out_dir`).
    """
    parser.add_argument("--out", metavar="DIR", help=f"{what} directory (default: {default})")
    parser.set_defaults(out_pattern=default)


def out_dir(args: argparse.Namespace, empty: bool, pattern: str | None = None) -> Path:
    """The directory of ``--out``, else a new one from the default pattern.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments (``args.out``, ``None`` when not given).
    empty : bool
        Refuse a directory that exists and is not empty (a command whose files have fixed
        names).
    pattern : str, optional
        The default directory, if not the one :func:`add_out_dir` declared; ``{timestamp}`` is
        expanded and a directory that holds a run gets a suffix
        (:func:`rths_hil.hybrid.plan.new_run_dir`).

    Returns
    -------
    Path
        The directory (not created).

    Raises
    ------
    InputError
        ``--out`` given empty, or (``empty``) naming a file or a directory with files.
    """
    from ..hybrid.plan import new_run_dir

    if args.out is not None and not args.out.strip():
        raise InputError("--out is empty: give a directory")
    if pattern is None:  # (an empty configured pattern is new_run_dir's to refuse)
        pattern = args.out_pattern
    out = Path(args.out) if args.out else new_run_dir(pattern)
    if empty and out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"--out {out}: exists and is not an empty directory; choose a new one")
    return out


def config_from_args(args: argparse.Namespace) -> Config:
    """The configuration ``args.config`` with the ``args.set`` overrides, cross-checked."""
    from ..config import load_config  # when a command runs: ``rths-hil --help`` stays quick

    return load_config(args.config, args.set)


def add_simulation_arguments(parser: argparse.ArgumentParser, gain: str, delay: str) -> None:
    """Add ``--zeta``, ``--gain``, ``--delay``, ``--pga`` and ``--fs`` of an offline simulation.

    The SDOF structure's damping ratio, the delay/gain actuator, the scale of the ground motion
    and the simulation rate; read them with :func:`simulation_from_args`.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    gain, delay : str
        The defaults of ``--gain`` and ``--delay`` (as the user would write them, e.g. ``"5ms"``).
    """
    parser.add_argument("--zeta", default="0.02", help="damping ratio (default 0.02; 2%% accepted)")
    parser.add_argument("--gain", default=gain, help=f"actuator gain k_p (default {gain})")
    parser.add_argument(
        "--delay", default=delay, help=f"actuator transport delay, e.g. 5ms (default {delay})"
    )
    parser.add_argument(
        "--pga", default=None, help="scale the ground motion to this PGA: m/s² or with a g suffix"
    )
    parser.add_argument("--fs", default="1024", help="simulation rate in Hz (default 1024)")


class Simulation(NamedTuple):
    """The options of :func:`add_simulation_arguments`, checked, in SI units."""

    zeta: float
    gain: float
    delay: float
    fs: float
    pga: float | None


def add_ground_motion_argument(
    parser: argparse.ArgumentParser, default: str, several: bool
) -> None:
    """Add ``--record``, the ground motion of an offline simulation.

    A PEER ``.AT2`` or ``.csv`` file or a bundled record's name
    (:func:`rths_hil.groundmotion.resolve`); ``args.record`` is ``None`` when not given, else
    the name or, with ``several``, the list of names (``--record`` repeated).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    default : str
        What is used without ``--record`` (for the help).
    several : bool
        Whether ``--record`` may be repeated.
    """
    parser.add_argument(
        "--record",
        action="append" if several else "store",
        default=None,
        help="ground motion: PEER .AT2 or .csv file, or a bundled record name"
        + ("; repeat for several" if several else "")
        + f" (default: {default})",
    )


def simulation_from_args(args: argparse.Namespace) -> Simulation:
    """The options of :func:`add_simulation_arguments`, checked, in SI units.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed arguments.

    Returns
    -------
    Simulation
        ``zeta`` in [0, 1), ``gain`` > 0, ``delay`` ≥ 0 (s), ``fs`` > 0 (Hz) and ``pga``
        (m/s², ``None``: the record's own).

    Raises
    ------
    InputError
        One line naming the option that is wrong.
    """
    zeta = parse_fraction(args.zeta, "--zeta")
    if not 0 <= zeta < 1:
        raise InputError(f"--zeta: damping ratio must lie in [0, 1), got {args.zeta}")
    return Simulation(
        zeta=zeta,
        gain=positive_number(args.gain, "--gain"),
        delay=positive_number(parse_time(args.delay, "--delay"), "--delay (s)", allow_zero=True),
        fs=positive_number(args.fs, "--fs"),
        pga=None if args.pga is None else parse_accel(args.pga, "--pga"),
    )

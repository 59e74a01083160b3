"""Command-line options several sub-commands share.

:func:`add_command` adds a sub-command with its help, description and function;
:func:`add_config_arguments` adds the optional ``CONFIG.toml`` and the repeatable
``--set KEY=VALUE`` of ``run``, ``commission``, ``tune`` and ``check-host``;
:func:`config_from_args` loads the configuration they name (:func:`rths_hil.config.load_config`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..config import Config

__all__ = ["add_command", "add_config_arguments", "config_from_args"]


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


def config_from_args(args: argparse.Namespace) -> Config:
    """The configuration ``args.config`` with the ``args.set`` overrides, cross-checked."""
    from ..config import load_config  # when a command runs: ``rths-hil --help`` stays quick

    return load_config(args.config, args.set)

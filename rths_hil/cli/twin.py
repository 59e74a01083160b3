"""``rths-hil twin …``: run a virtual servo-hydraulic twin, or calibrate one from a record.

The sub-commands live in :mod:`rths_hil.cli.twin_serve` (``twin serve``) and
:mod:`rths_hil.cli.twin_calibrate` (``twin calibrate``); this module only groups them.
"""

from __future__ import annotations

import argparse
import importlib


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``twin`` and its sub-commands to the top-level parser."""
    parser = sub.add_parser("twin", help="virtual servo-hydraulic twins: serve, calibrate")
    twin_sub = parser.add_subparsers(dest="twin_command", metavar="SUBCOMMAND")
    for name in ("twin_serve", "twin_calibrate"):
        try:
            module = importlib.import_module(f"{__package__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"{__package__}.{name}":
                continue
            raise
        module.register(twin_sub)

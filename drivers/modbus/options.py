"""``rths-hil twin serve`` options of a Modbus twin: the RTU device to serve and the unit ids
of one TCP server. The twin endpoint turns them into its settings
(:meth:`rths_hil.sim_backends.endpoints.modbus.ModbusTwin.connection_from_args`)."""

from __future__ import annotations

import argparse

__all__ = ["serve_options"]


def serve_options(group: argparse._ArgumentGroup) -> None:
    """Add ``--device`` and ``--device-id`` to ``twin serve``'s parser."""
    group.add_argument("--device", help="modbus rtu: serial device to serve (default: a new pty)")
    group.add_argument(
        "--device-id",
        type=int,
        action="append",
        default=None,
        help="modbus unit id (default 1); repeat for several units on one TCP server",
    )

"""``rths-hil twin serve`` options of a Modbus twin: the RTU device to serve and the unit ids
of one TCP server. The twin endpoint turns them into its settings
(:meth:`rths_hil.sim_backends.endpoints.modbus.ModbusTwin.connection_from_args`); ``--device``
checks the device it serves (:class:`DeviceOption`)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from rths_hil.errors import InputError

from ..serial.line import check_device

__all__ = ["DeviceOption", "serve_options"]


class DeviceOption(argparse.Action):
    """``--device``: stored as given, and checked against the served connection
    (:meth:`check_served`) once the twin endpoint has made it."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        """Store the device path."""
        setattr(namespace, self.dest, values)

    def check_served(self, value: Any, args: argparse.Namespace, conn: dict[str, Any]) -> None:
        """Refuse ``--device`` for a twin that serves no device (Modbus TCP, another
        ``--driver``), or a device that is not a serial device.

        Parameters
        ----------
        value : Any
            The option's value (a path; empty: not given).
        args : argparse.Namespace
            ``twin serve``'s options (``--driver``).
        conn : dict
            The endpoint settings the options gave.

        Raises
        ------
        InputError
            One line naming ``--device`` and its value.
        """
        if not value:
            return
        if "device" not in conn:
            raise InputError(
                f"--device {value}: --driver {args.driver} serves no device here "
                f"({conn.get('transport', 'its own line')})"
            )
        check_device(conn["device"])


def serve_options(group: argparse._ArgumentGroup) -> None:
    """Add ``--device`` and ``--device-id`` to ``twin serve``'s parser."""
    group.add_argument(
        "--device",
        action=DeviceOption,
        help="modbus rtu: serial device to serve (default: a new pty)",
    )
    group.add_argument(
        "--device-id",
        type=int,
        action="append",
        default=None,
        help="modbus unit id (default 1); repeat for several units on one TCP server",
    )

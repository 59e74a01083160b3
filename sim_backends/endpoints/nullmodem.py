"""A virtual null-modem cable: two pseudo-terminals whose traffic is relayed to each other.

What ``socat pty,raw,echo=0 pty,raw,echo=0`` or the ``tty0tty`` kernel module give a lab: two
serial device paths such that bytes written to one are read from the other. A twin opens one end
(:attr:`NullModem.twin_path`) with the same library the bridge uses on the other end
(:attr:`NullModem.bridge_path`), so both sides speak the protocol through the library's own
framing — the CAN, CAN profile and CANopen twins serve python-can's ``serial`` and ``slcan``
interfaces this way (:func:`serial_line`, :class:`CANLine`). Nothing leaves the machine: a
pseudo-terminal is a kernel object, not a network endpoint. :func:`can_line_from_args` is the
line a CAN twin served as its own process opens from the command line: one of these
pseudo-terminal pairs, or the lab's interface.

The cable keeps a descriptor of each end open itself, so that a process closing its end (or
being killed) does not hang the pair up: the next process that opens the same path continues
on the same cable. Bytes written towards an end nobody reads fill that end's input buffer; once
it is full, further bytes are dropped (a line with no listener loses them) rather than blocking
the other direction.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import tty
from typing import Any

import can
from rths_hil.drivers.can import BUS_KEYS

from rths_hil.errors import InputError
from rths_hil.keys import Key

log = logging.getLogger(__name__)

__all__ = [
    "LINE_KEYS",
    "PTY_CHANNEL",
    "PTY_INTERFACES",
    "CANLine",
    "NullModem",
    "can_line_from_args",
    "serial_line",
]


class NullModem:
    """Two raw pseudo-terminals cross-connected by a relay thread.

    Attributes
    ----------
    bridge_path, twin_path : str
        The two ends (``/dev/pts/N``); either may be given to the bridge, by convention the first.
    relayed : list of int
        Bytes relayed bridge → twin and twin → bridge.
    dropped : int
        Bytes dropped because the receiving end's buffer was full (nobody reading it).
    """

    def __init__(self) -> None:
        self._masters: list[int] = []
        self._slaves: list[int] = []
        paths = []
        try:
            for _ in range(2):
                master, slave = os.openpty()
                self._masters.append(master)
                self._slaves.append(slave)
                tty.setraw(slave)  # no echo, no CR → LF: the bytes as written
                os.set_blocking(master, False)
                paths.append(os.ttyname(slave))
        except OSError:
            self._close_fds()
            raise
        self.bridge_path, self.twin_path = paths
        self.relayed = [0, 0]
        self.dropped = 0
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="null-modem", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        a, b = self._masters
        other = {a: (b, 0), b: (a, 1)}
        while not self._stop.is_set():
            ready = select.select((a, b, self._wake_r), (), (), 0.5)[0]
            for fd in ready:
                if fd == self._wake_r:
                    return
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:  # the pair is being closed
                    return
                dst, k = other[fd]
                try:
                    n = os.write(dst, data)
                except BlockingIOError:
                    n = 0
                except OSError:
                    return
                self.relayed[k] += n
                if n < len(data):
                    self.dropped += len(data) - n
                    log.debug("null modem: %d bytes dropped (nobody reading)", len(data) - n)

    def close(self) -> None:
        """Stop the relay and close both pseudo-terminals (their paths disappear)."""
        if self._stop.is_set():
            return
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:  # pragma: no cover - already closed
            pass
        self._thread.join(timeout=2.0)
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in (*self._masters, *self._slaves):
            try:
                os.close(fd)
            except OSError:
                pass
        self._masters, self._slaves = [], []

    def __enter__(self) -> NullModem:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: ``channel`` of a twin on a serial-line interface that asks for a new null-modem pair of
#: pseudo-terminals (:class:`~rths_hil.sim_backends.endpoints.nullmodem.NullModem`).
PTY_CHANNEL = "pty"
#: python-can interfaces over a serial line that the twin serves on a null-modem cable, with
#: the python-can options of the bridge's end and of the twin's end. ``slcan`` waits 2 s after
#: opening for an adapter to boot (a pseudo-terminal needs no wait); ``serial`` reads with its
#: own 0.1 s timeout whatever ``recv`` asks (the driver reads it through a notifier thread), so
#: the twin's end reads with 5 ms to poll its watchdog on time.
PTY_INTERFACES: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "slcan": ({"sleep_after_open": 0.0}, {"sleep_after_open": 0.0}),
    "serial": ({}, {"timeout": 0.005}),
}


#: The python-can line of a CAN-family twin as its :attr:`TwinEndpoint.CONNECTION
#: <rths_hil.sim_backends.endpoints.base.TwinEndpoint.CONNECTION>` declares it: the driver's
#: bus keys, the channel defaulting to a line of the twin's own.
LINE_KEYS: dict[str, Key] = {
    **BUS_KEYS,
    "channel": Key(
        "str|int",
        None,
        doc="bus channel (none: a fresh virtual bus of the twin's own; "
        f"{PTY_CHANNEL!r} on serial or slcan: a null-modem pair of pseudo-terminals)",
    ),
}


def can_line_from_args(args: Any, who: str) -> dict[str, Any]:
    """The CAN line a twin served as its own process opens: ``--interface``, ``--channel``
    (default ``pty`` for the serial-line interfaces, else ``vcan0``) and ``--bitrate``.

    Raises
    ------
    InputError
        ``--interface virtual``: python-can's virtual bus cannot leave the process.
    """
    if args.interface == "virtual":
        raise InputError(
            f"{who}: --interface virtual: python-can's virtual bus only reaches buses inside the "
            "same process; use --interface serial or slcan (a pseudo-terminal pair on this "
            "machine), --interface socketcan --channel vcan0 (or the lab's interface), or start "
            "the twin in-process with rths_hil.sim_backends.twin.start_twin"
        )
    channel = args.channel
    if channel is None:
        channel = PTY_CHANNEL if args.interface in PTY_INTERFACES else "vcan0"
    conn: dict[str, Any] = {"interface": args.interface, "channel": channel}
    if args.bitrate is not None:
        conn["bitrate"] = args.bitrate
    return conn


def serial_line(
    interface: str, channel: str, kwargs: dict[str, Any], who: str
) -> tuple[NullModem | None, str, str, dict[str, Any], dict[str, Any]]:
    """The line a twin opens on a python-can ``interface`` and ``channel``.

    For a serial-line interface (:data:`PTY_INTERFACES`) with ``channel = "pty"``: a new
    null-modem cable of two pseudo-terminals. Returns the cable (``None`` otherwise), the
    channel the twin opens, the channel the bridge opens, the twin end's python-can options
    (``kwargs`` over the interface's own) and the options the bridge's end needs.

    Raises
    ------
    InputError
        The pseudo-terminals cannot be opened (``who`` names the twin).
    """
    if interface not in PTY_INTERFACES or channel != PTY_CHANNEL:
        return None, channel, channel, dict(kwargs), {}
    try:
        cable = NullModem()
    except OSError as exc:
        raise InputError(f"{who}: cannot open pseudo-terminals for {interface}: {exc}") from None
    bridge_options, twin_options = PTY_INTERFACES[interface]
    return (cable, cable.twin_path, cable.bridge_path, {**twin_options, **kwargs},
            dict(bridge_options))  # fmt: skip


class CANLine:
    """The python-can line of a CAN-family twin (CAN, CAN profile, CANopen): the settings
    ``interface``, ``channel``, ``bitrate`` and ``bus_options`` the twin keeps, and the
    null-modem :attr:`cable` while the line has one (:func:`serial_line`)."""

    interface: str
    channel: str
    bitrate: int | None
    bus_options: dict[str, Any]
    #: the pseudo-terminal pair of a serial-line interface with channel "pty", while open
    cable: NullModem | None = None

    def _open_line(self, who: str) -> tuple[str, str, dict[str, Any], dict[str, Any]]:
        """The two ends of the line, the cable made when it needs one (``who`` names the twin
        in an error).

        Returns
        -------
        tuple
            The channel the twin opens, the channel the bridge opens, the twin end's python-can
            options (``bus_options`` and ``bitrate`` over the interface's own) and the bridge
            end's ``bus_options`` (the interface's needs, then the twin's ``bus_options``).
        """
        kwargs = dict(self.bus_options)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        self.cable, channel, bridge_channel, kwargs, bridge_options = serial_line(
            self.interface, self.channel, kwargs, who
        )
        return channel, bridge_channel, kwargs, {**bridge_options, **self.bus_options}

    def _bridge_end(self, connection: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
        """``connection`` (what the bridge's driver opens) with the line's ``bitrate`` and the
        bridge end's python-can ``options`` (:meth:`_open_line`) where set."""
        if self.bitrate is not None:
            connection["bitrate"] = self.bitrate
        if options:
            connection["bus_options"] = options
        return connection

    @property
    def _line_note(self) -> str:
        """What the twin's ``where`` adds for a line that is a null-modem cable."""
        return " (pseudo-terminal null modem)" if self.cable is not None else ""

    def _send(self, bus: Any, frame: Any) -> None:
        """Put ``frame`` on the python-can ``bus``; nothing when the bus is gone (closed, or
        failing: the bridge then sees no answer)."""
        if bus is None:
            return
        try:
            bus.send(frame)
        except (can.CanError, OSError):  # pragma: no cover - bus gone
            pass

    def _close_cable(self) -> None:
        cable, self.cable = self.cable, None
        if cable is not None:
            cable.close()

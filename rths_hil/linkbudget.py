"""Link budget: how much of each bus's capacity a test uses, from the frames on the wire.

Every step each channel sends one command and receives one feedback. Before any software, the
bus has to carry those bits in time: this module computes, for each link, the fraction of its
capacity used per second and refuses a configuration above a limit (80 % by default) with one
line saying what would fit. It names no protocol: the protocol descriptor of a channel's driver
(:class:`rths_hil.drivers.protocol.Protocol`, from the driver registry) knows its link
(``link_key``), its frames and their load (``link_load``, a :class:`LinkLoad`) and what would
bring it under the limit (``link_advice``), each in the link model of its protocol's package
(``drivers/can/linkbudget.py``, ``drivers/canopen/linkbudget.py``,
``drivers/modbus/linkbudget.py``, ``drivers/serial/linkbudget.py``; the formulas are in those
modules and, with a table of rates × channels, in ``docs/protocols.md``). Here: the arithmetic
they share, the check against the limit and the console lines.

A link's load is ``channels · per_channel · fs + per_second`` of its capacity: ``per_channel``
the link time of one channel's step (command and feedback frames, in bits over the bit rate or
characters over the baud rate), ``per_second`` what does not scale with the loop rate
(heartbeats). What would fit, for any link: the highest loop rate and the most channels per
link under the limit; then the protocol's own advice (a higher bit or baud rate, another
transport).

A link without a rate reports "no limit" (a :class:`LinkLoad` whose ``load`` is ``None``): each
link model says which of its links have none (a virtual bus, a pseudo-terminal);
:func:`is_loopback` tells the loopback interface, which has none either.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from .errors import InputError
from .units import positive_number

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_LIMIT",
    "LinkLoad",
    "channels_count",
    "check_links",
    "format_loads",
    "is_loopback",
    "link_inputs",
    "link_key",
    "link_load",
    "positive",
    "rate_text",
]

#: Default refusal threshold: a link above 80 % of its capacity is refused.
DEFAULT_LIMIT = 0.8

#: One checker of positive numbers for the package (rths_hil.units).
positive = positive_number


# --------------------------------------------------------------------------------------------
# links
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LinkLoad:
    """The load of one link (bus, line or connection) shared by ``channels`` channels.

    Attributes
    ----------
    link : str
        Name of the link (driver, transport and where: ``can virtual:rths-hil``,
        ``modbus rtu /dev/ttyUSB0``, ``serial /dev/ttyUSB0``).
    load : float or None
        Fraction of the link's capacity used (1.0 = full); ``None`` when the link has no rate
        (virtual bus, pseudo-terminal, loopback) or its rate is unknown.
    detail : str
        One line: frames, bits or bytes per step, rate.
    channels : int
        Channels on the link.
    fs : float
        Loop rate (Hz).
    enforced : bool
        Whether :func:`check_links` refuses the link above the limit (``False`` for a load
        computed for information only, e.g. a virtual bus with a ``bitrate``).
    kind : str
        What kind of link it is: the registry name of the driver whose link model advises on
        it (``Protocol.link_advice``), optionally with a variant after a hyphen (``can``,
        ``modbus-rtu``, ``modbus-tcp``, ``serial``); ``other``: no advice but the loop rate
        and the channels per link.
    rate : float or None
        Bit rate (CAN, Ethernet) or baud rate (serial lines).
    per_channel : float
        Link time (s) of one channel's step traffic (command + feedback).
    per_second : float
        Link time (s) per second that does not scale with the loop rate (heartbeats).
    """

    link: str
    load: float | None
    detail: str
    channels: int = 1
    fs: float = 0.0
    enforced: bool = True
    kind: str = "other"
    rate: float | None = None
    per_channel: float = 0.0
    per_second: float = 0.0

    @property
    def limited(self) -> bool:
        """True when the link has a rate and the load is checked."""
        return self.load is not None and self.enforced

    def summary(self) -> str:
        """One line for the console: link, load, detail."""
        if self.load is None:
            return f"{self.link}: no limit ({self.detail})"
        tail = "" if self.enforced else ", not enforced"
        return f"{self.link}: {self.load * 100:.1f} % ({self.detail}{tail})"


def rate_text(bits_per_s: float) -> str:
    """A bit rate as the console gives it: ``500 kbit/s``, ``1 Mbit/s``."""
    if bits_per_s >= 1e6:
        return f"{bits_per_s / 1e6:g} Mbit/s"
    return f"{bits_per_s / 1e3:g} kbit/s"


def is_loopback(host: str) -> bool:
    """Whether ``host`` is the loopback interface (no line rate to check)."""
    h = str(host).strip().lower()
    return h in ("localhost", "::1", "ip6-localhost") or h.startswith("127.")


def link_inputs(
    connection: dict[str, Any] | None, channels_on_link: int, fs: float
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A link model's inputs, checked: a copy of the connection, and the channels on the link
    and the loop rate as the :class:`LinkLoad` fields they fill (``channels``, ``fs``)."""
    fs = positive(fs, "loop rate fs (Hz)")
    return dict(connection or {}), {"channels": channels_count(channels_on_link), "fs": fs}


def channels_count(channels_on_link: int) -> int:
    """The channels on a link, checked (≥ 1)."""
    ch = int(channels_on_link)
    if ch < 1:
        raise InputError(f"channels on a link must be ≥ 1, got {channels_on_link}")
    return ch


def _protocol(driver_name: str) -> Any:
    """The protocol descriptor of ``driver_name`` (the driver registry), or ``None`` for an
    unknown name."""
    from rths_hil.drivers.registry import available, protocol

    if str(driver_name) not in available():
        return None
    return protocol(str(driver_name))


def link_key(driver_name: str, connection: dict[str, Any]) -> str:
    """Name of the physical link a channel's connection uses; equal names share one link.

    Asks the protocol descriptor (``Protocol.link_key``): CAN: interface and channel; Modbus
    TCP: host and port; Modbus RTU: the serial device; serial: the port or URL. Other drivers (and
    unknown names): the driver name and its sorted settings.
    """
    c = dict(connection or {})
    proto = _protocol(driver_name)
    if proto is None:
        return f"{driver_name} " + ",".join(f"{k}={c[k]}" for k in sorted(c))
    key: str = proto.link_key(c)
    return key


def link_load(
    driver_name: str,
    connection: dict[str, Any],
    channels_on_link: int,
    fs: float,
    *,
    heartbeat_hz: float = 0.0,
) -> LinkLoad:
    """Load of the link used by ``channels_on_link`` channels of ``driver_name`` at ``fs``.

    The protocol descriptor computes it (``Protocol.link_load``: the link model of its
    protocol's package); a driver that does not know its frames, or an unknown name, reports "not
    checked".

    Parameters
    ----------
    driver_name : str
        Driver registry name (``can``, ``modbus``, ``serial`` or a lab's entry point).
    connection : dict
        The driver's connection settings (as given to ``rths_hil.drivers.registry.create_driver``).
    channels_on_link : int
        Channels sharing this link (see :func:`link_key`).
    fs : float
        Loop rate (Hz): one command and one feedback per channel and step.
    heartbeat_hz : float
        Heartbeat frames per second per channel (0: none), e.g. ``1 / loop.heartbeat``.

    Returns
    -------
    LinkLoad
    """
    c = dict(connection or {})
    fs = positive(fs, "loop rate fs (Hz)")
    ch = channels_count(channels_on_link)
    proto = _protocol(driver_name)
    if proto is None:
        return LinkLoad(
            link_key(driver_name, c),
            None,
            f"driver {driver_name!r}: frame sizes unknown, not checked",
            channels=ch,
            fs=fs,
        )
    load: LinkLoad = proto.link_load(c, ch, fs, heartbeat_hz=float(heartbeat_hz))
    return load


def _what_fits(ld: LinkLoad, limit: float) -> str:
    """The alternatives that would bring ``ld`` under ``limit``, as one phrase: the loop rate
    and the channels per link, then the advice of the link's protocol (``Protocol.link_advice``
    of the driver its ``kind`` names)."""
    options = []
    if ld.per_channel > 0 and limit > ld.per_second:
        budget = limit - ld.per_second
        fs_max = budget / (ld.channels * ld.per_channel)
        options.append(f"a loop rate ≤ {math.floor(fs_max):d} Hz")
        per_bus = math.floor(budget / (ld.per_channel * ld.fs))
        if 1 <= per_bus < ld.channels:
            options.append(f"≤ {per_bus} channel{'s' if per_bus > 1 else ''} per link")
        elif per_bus < 1:
            options.append("not even one channel per link at this rate")
    proto = _protocol(ld.kind.split("-", 1)[0])
    if proto is not None:
        options += proto.link_advice(ld, limit)
    return "; ".join(options) if options else "nothing at this rate"


def check_links(loads: list[LinkLoad] | tuple[LinkLoad, ...], limit: float = DEFAULT_LIMIT) -> None:
    """Refuse the configuration if an enforced link is loaded above ``limit``.

    Raises
    ------
    InputError
        One line naming the most loaded link, its load, and what would fit (lower rate, fewer
        channels per link, higher bit rate, CAN FD); other links over the limit are counted.
    """
    limit = positive(limit, "link load limit")
    over = sorted(
        (ld for ld in loads if ld.limited and ld.load is not None and ld.load > limit),
        key=lambda ld: -(ld.load or 0.0),
    )
    for ld in loads:
        log.info("link budget: %s", ld.summary())
    if not over:
        return
    ld = over[0]
    load = ld.load or 0.0  # (not None: over the limit)
    more = (
        f" (and {len(over) - 1} more link{'s' if len(over) > 2 else ''} over)"
        if len(over) > 1
        else ""
    )
    raise InputError(
        f"link {ld.link} is {load * 100:.0f} % loaded with {ld.channels} channel"
        f"{'s' if ld.channels > 1 else ''} at {ld.fs:g} Hz (limit {limit * 100:.0f} %): "
        f"{ld.detail}; would fit: {_what_fits(ld, limit)}{more}"
    )


def format_loads(loads: list[LinkLoad] | tuple[LinkLoad, ...]) -> str:
    """One line per link, for the start-up console."""
    return "\n".join("link " + ld.summary() for ld in loads)

"""What the planner knows of a protocol: one small, frozen descriptor per driver name.

The :class:`~rths_hil.drivers.base.Driver` class is the bus contract only (open, send, receive,
arm, e-stop, in the style of python-can's ``BusABC``). What the plan and the link budget need
before any bus is opened — which physical link a connection uses, the load of its frames, who
may share it, whether its twin can be served from the loop's thread, which profile format the
protocol takes and which connection settings are file paths — is a :class:`Protocol`. Each
protocol package exports one as ``PROTOCOL`` (``rths_hil.drivers.can.PROTOCOL`` …), its hooks
the functions of the same names in the package's link model (:meth:`Protocol.from_hooks`);
:mod:`rths_hil.drivers.registry` maps driver names to them, and finds the packages shipped here
by that name: a folder under ``drivers/`` whose ``__init__.py`` binds ``PROTOCOL`` is the
driver of the folder's name (the descriptor's :attr:`Protocol.name`), with no list to edit.
A lab's driver registered as a :class:`Driver` subclass gets one built from its class
(:meth:`Protocol.from_driver`): the class's hooks of the same names, where it has them, else
the defaults.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad, link_inputs

if TYPE_CHECKING:
    from rths_hil.keys import Key

    from .base import Driver

__all__ = ["HOOKS", "ChannelUse", "LinkInputs", "Protocol", "default_own_link", "link_model"]

#: One channel of a test as :attr:`Protocol.check_sharing` sees it: (index in ``actuators``,
#: channel name, its connection settings, whether a twin serves it).
ChannelUse = tuple[int, str, dict[str, Any], bool]

#: The descriptor's planning hooks a lab's driver class may define (as class methods).
HOOKS = ("link_key", "link_load", "link_advice", "check_sharing", "own_link", "inline_twin")


def default_own_link(connection: dict[str, Any]) -> bool:
    """True when a channel with a twin gets a link of its own: no bus, port or device is
    named in ``connection`` (the twin opens a fresh one)."""
    c = connection or {}
    return not (c.get("channel") or c.get("port") or c.get("url"))


@dataclass(frozen=True)
class LinkInputs:
    """What a link model computes a link's load from, checked (:func:`link_model`).

    Attributes
    ----------
    connection : dict
        A copy of the connection settings.
    link : str
        The link's name (the protocol's ``link_key`` of ``connection``).
    channels : int
        Channels on the link (≥ 1).
    fs : float
        Loop rate (Hz, > 0).
    heartbeat_hz : float
        Heartbeat frames per second per channel (0: none).
    """

    connection: dict[str, Any]
    link: str
    channels: int
    fs: float
    heartbeat_hz: float

    @property
    def base(self) -> dict[str, Any]:
        """The :class:`~rths_hil.linkbudget.LinkLoad` fields the inputs fill (``channels``,
        ``fs``)."""
        return {"channels": self.channels, "fs": self.fs}


def link_model(
    link_key: Callable[[dict[str, Any]], str],
) -> Callable[[Callable[[LinkInputs], LinkLoad]], Callable[..., LinkLoad]]:
    """Decorator: a protocol's ``link_load`` hook from its link model, a function of the
    checked inputs (:class:`LinkInputs`, the link named by ``link_key``).

    The hook takes ``(connection, channels_on_link, fs, *, heartbeat_hz=0.0)``
    (:attr:`Protocol.link_load`); a channel count below 1 or a loop rate that is not a positive
    number is refused (:class:`~rths_hil.errors.InputError`) before the model runs.
    """

    def wrap(model: Callable[[LinkInputs], LinkLoad]) -> Callable[..., LinkLoad]:
        def link_load(
            connection: dict[str, Any],
            channels_on_link: int,
            fs: float,
            *,
            heartbeat_hz: float = 0.0,
        ) -> LinkLoad:
            c, base = link_inputs(connection, channels_on_link, fs)
            return model(
                LinkInputs(c, link_key(c), base["channels"], base["fs"], float(heartbeat_hz))
            )

        for attr in ("__module__", "__name__", "__qualname__", "__doc__"):
            setattr(link_load, attr, getattr(model, attr))
        return link_load

    return wrap


def _no_advice(load: LinkLoad, limit: float) -> list[str]:
    return []


def _no_check(channels: list[ChannelUse]) -> None:
    return None


def _never(connection: dict[str, Any]) -> bool:
    return False


@dataclass(frozen=True)
class Protocol:
    """The planning facts of one protocol (one driver name).

    Attributes
    ----------
    name : str
        The driver name (``driver.name``).
    driver : type
        The :class:`~rths_hil.drivers.base.Driver` subclass that speaks it.
    link_key : callable, optional
        ``(connection) -> str``: the name of the physical link a connection uses; equal names
        share one link. Default: the driver name and its sorted settings (every channel its
        own link).
    link_load : callable, optional
        ``(connection, channels_on_link, fs, *, heartbeat_hz) ->``
        :class:`~rths_hil.linkbudget.LinkLoad`: the link's load at loop rate ``fs`` (the link
        model of the protocol's package, written with :func:`link_model`). Default: frame
        sizes unknown, not checked.
    link_advice : callable
        ``(load, limit) -> list[str]``: what else would bring a link of this protocol (its
        ``load.kind``) under ``limit`` (a higher bit or baud rate, another transport).
    check_sharing : callable
        ``(channels) -> None``: refuse channels that cannot share their link, one line starting
        ``actuators: …`` (:class:`~rths_hil.errors.InputError`); ``channels`` are
        :data:`ChannelUse` tuples of every channel using this driver.
    own_link : callable
        ``(connection) -> bool``: a channel with a twin gets a link of its own
        (:func:`default_own_link`).
    inline_twin : callable
        ``(connection) -> bool``: the twin can be served from the loop's thread
        (``twin.inline``). Default: never.
    profile_protocol : str or None
        The ``protocol`` of the controller profiles this driver takes (``driver.profile``), or
        ``None``: a profile format, a protocol package's ``profile_format`` module, named
        after the package (:func:`rths_hil.drivers.registry.profile_formats`).
    profile_driver : callable or None
        ``() -> type[Driver]``: the driver class that speaks such a profile.
    path_keys : tuple of str
        Connection settings that are file paths (resolved relative to the config file).
    serve_options : callable or None
        ``(group) -> None``: add the protocol's own ``rths-hil twin serve`` options to an
        :mod:`argparse` argument group (its twin endpoint's ``connection_from_args`` reads
        them). Protocols on one kind of line share one function (CANopen uses CAN's); the
        command adds each function once. Default: none beyond the command's own.
    """

    name: str
    driver: type[Driver]
    link_key: Callable[[dict[str, Any]], str] | None = None
    link_load: Callable[..., LinkLoad] | None = None
    link_advice: Callable[[LinkLoad, float], list[str]] = _no_advice
    check_sharing: Callable[[list[ChannelUse]], None] = _no_check
    own_link: Callable[[dict[str, Any]], bool] = default_own_link
    inline_twin: Callable[[dict[str, Any]], bool] = _never
    profile_protocol: str | None = None
    profile_driver: Callable[[], type[Driver]] | None = None
    path_keys: tuple[str, ...] = field(default=())
    serve_options: Callable[[argparse._ArgumentGroup], None] | None = None

    def __post_init__(self) -> None:
        name = self.name
        if self.link_key is None:

            def key(connection: dict[str, Any]) -> str:
                c = dict(connection or {})
                return f"{name} " + ",".join(f"{k}={c[k]}" for k in sorted(c))

            object.__setattr__(self, "link_key", key)
        if self.link_load is None:

            @link_model(self.link_key)  # type: ignore[arg-type]
            def load(i: LinkInputs) -> LinkLoad:
                return LinkLoad(
                    i.link, None, f"driver {name!r}: frame sizes unknown, not checked", **i.base
                )

            object.__setattr__(self, "link_load", load)

    def profile_driver_class(self) -> type[Driver]:
        """The driver class that speaks a profile of :attr:`profile_protocol`.

        Raises
        ------
        InputError
            This driver takes no profile.
        """
        if self.profile_driver is None:
            raise InputError(f"driver {self.name!r} takes no profile")
        return self.profile_driver()

    def connection_keys(self, profile: bool = False) -> dict[str, Key] | None:
        """The connection settings the protocol's driver declares (``CONNECTION``).

        Parameters
        ----------
        profile : bool
            Those of the driver that speaks a lab's profile (:meth:`profile_driver_class`).

        Returns
        -------
        dict of str to Key or None
            Name → :class:`~rths_hil.config.Key`; ``None`` when the class declares none (its
            constructor's signature is checked instead).
        """
        cls = self.profile_driver_class() if profile else self.driver
        keys = getattr(cls, "CONNECTION", None)
        return None if keys is None else dict(keys)

    @classmethod
    def from_hooks(cls, name: str, driver: type[Driver], hooks: Any, **facts: Any) -> Protocol:
        """The descriptor whose planning hooks are the functions of ``hooks`` named as them.

        Parameters
        ----------
        name : str
            The driver name.
        driver : type
            The driver class.
        hooks : module or class
            Where the hooks are (a protocol package's link model module, a driver class): its
            attributes named as one of :data:`HOOKS`; a hook it lacks keeps the default.
        **facts
            The other attributes (``profile_protocol``, ``path_keys`` …).
        """
        found = {h: getattr(hooks, h) for h in HOOKS if hasattr(hooks, h)}
        return cls(name=name, driver=driver, **found, **facts)

    @classmethod
    def from_driver(cls, name: str, driver: type[Driver]) -> Protocol:
        """The descriptor of a driver class registered on its own (a lab's entry point).

        Its class methods named as the hooks (:data:`HOOKS`), its ``profile_protocol`` and
        ``profile_driver``, its ``path_keys`` and ``serve_options``, where it has them; the
        defaults otherwise.
        """
        return cls.from_hooks(
            name,
            driver,
            driver,
            profile_protocol=getattr(driver, "profile_protocol", None),
            profile_driver=getattr(driver, "profile_driver", None),
            path_keys=tuple(getattr(driver, "path_keys", ())),
            serve_options=getattr(driver, "serve_options", None),
        )

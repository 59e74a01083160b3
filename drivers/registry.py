"""Driver registry: a driver name → its protocol descriptor, its driver class, a built driver.

Three sources, in the style of python-can's ``BACKENDS`` plus entry points:

* :data:`BUILTIN` — the protocols shipped here (``can``, ``canopen``, ``modbus``, ``serial``),
  by name → the ``"module:PROTOCOL"`` of the protocol's package, imported only when asked for.
  A protocol added to this repository gets one line here.
* the ``rths_hil.drivers`` entry-point group — a lab's own driver package, installed beside
  rths_hil, declares in its ``pyproject.toml``::

      [project.entry-points."rths_hil.drivers"]
      mylab = "mylab_driver:MyLabDriver"      # a Driver subclass, or
      toy = "toy_protocol:PROTOCOL"           # its Protocol descriptor

  A :class:`~rths_hil.drivers.base.Driver` subclass gets a descriptor built from its class
  (:meth:`~rths_hil.drivers.protocol.Protocol.from_driver`).
* :func:`register` — a descriptor added at run time (a test, a script).

The driver class takes its connection settings as keyword arguments. A class that declares
them (``CONNECTION``: name → :class:`~rths_hil.config.Key`, as every built-in driver does) has
them read by :func:`~rths_hil.config.check_table`, the validator of the run configuration,
profiles and model files (:func:`check_connection`); a lab's class without it has the names
checked against its constructor's signature. With a twin, the settings go to the twin's
endpoint, which declares those it takes the same way (``TwinEndpoint.CONNECTION``): they are
read against both. An entry point with a built-in name replaces the
built-in driver; a registered descriptor replaces both.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from rths_hil.errors import InputError
from rths_hil.keys import REQUIRED
from rths_hil.plugins import load_target
from rths_hil.plugins import targets as plugin_targets

from .base import Driver
from .protocol import Protocol

if TYPE_CHECKING:
    from rths_hil.keys import Key

__all__ = [
    "BUILTIN",
    "DEFAULT",
    "ENTRY_POINT_GROUP",
    "available",
    "check_connection",
    "create_driver",
    "driver_class",
    "protocol",
    "register",
    "unregister",
]

ENTRY_POINT_GROUP = "rths_hil.drivers"

#: The protocols shipped with rths_hil: driver name → ``"module:PROTOCOL"``.
BUILTIN: dict[str, str] = {
    "can": "rths_hil.drivers.can:PROTOCOL",
    "modbus": "rths_hil.drivers.modbus:PROTOCOL",
    "serial": "rths_hil.drivers.serial:PROTOCOL",
    "canopen": "rths_hil.drivers.canopen:PROTOCOL",
}
#: The driver a configuration uses when it names none (``driver.name``).
DEFAULT = "can"

_REGISTERED: dict[str, Protocol] = {}


def register(proto: Protocol) -> None:
    """Add (or replace) the protocol ``proto.name`` for this process."""
    if not isinstance(proto, Protocol):
        raise InputError(f"register: {proto!r} is not a rths_hil.drivers.protocol.Protocol")
    _REGISTERED[proto.name] = proto


def unregister(name: str) -> None:
    """Remove a protocol added by :func:`register` (nothing when there is none)."""
    _REGISTERED.pop(name, None)


def available() -> dict[str, str]:
    """Map every known driver name to its ``module:attr`` target.

    A protocol added by :func:`register` maps to ``"(registered)"``.
    """
    found = plugin_targets(ENTRY_POINT_GROUP, BUILTIN)
    found.update({name: "(registered)" for name in _REGISTERED})
    return found


def protocol(name: str) -> Protocol:
    """The protocol descriptor of driver ``name``.

    Raises
    ------
    InputError
        No driver has that name, or its entry point is neither a Driver subclass nor a
        Protocol.
    """
    if name in _REGISTERED:
        return _REGISTERED[name]
    targets = plugin_targets(ENTRY_POINT_GROUP, BUILTIN)
    if name not in targets:
        known = sorted({*targets, *_REGISTERED})
        raise InputError(f"unknown driver {name!r}; available: {', '.join(known)}")
    target = targets[name]
    obj = load_target(target, None, "driver entry point")
    if isinstance(obj, Protocol):
        proto = obj
    elif isinstance(obj, type) and issubclass(obj, Driver):
        proto = Protocol.from_driver(name, obj)
    else:
        raise InputError(
            f"driver entry point {target!r} is not a rths_hil.drivers.base.Driver subclass "
            "(nor a rths_hil.drivers.protocol.Protocol)"
        )
    return proto


def driver_class(name: str) -> type[Driver]:
    """Return the driver class registered under ``name``.

    Raises
    ------
    InputError
        If no driver has that name.
    """
    return protocol(name).driver


def check_connection(
    cls: type[Driver],
    connection: Mapping[str, Any],
    where: str = "",
    path: str = "driver.connection",
    *,
    defaults: bool = True,
    twin: bool = False,
    twin_keys: Mapping[str, Key] | None = None,
) -> dict[str, Any]:
    """``connection`` (without ``profile``) as driver class ``cls`` takes it.

    A class that declares ``CONNECTION`` has it read by :func:`~rths_hil.config.check_table`
    (types, SI units, ranges, choices; an unknown key gets the closest known one); a class
    without it has the names checked against its constructor's signature.

    Parameters
    ----------
    cls : type
        The driver class.
    connection : mapping
        The connection settings as configured.
    where : str
        The source, first in every message (``run.toml``); empty for none.
    path : str
        The settings' key path in messages (``driver.connection``).
    defaults : bool
        Fill the keys not given with their declared defaults (``False``: only those given).
    twin : bool
        The settings go to a twin first (:func:`rths_hil.sim_backends.twin.start_twin`), which
        fills in the line and the files the driver needs and takes settings of its own (the
        serial twin's ``transport``): a required key of the driver may be missing. Without
        ``twin_keys`` only the keys the driver declares are read, the others are passed on as
        given (the twin's constructor checks them).
    twin_keys : mapping of str to Key, optional
        With ``twin``: the settings the twin's endpoint takes (its ``CONNECTION``,
        :func:`rths_hil.sim_backends.twin.twin_keys`). A key neither declares is unknown (the
        closest of either named); a key of the driver's is read by its key, then every key
        by the twin's; a key of the driver's the twin does not take is refused (the twin
        gives the driver its line). Only the keys given are returned (the twin fills in the
        rest), whatever ``defaults``.

    Returns
    -------
    dict
        The settings coerced to their keys' types and SI units (as given, for a class without
        ``CONNECTION`` and a twin without ``twin_keys``).

    Raises
    ------
    InputError
        One line ``where: path.key: what is wrong``.
    """
    from rths_hil.config import check_table

    keys = None if cls.CONNECTION is None else dict(cls.CONNECTION)
    if twin and twin_keys is not None:
        return _check_with_twin(connection, keys or {}, dict(twin_keys), where, path)
    if keys is None:
        if not twin:
            _check_signature(cls, connection, where, path)
        return dict(connection)
    if not twin:
        return check_table(connection, keys, where, path, defaults=defaults)
    keys = _optional(keys)
    ours = {k: v for k, v in connection.items() if k in keys}
    checked = check_table(ours, keys, where, path, defaults=defaults)
    return {k: checked[k] if k in checked else v for k, v in connection.items()} | checked


def _optional(keys: dict[str, Key]) -> dict[str, Key]:
    """``keys`` with a required key optional (a twin fills it in)."""
    return {k: replace(v, default=None) if v.default is REQUIRED else v for k, v in keys.items()}


def _check_with_twin(
    connection: Mapping[str, Any],
    keys: dict[str, Key],
    twin_keys: dict[str, Key],
    where: str,
    path: str,
) -> dict[str, Any]:
    """``connection`` read against the driver's ``keys`` and its twin's ``twin_keys``.

    See :func:`check_connection` with ``twin_keys``; returns the keys given, as the twin takes
    them.
    """
    from rths_hil.config import check_table, unknown_key

    pre = f"{where}: " if where else ""
    known = {**keys, **twin_keys}
    for name in connection:
        if name not in known:
            raise InputError(f"{pre}{unknown_key(f'{path}.{name}', str(name), known)}")
    # the driver's reading first (its ranges): the values reach it through the twin
    keys = _optional(keys)
    given = {k: v for k, v in connection.items() if k in keys}
    check_table(given, keys, where, path, defaults=False)
    for name in connection:
        if name not in twin_keys:
            raise InputError(
                f"{pre}{path}.{name}: not a setting of the twin (twin.enabled = true: the twin "
                f"gives the driver its line); the twin's keys: {', '.join(twin_keys)}"
            )
    return check_table(connection, twin_keys, where, path, defaults=False)


def _check_signature(
    cls: type[Driver], connection: Mapping[str, Any], where: str, path: str
) -> None:
    """Refuse a setting ``cls.__init__`` does not take (a class without ``CONNECTION``)."""
    params = inspect.signature(cls.__init__).parameters
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return
    kinds = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    accepted = sorted(n for n, p in params.items() if n != "self" and p.kind in kinds)
    unknown = sorted(set(connection) - set(accepted))
    if unknown:
        pre = f"{where}: " if where else ""
        raise InputError(
            f"{pre}{path}: unknown connection setting(s) {', '.join(unknown)}; "
            f"accepted: {', '.join(accepted)}"
        )


def create_driver(name: str, **connection: Any) -> Driver:
    """Build (not open) the driver ``name`` with its connection settings.

    The settings are read by :func:`check_connection` (``profile`` aside: a lab's profile
    picks the protocol's profile driver); the driver is built with the values coerced, the
    keys not given at their declared defaults.

    Raises
    ------
    InputError
        Unknown driver name, or a connection setting the driver does not take (one line
        ``driver.connection.KEY: …``).
    """
    proto = protocol(name)
    cls = proto.driver
    connection = dict(connection)
    profile = connection.pop("profile", None)
    from .profile import is_builtin

    if not is_builtin(profile):
        cls = proto.profile_driver_class()
    values = check_connection(cls, connection)
    if not is_builtin(profile):
        values["profile"] = profile
    return cls(**values)

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

The driver class takes its connection settings as keyword arguments. An entry point with a
built-in name replaces the built-in driver; a registered descriptor replaces both.
"""

from __future__ import annotations

import inspect
from typing import Any

from rths_hil.errors import InputError
from rths_hil.plugins import load_target
from rths_hil.plugins import targets as plugin_targets

from .base import Driver
from .protocol import Protocol

__all__ = [
    "BUILTIN",
    "DEFAULT",
    "ENTRY_POINT_GROUP",
    "available",
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


def create_driver(name: str, **connection: Any) -> Driver:
    """Build (not open) the driver ``name`` with its connection settings.

    Raises
    ------
    InputError
        Unknown driver name, or a connection key the driver does not take.
    """
    proto = protocol(name)
    cls = proto.driver
    connection = dict(connection)
    profile = connection.pop("profile", None)
    from .profile import is_builtin

    if not is_builtin(profile):
        cls = proto.profile_driver_class()
        connection["profile"] = profile
    params = inspect.signature(cls.__init__).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        accepted = [n for n, p in params.items() if n != "self" and p.kind is p.KEYWORD_ONLY]
        accepted += [
            n for n, p in params.items() if n != "self" and p.kind is p.POSITIONAL_OR_KEYWORD
        ]
        unknown = sorted(set(connection) - set(accepted))
        if unknown:
            raise InputError(
                f"driver {name!r}: unknown connection setting(s) {', '.join(unknown)}; "
                f"accepted: {', '.join(sorted(accepted))}"
            )
    return cls(**connection)

"""Driver registry: find a driver class by name and build it from connection settings.

Two sources, in the style of python-can's ``BACKENDS`` plus entry points:

* :data:`BUILTIN` — the drivers shipped here (``can``, ``modbus``, ``serial``), by name →
  ``"module:Class"``, imported only when asked for. A driver added to this repository gets one
  line here.
* the ``rths_hil.drivers`` entry-point group — a lab's own driver package, installed beside
  rths_hil, declares in its ``pyproject.toml``::

      [project.entry-points."rths_hil.drivers"]
      mylab = "mylab_driver:MyLabDriver"

The class must subclass :class:`rths_hil.drivers.base.Driver` and take its connection settings as
keyword arguments. An entry point with a built-in name replaces the built-in driver.
"""

from __future__ import annotations

import inspect
from typing import Any

from rths_hil.errors import InputError
from rths_hil.plugins import load_target
from rths_hil.plugins import targets as plugin_targets

from .base import Driver

ENTRY_POINT_GROUP = "rths_hil.drivers"

#: The drivers shipped with rths_hil: name → ``"module:Class"``.
BUILTIN: dict[str, str] = {
    "can": "rths_hil.drivers.can:CANDriver",
    "modbus": "rths_hil.drivers.modbus:ModbusDriver",
    "serial": "rths_hil.drivers.serial:SerialDriver",
    "canopen": "rths_hil.drivers.canopen:CANopenDriver",
}


def _load(target: str) -> type[Driver]:
    cls: type[Driver] = load_target(target, Driver, "driver entry point")
    return cls


def available() -> dict[str, str]:
    """Map every known driver name to its ``module:Class`` target."""
    return plugin_targets(ENTRY_POINT_GROUP, BUILTIN)


def driver_class(name: str) -> type[Driver]:
    """Return the driver class registered under ``name``.

    Raises
    ------
    InputError
        If no driver has that name.
    """
    targets = available()
    if name not in targets:
        raise InputError(f"unknown driver {name!r}; available: {', '.join(sorted(targets))}")
    return _load(targets[name])


def create_driver(name: str, **connection: Any) -> Driver:
    """Build (not open) the driver ``name`` with its connection settings.

    Raises
    ------
    InputError
        Unknown driver name, or a connection key the driver does not take.
    """
    cls = driver_class(name)
    connection = dict(connection)
    profile = connection.pop("profile", None)
    from .profile import is_builtin

    if not is_builtin(profile):
        cls = cls.profile_driver()
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

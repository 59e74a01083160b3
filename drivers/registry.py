"""Driver registry: a driver name → its protocol descriptor, its driver class, a built driver.

Three sources, in the style of python-can's ``BACKENDS`` plus entry points:

* the protocols shipped here, **found, not listed**: each sub-package of ``rths_hil.drivers``
  (a folder under ``drivers/``) is the protocol of its folder's name and exports its
  :class:`~rths_hil.drivers.protocol.Protocol` as ``PROTOCOL`` (:func:`builtin`: ``can``,
  ``canopen``, ``modbus``, ``serial``). The folders are listed, not imported: a package is
  imported when its driver is asked for. A protocol added to this repository is one folder,
  no line here; its controller-profile format, if it has one, is the folder's
  ``profile_format`` module (:func:`profile_formats`), and its twin the endpoint module of its
  name (:func:`rths_hil.sim_backends.registry.builtin_twins`).
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

import functools
import importlib
import inspect
import os
import pkgutil
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
    "builtin",
    "check_connection",
    "clear_cache",
    "create_driver",
    "driver_class",
    "profile_formats",
    "protocol",
    "register",
    "unregister",
]

ENTRY_POINT_GROUP = "rths_hil.drivers"

#: The protocols shipped with rths_hil: driver name → ``"module:PROTOCOL"``, sorted by name
#: (:func:`builtin`, found when first read: there is no list to edit).
BUILTIN: dict[str, str]
#: The driver a configuration uses when it names none (``driver.name``); :func:`builtin`
#: checks that its package is there.
DEFAULT = "can"

_REGISTERED: dict[str, Protocol] = {}


def __getattr__(name: str) -> Any:
    if name == "BUILTIN":
        return builtin()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _package() -> Any:
    """The package ``rths_hil.drivers`` (its ``__path__`` is where the protocols are)."""
    return importlib.import_module(__package__ or "rths_hil.drivers")


@functools.lru_cache(maxsize=8)
def _folders(path: tuple[str, ...]) -> tuple[str, ...]:
    """The sub-packages in the folders ``path``, sorted (listed by pkgutil, not imported)."""
    return tuple(sorted({m.name for m in pkgutil.iter_modules(path) if m.ispkg}))


def builtin() -> dict[str, str]:
    """The protocols shipped with rths_hil: driver name → ``"module:PROTOCOL"``, by name.

    Each sub-package of ``rths_hil.drivers`` (in every folder of its ``__path__``) is the
    protocol of its folder's name; its ``PROTOCOL`` (a descriptor of that name) is checked
    when :func:`protocol` imports it. Listed once per ``__path__`` (:func:`clear_cache`);
    nothing is imported.

    Raises
    ------
    RuntimeError
        The package of :data:`DEFAULT` is not there (an installation without it).
    """
    pkg = _package()
    found = {name: f"{pkg.__name__}.{name}:PROTOCOL" for name in _folders(tuple(pkg.__path__))}
    if DEFAULT not in found:
        raise RuntimeError(
            f"rths_hil.drivers: no package of the default driver {DEFAULT!r} (found: "
            f"{', '.join(found) or 'none'}); the installation is incomplete"
        )
    return found


@functools.lru_cache(maxsize=8)
def _formats(path: tuple[str, ...], prefix: str) -> tuple[str, ...]:
    """The protocol packages in ``path`` that have a ``profile_format`` module, sorted."""
    out = []
    for name in _folders(path):
        inside = [os.path.join(folder, name) for folder in path]
        if any(m.name == "profile_format" for m in pkgutil.iter_modules(inside)):
            out.append(name)
    return tuple(out)


def profile_formats() -> dict[str, str]:
    """The controller-profile formats (a profile's ``protocol``) → ``"module:load"``, by name.

    A protocol package with a ``profile_format`` module has a profile format of its name
    (``protocol = "modbus"`` in a profile: ``rths_hil.drivers.modbus.profile_format``); the
    module defines ``load(source, data, base)`` (the profile ``source``, its TOML ``data``,
    ``base`` the folder relative paths in it start from → a
    :class:`~rths_hil.drivers.profile.ProfileFormat`). Listed, not imported
    (:func:`rths_hil.drivers.profile.load_profile` imports the one a profile names).
    """
    pkg = _package()
    return {
        name: f"{pkg.__name__}.{name}.profile_format:load"
        for name in _formats(tuple(pkg.__path__), f"{pkg.__name__}.")
    }


def clear_cache() -> None:
    """Forget the protocol packages and profile formats listed.

    A test that changes ``rths_hil.drivers.__path__`` leaves none of it behind (a changed
    ``__path__`` is listed anew anyway).
    """
    _folders.cache_clear()
    _formats.cache_clear()


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

    The built-in protocols (:func:`builtin`), then the entry points; a protocol added by
    :func:`register` maps to ``"(registered)"``.
    """
    found = plugin_targets(ENTRY_POINT_GROUP, builtin())
    found.update({name: "(registered)" for name in _REGISTERED})
    return found


def protocol(name: str) -> Protocol:
    """The protocol descriptor of driver ``name``.

    Only the package of that driver is imported.

    Raises
    ------
    InputError
        No driver has that name, its entry point is neither a Driver subclass nor a
        Protocol, or a built-in package's ``PROTOCOL`` is not a Protocol of its folder's name.
    """
    if name in _REGISTERED:
        return _REGISTERED[name]
    shipped = builtin()
    targets = plugin_targets(ENTRY_POINT_GROUP, shipped)
    if name not in targets:
        known = sorted({*targets, *_REGISTERED})
        raise InputError(f"unknown driver {name!r}; available: {', '.join(known)}")
    target = targets[name]
    obj = load_target(target, None, "driver entry point")
    if target == shipped.get(name):
        if not isinstance(obj, Protocol) or obj.name != name:
            raise InputError(
                f"driver package {target.partition(':')[0]}: PROTOCOL must be a "
                f"rths_hil.drivers.protocol.Protocol named {name!r} (its folder's name), "
                f"got {getattr(obj, 'name', obj)!r}"
            )
        return obj
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

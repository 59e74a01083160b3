"""The twins' registries: where a twin endpoint, an actuator model or an effect is added.

Three tables, in the style of python-can's ``BACKENDS`` (name → where the class lives, imported
only when asked for):

* :data:`TWINS` — driver name → the endpoint that speaks that driver's protocol, **found, not
  listed** (:func:`builtin_twins`): the module of :mod:`rths_hil.sim_backends.endpoints` named
  after a driver shipped here (``endpoints/can.py`` for ``drivers/can/``) is its twin, and says
  so at its top level::

      TWIN = TwinEntry("rths_hil.sim_backends.endpoints.can:CANTwin", fresh_channel=True)

  (the module is imported when its twin is asked for), plus the ``rths_hil.twins`` entry-point
  group, so a lab's driver package ships its twin beside its driver (same name in both
  groups)::

      [project.entry-points."rths_hil.twins"]
      mylab = "mylab_driver:MyLabTwin"

  :func:`rths_hil.sim_backends.twin.start_twin`, the plan and ``rths-hil twin serve`` ask it
  (:func:`available_twins`, :func:`twin_class`). The driver registry beside it finds the
  protocol packages the same way (:func:`rths_hil.drivers.registry.builtin`) with the
  ``rths_hil.drivers`` group.
* :data:`MODELS` — actuator model name (a model file's ``actuator.model``) → the
  :class:`~rths_hil.sim_backends.base.ActuatorModel` in front of the transport delay and gain of
  the FEI paper's Fig. 4.1, with its parameters.
  :func:`rths_hil.sim_backends.models.make_model` and the model file ask it.
* :data:`rths_hil.sim_backends.effects.EFFECTS` — effect kind →
  :class:`~rths_hil.sim_backends.effects.Effect` subclass (each class carries everything the twin
  and the diagnosis know about it).

This module holds tables and lookups only: it builds nothing (a plant is built by
:func:`rths_hil.sim_backends.modelfile.build_plant`) and imports no module that imports it.

Adding a model or an effect touches one module (the class) and one line here (or in
``EFFECTS``), see docs/models.md, "Adding a twin model or an effect"; adding a twin endpoint
touches its module alone (named after its driver, with its ``TWIN``), see docs/protocols.md,
"Adding a driver".
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rths_hil.errors import InputError
from rths_hil.plugins import targets as plugin_targets

from .benchmark import BENCHMARK_NOMINAL, BenchmarkServo
from .effects import EFFECTS

__all__ = [
    "EFFECTS",
    "MODELS",
    "TWINS",
    "ModelEntry",
    "TwinEntry",
    "available_twins",
    "builtin_entry",
    "builtin_twins",
    "model_class",
    "model_entry",
    "twin_class",
]


@dataclass(frozen=True)
class TwinEntry:
    """A twin endpoint.

    The endpoint module of a driver shipped here declares its own, as ``TWIN = TwinEntry(...)``
    (:func:`builtin_entry`); a lab's twin describes itself with class attributes of its
    endpoint (:func:`twin_class`).

    Attributes
    ----------
    target : str
        ``"module:Class"`` of the :class:`~rths_hil.sim_backends.endpoints.base.TwinEndpoint`
        subclass.
    seq_bits : int or None
        Width of the sequence counter the protocol's frames carry (the controller checks and
        echoes it); ``None`` when the protocol has none.
    transports : tuple of str
        Transports ``rths-hil twin serve --transport`` accepts, the default first (empty: the
        endpoint's own settings, e.g. a python-can interface).
    fresh_channel : bool
        The ``channel`` setting defaults to a fresh unique name (python-can's ``virtual`` bus:
        twins started in one process must not hear each other).
    """

    target: str
    seq_bits: int | None = 16
    transports: tuple[str, ...] = ()
    fresh_channel: bool = False


#: Twin endpoints by the name of the driver whose protocol they speak, sorted by name
#: (every :func:`builtin_entry`, computed when read: each endpoint module is imported).
TWINS: dict[str, TwinEntry]


def __getattr__(name: str) -> Any:
    if name == "TWINS":
        return {driver: builtin_entry(driver) for driver in builtin_twins()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def builtin_twins() -> dict[str, str]:
    """The twin endpoints shipped with rths_hil: driver name → its module, by name.

    A driver shipped here (:func:`rths_hil.drivers.registry.builtin`) has a twin when
    :mod:`rths_hil.sim_backends.endpoints` (in any folder of its ``__path__``) has a module of
    its name; listed, not imported (:func:`builtin_entry` imports one).
    """
    from rths_hil.drivers.registry import builtin

    pkg = importlib.import_module(f"{__package__ or 'rths_hil.sim_backends'}.endpoints")
    here = {m.name for m in pkgutil.iter_modules(pkg.__path__)}
    return {name: f"{pkg.__name__}.{name}" for name in builtin() if name in here}


def builtin_entry(driver_name: str) -> TwinEntry:
    """The :class:`TwinEntry` the endpoint module of ``driver_name`` declares (``TWIN``).

    Raises
    ------
    InputError
        No endpoint module of that name, or its ``TWIN`` is not a :class:`TwinEntry`.
    """
    module = builtin_twins().get(driver_name)
    if module is None:
        raise InputError(f"no twin endpoint module for driver {driver_name!r}")
    entry = getattr(importlib.import_module(module), "TWIN", None)
    if not isinstance(entry, TwinEntry):
        raise InputError(
            f"twin endpoint {module}: TWIN must be a rths_hil.sim_backends.registry.TwinEntry, "
            f"got {entry!r}"
        )
    return entry


@dataclass(frozen=True)
class ModelEntry:
    """An actuator model.

    Attributes
    ----------
    target : str
        ``"module:Class"`` of the :class:`~rths_hil.sim_backends.base.ActuatorModel`, built as
        ``Class(dt=dt, **params)``; empty for the bare delay and gain.
    params : dict
        Parameter name → (default, or ``None`` when required; SI unit).
    doc : str
        One line for the documentation and error messages.
    uses_specimen : bool
        The model takes ``specimen_stiffness``, ``specimen_damping`` and ``specimen_mass`` from
        a model file's ``[specimen]`` unless set in ``[actuator]`` (one specimen loads the
        actuator and produces the measured force).
    """

    target: str
    params: Mapping[str, tuple[float | None, str]]
    doc: str = ""
    uses_specimen: bool = False


def _benchmark_params() -> dict[str, tuple[float | None, str]]:
    """``BenchmarkServo.PARAMS`` with their defaults (Table 2, or the constructor's own)."""
    own = inspect.signature(BenchmarkServo.__init__).parameters
    return {
        k: (BENCHMARK_NOMINAL[k] if k in BENCHMARK_NOMINAL else own[k].default, "")
        for k in BenchmarkServo.PARAMS
    }


#: Actuator models by the name a model file's ``actuator.model`` uses.
MODELS: dict[str, ModelEntry] = {
    "delay_gain": ModelEntry("", {}, "transport delay and gain only (the FEI paper, Fig. 4.1)"),
    "servo_lag": ModelEntry(
        "rths_hil.sim_backends.first_order:FirstOrderServo",
        {"time_constant": (None, "s")},
        "first-order servo lag 1/(T s + 1)",
    ),
    "benchmark": ModelEntry(
        "rths_hil.sim_backends.benchmark:BenchmarkServo",
        _benchmark_params(),
        "servo-hydraulic plant of the RTHS benchmark (Silva et al. 2020)",
        uses_specimen=True,
    ),
}

#: Names a model file may still use for a model of :data:`MODELS` (read as the new name).
MODEL_ALIASES: dict[str, str] = {"first_order": "servo_lag"}


def _load(target: str) -> Any:
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


#: Entry-point group of twins shipped by other packages (name = the driver's name).
TWIN_ENTRY_POINT_GROUP = "rths_hil.twins"

#: The base class every twin endpoint derives from (loaded like the entries: the endpoints
#: import this registry).
TWIN_ENDPOINT = "rths_hil.sim_backends.endpoints.base:TwinEndpoint"


def available_twins() -> dict[str, str]:
    """Every driver name a twin exists for → where its endpoint is.

    The built-in twins (:func:`builtin_twins`) as ``"<endpoint module>:TWIN"`` (its
    :class:`TwinEntry`), then the entry points as ``"module:Class"``; an entry point with a
    built-in name replaces the built-in twin.
    """
    shipped = {name: f"{module}:TWIN" for name, module in builtin_twins().items()}
    return plugin_targets(TWIN_ENTRY_POINT_GROUP, shipped)


def twin_class(driver_name: str) -> tuple[type, TwinEntry]:
    """The endpoint class and its entry for ``driver_name``.

    A twin from an entry point describes itself with class attributes of its endpoint
    (``seq_bits``, ``transports``, ``fresh_channel``; :class:`TwinEntry` documents them).

    Raises
    ------
    InputError
        No twin speaks that driver's protocol, or the entry point is not a TwinEndpoint.
    """
    targets = available_twins()
    target = targets.get(driver_name)
    if target is None:
        raise InputError(
            f"no twin for driver {driver_name!r}; twins exist for {', '.join(sorted(targets))}"
        )
    module = builtin_twins().get(driver_name)
    if module is not None and target == f"{module}:TWIN":
        entry = builtin_entry(driver_name)
        return _load(entry.target), entry
    try:
        cls = _load(target)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"twin entry point {driver_name!r} = {target!r}: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, _load(TWIN_ENDPOINT))):
        raise InputError(
            f"twin entry point {target!r} is not a "
            "rths_hil.sim_backends.endpoints.base.TwinEndpoint"
        )
    entry = TwinEntry(
        target,
        seq_bits=getattr(cls, "seq_bits", 16),
        transports=tuple(getattr(cls, "transports", ())),
        fresh_channel=bool(getattr(cls, "fresh_channel", False)),
    )
    return cls, entry


def model_entry(name: str) -> tuple[str, ModelEntry]:
    """``(canonical name, entry)`` of actuator model ``name`` (an alias gives its new name).

    Raises
    ------
    InputError
        Unknown model name.
    """
    name = MODEL_ALIASES.get(name, name)
    if name not in MODELS:
        raise InputError(f"unknown actuator model {name!r} (known: {', '.join(MODELS)})")
    return name, MODELS[name]


def model_class(name: str) -> type | None:
    """The actuator model class registered under ``name`` (``None`` for ``delay_gain``)."""
    _, entry = model_entry(name)
    return _load(entry.target) if entry.target else None

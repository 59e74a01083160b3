"""Start a virtual servo-hydraulic twin: a plant behind a real protocol endpoint.

>>> from rths_hil.sim_backends.twin import start_twin, default_plant
>>> from rths_hil.drivers.registry import create_driver
>>> with start_twin("modbus", default_plant()) as twin:            # doctest: +SKIP
...     with create_driver("modbus", **twin.connection) as drv:
...         drv.send(0, 0.001); fb = drv.receive(0.1)

``twin.connection`` holds exactly the keyword arguments the matching driver needs to reach the
twin (e.g. the TCP port actually bound when port 0 was asked, the pseudo-terminal path).
"""

from __future__ import annotations

import uuid
from typing import TYPE_CHECKING, Any

from rths_hil.drivers.profile import is_builtin

from rths_hil.errors import InputError

from .base import Plant
from .delay import DelayGain
from .endpoints.base import TwinController, TwinEndpoint
from .faults import Faults
from .force import DEFAULT_LOOP_GAIN, ForcePlant
from .plant import TwinPlant
from .registry import twin_class
from .specimen import KelvinVoigt

if TYPE_CHECKING:
    from rths_hil.keys import Key

__all__ = ["default_force_plant", "default_plant", "start_twin", "twin_keys"]

#: Default step of the twins (s): the bridge's 1024 Hz loop.
DEFAULT_DT = 1.0 / 1024.0


def default_plant(
    delay: float = 0.020, gain: float = 1.0, stiffness: float = 1.0e6, dt: float = DEFAULT_DT
) -> TwinPlant:
    """The delay + gain actuator of the FEI paper's Fig. 4.1 (20 ms, gain 1) on a 1 MN/m
    spring, noiseless, at 1024 Hz."""
    return TwinPlant(DelayGain(delay, gain, dt), specimen=KelvinVoigt(stiffness, 0.0, dt))


def default_force_plant(
    delay: float = 0.005,
    gain: float = 1.0,
    stiffness: float = 1.19e6,
    loop_gain: float | None = None,
    dt: float = DEFAULT_DT,
) -> ForcePlant:
    """The force-controlled twin (:class:`~rths_hil.sim_backends.force.ForcePlant`): a 5 ms
    delay and gain 1 on the force set-point, then the closed force loop on a spring of
    ``stiffness`` (default the RTHS benchmark's 1.19 MN/m, a 4.2 ms loop at the default
    ``loop_gain``), noiseless, at 1024 Hz. A channel with ``control.mode = "force"`` or
    ``"load"`` gets this twin built from its ``[twin]`` tables
    (:func:`~rths_hil.sim_backends.force.force_plant`, ``twin.force_loop_gain``)."""
    return ForcePlant(
        KelvinVoigt(stiffness, 0.0, dt),
        DEFAULT_LOOP_GAIN if loop_gain is None else loop_gain,
        delay,
        gain,
    )


def twin_keys(driver_name: str, profile: bool = False) -> dict[str, Key] | None:
    """The settings the twin of ``driver_name`` takes (its endpoint's ``CONNECTION``).

    Parameters
    ----------
    driver_name : str
        A driver a twin exists for (:func:`~rths_hil.sim_backends.registry.available_twins`).
    profile : bool
        Those of the twin that speaks a lab's profile (the endpoint's ``profile_twin()``).

    Returns
    -------
    dict of str to Key or None
        Name → :class:`~rths_hil.keys.Key` (``profile`` aside: :func:`start_twin` takes it
        apart); ``None`` when the endpoint declares none (a lab's twin).

    Raises
    ------
    InputError
        No twin for that driver, or (``profile``) none of its protocol speaks a profile.
    """
    cls, _ = twin_class(driver_name)
    assert issubclass(cls, TwinEndpoint)  # a built-in twin is; twin_class checks an entry point
    if profile:
        cls = cls.profile_twin()
    keys = getattr(cls, "CONNECTION", None)
    return None if keys is None else dict(keys)


def start_twin(
    driver_name: str,
    plant: Plant,
    *,
    faults: Faults | None = None,
    heartbeat_timeout: float | None = None,
    initial_position: float = 0.0,
    threaded: bool = True,
    **connection: Any,
) -> TwinEndpoint:
    """Start the twin endpoint matching ``driver_name`` around ``plant``; return it running.

    Parameters
    ----------
    driver_name : str
        Which protocol to speak: a name of :data:`rths_hil.sim_backends.registry.TWINS` (``can``,
        ``modbus``, ``serial``).
    plant : Plant
        The plant stepped once per command.
    faults : Faults, optional
        Fault plan (:mod:`rths_hil.sim_backends.faults`).
    heartbeat_timeout : float, optional
        Heartbeat watchdog period (s); off by default.
    initial_position : float
        Where the twin's actuator sits at rest (m; :class:`TwinController`).
    threaded : bool
        Serve in a thread (default). ``False``: the caller serves with ``endpoint.pump()``
        (CAN on the ``virtual`` interface only; the lockstep loop's fast path).
    **connection
        Endpoint settings (the endpoint's ``CONNECTION``, :func:`twin_keys`; a run reads them
        from ``driver.connection`` before the twin starts). ``can``: ``interface``
        (``virtual``; ``slcan`` reaches other processes over a pseudo-terminal pair),
        ``channel`` (a fresh unique name by default; ``slcan``: ``pty``), ``bitrate``,
        ``dbc``, ``bus_options``. ``modbus``: ``transport``
        (``tcp`` or ``rtu``), ``host`` (127.0.0.1), ``port`` (0 = any free port), ``device_id``
        (1), ``device`` (RTU: serial device; default a new pseudo-terminal). ``serial``:
        ``transport`` (``pty`` or ``tcp``), ``host``, ``port``.

    Returns
    -------
    TwinEndpoint
        Running; a context manager that stops it. ``.connection`` holds the driver's kwargs.

    Raises
    ------
    InputError
        Unknown driver name or endpoint setting, or a transport that cannot be opened.
    """
    cls, entry = twin_class(driver_name)
    assert issubclass(cls, TwinEndpoint)  # a built-in twin is; twin_class checks an entry point
    profile = connection.pop("profile", None)
    if not is_builtin(profile):
        cls = cls.profile_twin()
        connection["profile"] = profile
    controller = TwinController(
        plant,
        faults,
        seq_bits=entry.seq_bits,
        heartbeat_timeout=heartbeat_timeout,
        initial_position=initial_position,
    )
    if entry.fresh_channel and connection.get("interface", "virtual") == "virtual":
        connection.setdefault("channel", f"rths-twin-{uuid.uuid4().hex[:8]}")
    try:
        endpoint: TwinEndpoint = cls(controller, **connection)
    except TypeError as exc:  # a setting the endpoint does not take, given past the plan
        raise InputError(f"twin {driver_name!r}: bad endpoint setting: {exc}") from None
    return endpoint.start(threaded)

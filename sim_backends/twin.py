"""Start a virtual servo-hydraulic twin: a plant behind a real protocol endpoint.

>>> from sim_backends.twin import start_twin, default_plant
>>> from drivers.registry import create_driver
>>> with start_twin("modbus", default_plant()) as twin:            # doctest: +SKIP
...     with create_driver("modbus", **twin.connection) as drv:
...         drv.send(0, 0.001); fb = drv.receive(0.1)

``twin.connection`` holds exactly the keyword arguments the matching driver needs to reach the
twin (e.g. the TCP port actually bound when port 0 was asked, the pseudo-terminal path).
"""

from __future__ import annotations

import uuid
from typing import Any

from rths_hil.errors import InputError

from .base import ActuatorModel, Plant
from .delay import DelayGain
from .endpoints.base import TwinController, TwinEndpoint
from .faults import Faults

__all__ = ["SpringPlant", "default_plant", "start_twin"]

#: Default step of the twins (s): the bridge's 1024 Hz loop.
DEFAULT_DT = 1.0 / 1024.0


class SpringPlant:
    """An actuator model driving a linear spring–dashpot specimen.

    ``force = stiffness · x + damping · (x - x_prev) / dt`` with ``x`` the model's displacement
    (backward-difference velocity). Satisfies :class:`sim_backends.base.Plant`.

    Parameters
    ----------
    model : ActuatorModel
        Command → displacement model (e.g. :class:`~sim_backends.delay.DelayGain`).
    stiffness : float
        Specimen stiffness (N/m).
    damping : float
        Specimen damping (N·s/m).
    """

    def __init__(self, model: ActuatorModel, stiffness: float = 1.0e6, damping: float = 0.0):
        self.model = model
        self.dt = model.dt
        self.stiffness = float(stiffness)
        self.damping = float(damping)
        self._prev = 0.0

    def reset(self) -> None:
        self.model.reset()
        self._prev = 0.0

    def step(self, command: float) -> tuple[float, float]:
        x = self.model.step(command)
        v = (x - self._prev) / self.dt
        self._prev = x
        return x, self.stiffness * x + self.damping * v


def default_plant(
    delay: float = 0.020, gain: float = 1.0, stiffness: float = 1.0e6, dt: float = DEFAULT_DT
) -> SpringPlant:
    """Seed Fig. 4.1 delay + gain actuator (20 ms, gain 1) on a 1 MN/m spring, at 1024 Hz."""
    return SpringPlant(DelayGain(delay, gain, dt), stiffness=stiffness)


def start_twin(
    driver_name: str,
    plant: Plant,
    *,
    faults: Faults | None = None,
    heartbeat_timeout: float | None = None,
    threaded: bool = True,
    **connection: Any,
) -> TwinEndpoint:
    """Start the twin endpoint matching ``driver_name`` around ``plant``; return it running.

    Parameters
    ----------
    driver_name : {"can", "modbus", "serial"}
        Which protocol to speak.
    plant : Plant
        The plant stepped once per command.
    faults : Faults, optional
        Fault plan (:mod:`sim_backends.faults`).
    heartbeat_timeout : float, optional
        Heartbeat watchdog period (s); off by default.
    threaded : bool
        Serve in a thread (default). ``False``: the caller serves with ``endpoint.pump()``
        (CAN on the ``virtual`` interface only; the lockstep loop's fast path).
    **connection
        Endpoint settings. ``can``: ``interface`` (``virtual``), ``channel`` (a fresh unique
        name by default), ``bitrate``, ``dbc``, ``bus_options``. ``modbus``: ``transport``
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
    seq_bits = None if driver_name == "serial" else 16
    controller = TwinController(
        plant, faults, seq_bits=seq_bits, heartbeat_timeout=heartbeat_timeout
    )
    try:
        if driver_name == "can":
            from .endpoints.can import CANTwin

            connection.setdefault("channel", f"rths-twin-{uuid.uuid4().hex[:8]}")
            endpoint: TwinEndpoint = CANTwin(controller, **connection)
        elif driver_name == "modbus":
            from .endpoints.modbus import ModbusTwin

            endpoint = ModbusTwin(controller, **connection)
        elif driver_name == "serial":
            from .endpoints.serial import SerialTwin

            endpoint = SerialTwin(controller, **connection)
        else:
            raise InputError(f"no twin for driver {driver_name!r}; use can, modbus or serial")
    except TypeError as exc:
        raise InputError(f"twin {driver_name!r}: bad endpoint setting: {exc}") from None
    return endpoint.start(threaded)

"""The experimental site: OpenSees' element DOFs ↔ the bridge's actuator channels.

:class:`Mapping` is the site's experimental setup (OpenFresco's ``ExperimentalSetup`` role,
:mod:`rths_hil.hybrid.setup`, which the channels' rows over a numerical structure use too): it
turns element displacements into actuator commands and measured actuator forces back into
element forces by a transformation ``T`` (``n_actuators × n_dofs``)::

    d = T·u          (actuator displacement from the element's trial displacements)
    p = Tᵀ·f         (element forces from the measured actuator forces)

The default for a two-node element with one DOF per node (``-dof 1 -dof 1``) is OpenFresco's
basic system of a one-actuator setup: ``T = [−1, 1]``, the actuator elongation ``u₂ − u₁``,
forces ``(−f, +f)``. With ``n`` actuators, an element of ``n + 1`` nodes (one DOF each) gets
the basic system of ``n`` two-node elements in series
(:func:`~rths_hil.hybrid.setup.chain_transform`: actuator ``i`` between nodes ``i`` and
``i + 1``), an element of ``n`` DOFs the identity (actuator ``i`` on
element DOF ``i``); a one-DOF element with one actuator gets ``T = [1]``. Stiffness, damping
and mass replies are ``Tᵀ·K·T`` with ``K`` (``C``, ``M``) given per actuator in the
configuration (the specimen estimate); damping and mass default to zero (the measured force
already contains the specimen's damping and inertia: a non-zero reply would count them twice
in OpenSees' ``genericClient``, which adds ``C·v`` and ``M·a`` to the measured forces).

:class:`ExperimentalSite` is the structure stage the loop drives: it listens, accepts the
client, and each loop step turns the measurement into the next actuator command through its
timing mode (:mod:`.timing`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from collections.abc import Mapping as _Mapping
from typing import Any

import numpy as np

from ..config import SCHEMA, check_table
from ..errors import InputError
from ..hybrid.setup import Setup, check_rows, site_transform, split_rows
from . import protocol as P
from .server import SiteServer
from .timing import SiteFault, TimingMode, make_timing

log = logging.getLogger(__name__)

__all__ = ["DEFAULTS", "TIMINGS", "ExperimentalSite", "Mapping", "SiteFault"]

_TRANSFORM = "openfresco.transform"

TIMINGS = ("lockstep", "predictor-corrector", "ramp-hold")

#: ``[openfresco]`` keys and their defaults (SI units), from the configuration schema.
DEFAULTS: dict[str, Any] = {name: key.default for name, key in SCHEMA["openfresco"].items()}


def _matrix(value: Any, n: int, what: str) -> np.ndarray:
    """Per-actuator values: none (zero), a number, n values (diagonal) or n² (row-major)."""
    try:
        a = np.asarray(value if value is not None else [], dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"openfresco.{what}: not a number or list of numbers: {value!r}") from None
    if a.size == 0:
        a = np.zeros((n, n))
    elif a.ndim == 0 or a.size == 1:
        a = np.eye(n) * float(a.ravel()[0])
    elif a.size == n:
        a = np.diag(a.ravel())
    elif a.size == n * n:
        a = a.reshape(n, n)
    else:
        raise InputError(
            f"openfresco.{what}: {a.size} values for {n} actuator(s): give {n} (one per "
            f"actuator) or {n * n} (a matrix, row-major)"
        )
    if not np.all(np.isfinite(a)):
        raise InputError(f"openfresco.{what}: values must be finite")
    return a


class Mapping(Setup):
    """The site's setup: element DOFs ↔ actuators (``d = T·u``, ``p = Tᵀ·f``) and the matrix
    replies (:class:`rths_hil.hybrid.setup.Setup`, OpenFresco's ``ExperimentalSetup`` role).

    Parameters
    ----------
    n_actuators : int
        Actuator channels the site drives.
    transform : list of list of float, optional
        ``T`` by rows (one row per actuator); default by the element's DOF count (see module).
    stiffness, damping, mass : float, list or matrix
        Per-actuator estimates (N/m, N·s/m, kg) for the replies to getInitialStiff /
        getTangentStiff, getDamp, getMass.

    Notes
    -----
    ``T`` is fixed when the client's element is known (:meth:`bind`); before that :attr:`T`
    is ``None``.
    """

    T: np.ndarray | None  # type: ignore[assignment]

    def __init__(
        self,
        n_actuators: int = 1,
        transform: list | None = None,
        stiffness: Any = 0.0,
        damping: Any = 0.0,
        mass: Any = 0.0,
    ) -> None:
        if int(n_actuators) < 1:
            raise InputError(f"openfresco.actuators must be ≥ 1, got {n_actuators!r}")
        self.n_actuators = n = int(n_actuators)
        self.rows = (
            split_rows(transform, n, _TRANSFORM)
            if transform is not None and len(transform)
            else None
        )
        self.K = _matrix(stiffness, n, "stiffness")
        self.C = _matrix(damping, n, "damping")
        self.M = _matrix(mass, n, "mass")
        self.T = None
        if self.rows is not None:
            check_rows(self.rows, n, None, _TRANSFORM)

    def bind(self, session: P.SessionID) -> None:
        """Fix ``T`` for the client's element (called when its ID arrives)."""
        nb = session.nb
        n = self.n_actuators
        T: np.ndarray | None
        if session.protocol == "generic-tcp":
            T = np.eye(n)
            if nb != n:
                raise InputError(
                    f"GenericTCP controls {nb} displacements, the site drives {n} actuators"
                )
        elif self.rows is not None:
            T = check_rows(self.rows, n, nb, _TRANSFORM)
        else:
            T = site_transform(n, nb)  # one actuator per DOF, or the basic system u_{i+1} − u_i
            if T is None:
                raise InputError(
                    f"the client's element has {nb} DOFs for {n} actuator(s): give "
                    "openfresco.transform (one row of element-DOF weights per actuator)"
                )
        Setup.__init__(self, T)
        self._mats = {
            P.GET_INITIAL_STIFF: self.on_dofs(self.K),
            P.GET_TANGENT_STIFF: self.on_dofs(self.K),
            P.GET_DAMP: self.on_dofs(self.C),
            P.GET_MASS: self.on_dofs(self.M),
        }

    def matrix(self, action: int) -> np.ndarray:
        """The element matrix for a stiffness / damping / mass request."""
        return self._mats[action]


def _genericclient_lines(host: str, port: int, nb: int = 2) -> tuple[str, str]:
    dofs = " ".join(["-dof 1"] * nb)
    py_dofs = ", ".join(["'-dof', 1"] * nb)
    nodes = " ".join(str(i + 1) for i in range(nb))
    py_nodes = ", ".join(str(i + 1) for i in range(nb))
    tcl = f"element genericClient $tag -node {nodes} {dofs} -server {port} {host}"
    py = (
        f"ops.element('genericClient', tag, '-node', {py_nodes}, {py_dofs}, "
        f"'-server', {port}, '{host}')"
    )
    return py, tcl


class ExperimentalSite:
    """The OpenSees-driven structure stage: a server, a mapping and a timing mode.

    Parameters
    ----------
    options : mapping
        The ``[openfresco]`` table (keys of :data:`DEFAULTS`).
    dt : float
        Loop step (s).
    n_actuators : int, optional
        Number of actuator channels (the loop's channels; default 1).

    Notes
    -----
    :meth:`open` listens and waits for the client; :meth:`step` is called once per loop step;
    :meth:`close` (after the loop's e-stop) drops the connection, so OpenSees reports the
    failed element and stops.
    """

    def __init__(
        self, options: _Mapping[str, Any], dt: float, n_actuators: int | None = None
    ) -> None:
        o = check_table(options, SCHEMA["openfresco"], path="openfresco")
        self.options = o
        self.dt = float(dt)
        n = int(n_actuators if n_actuators is not None else 1)
        self.mapping = Mapping(n, o["transform"], o["stiffness"], o["damping"], o["mass"])
        self.n = n
        self.host = str(o["host"])
        if self.host not in ("127.0.0.1", "localhost", "::1"):
            log.warning(
                "openfresco.host = %r: the site accepts connections from other machines",
                self.host,
            )
        mt = int(o["max_trials_per_step"])
        #: distinct trials per OpenSees step before the site stops (0: no limit)
        self.max_trials = (0 if o["timing"] == "predictor-corrector" else 1) if mt < 0 else mt
        edt = float(o["element_dt"] or 0.0)
        if edt > 0 and o["timing"] != "ramp-hold":
            from .server import _dt_fault

            msg = _dt_fault(edt, self.dt)
            if msg is not None:
                raise InputError(msg.replace("OpenSees' time step", "openfresco.element_dt", 1))
        self.server: SiteServer | None = None
        self.timing: TimingMode | None = None
        self.fault: str | None = None

    @property
    def loop_mode(self) -> str:
        """The loop mode the timing needs: ``lockstep`` or ``paced``."""
        return "lockstep" if self.options["timing"] == "lockstep" else "paced"

    # ------------------------------------------------------------------------------------------
    def listen(self) -> tuple[str, int]:
        """Bind and listen; return ``(host, port)`` (the port is real when 0 was asked)."""
        o = self.options
        self.server = SiteServer(
            self.host, int(o["port"]), o["protocol"], self.mapping, quickack=bool(o["quickack"])
        )
        self.server.max_trials = self.max_trials
        # lockstep and predictor–corrector run the specimen on OpenSees' clock: its step
        # must be a whole number of loop periods (ramp-hold runs on its own ramp time)
        self.server.loop_dt = self.dt if o["timing"] != "ramp-hold" else None
        return self.server.host, self.server.port

    def paste_lines(self) -> tuple[str, str]:
        """The ``genericClient`` lines (OpenSeesPy, Tcl) to paste into the OpenSees model."""
        host = self.server.host if self.server else self.host
        port = self.server.port if self.server else self.options["port"]
        T = self.mapping.rows
        return _genericclient_lines(host, port, T.shape[1] if T is not None else self.n + 1)

    def accept(self, stop: Callable[[], bool] = lambda: False) -> P.SessionID:
        """Wait for the client and its ID (one line + :class:`InputError` when wrong)."""
        if self.server is None:
            self.listen()
        limit = self.options["connect_timeout"] or None
        ses = self.server.accept(limit, stop)
        o = self.options
        ramp = o["ramp_time"] or (0.01 if o["timing"] == "lockstep" else 0.5)
        wait = o["wait"] * self.dt
        self.timing = make_timing(
            o["timing"],
            self.server.mailbox,
            self.n,
            self.dt,
            {**o, "ramp_time": ramp, "wait": wait, "stiffness_matrix": self.mapping.K},
        )
        self.server.start()
        return ses

    def step(self, k: int, disp, force) -> np.ndarray | None:
        """Measurement of loop step ``k`` → command of step ``k + 1`` (None: the client is done).

        Raises :class:`SiteFault` (one line) when the session fails.
        """
        try:
            return self.timing.step(k, np.atleast_1d(disp), np.atleast_1d(force))
        except SiteFault as exc:
            self.fault = str(exc)
            raise

    def close(self) -> None:
        """Drop the connection and stop listening."""
        if self.server is not None:
            self.server.close()

    def summary(self) -> dict[str, Any]:
        """Counts of the session: actions by name, command kinds, targets, latencies."""
        o = self.options
        out: dict[str, Any] = {"timing": o["timing"], "protocol": o["protocol"]}
        if self.server is not None:
            out["actions"] = dict(self.server.counts)
            out["client_id"] = self.server.session.as_tuple() if self.server.session else None
        tm = self.timing
        if tm is not None:
            lat = tm.latencies()
            out["kinds"] = tm.kind_counts()
            out["targets"] = len(tm.targets)
            out["latency_max"] = float(lat.max()) if lat.size else math.nan
            out["latency_p50"] = float(np.median(lat)) if lat.size else math.nan
            if hasattr(tm, "worst_late"):
                out["worst_late"] = tm.worst_late
        return out

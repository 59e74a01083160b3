"""Protocol-independent part of a twin: the controller state machine and the endpoint thread.

:class:`TwinController` is what every endpoint drives. Its rules (the lockstep contract the
real-time loop relies on):

* Each command with a new sequence number ``k`` advances the plant exactly one step
  (``plant.step(command) -> (disp, force)``) when the controller is enabled, and the feedback
  echoes ``k``. A repeated ``k`` (a retransmitted or duplicated command) does not step the plant
  again: the same feedback is sent again. An older ``k`` is ignored.
* ``enable=False`` holds the last position without stepping (status without ``ENABLED``).
* An e-stop latches: the plant is no longer stepped, the feedback repeats the last measured
  displacement and force with status ``ESTOP_ACTIVE`` for every command, until a command with
  ``enable=False`` acknowledges it; a later ``enable=True`` command re-enables.
* Controller-side watchdog (as a servo controller has): while the controller is enabled, a
  valid command or a heartbeat must come at least every ``heartbeat_timeout`` seconds. When
  none does (the bridge crashed, was killed or lost the link) the controller holds its last
  position and latches the e-stop (status ``ESTOP_ACTIVE | WATCHDOG``) until it is re-armed.
  The check runs in the endpoint's own thread, so it fires whether or not anything arrives.
* Arming (the start of a run): a command with sequence number 0 and ``enable=False`` restarts
  the sequence count (the run's step 0 is a new command whatever a previous run sent),
  acknowledges a latched e-stop or watchdog trip, puts the twin's plant back at rest and
  holds; its reply reports the status before arming and where the actuator is now (the
  controller's position after arming). The run's first ``enable=True`` command enables it
  (:meth:`rths_hil.drivers.base.Driver.arm`).
* Initial position (``initial_position``, m): where the actuator sits at rest, as a real
  actuator that a previous test or the operator left off centre. The plant runs about it
  (``measured = initial_position + plant(command − initial_position)``): commanding the
  initial position holds still, commanding 0 moves the actuator there through its dynamics.
* Force control: a plant that runs in force mode (``plant.control == "force"``, the force twin
  of :mod:`rths_hil.sim_backends.force`) takes the decoded force set-point (N) unchanged
  (:attr:`TwinController.control`); the initial position does not offset it. The endpoint
  decodes the force set-point role of its protocol instead of the displacement's.

:class:`TwinEndpoint` runs the protocol side in a daemon thread and applies the frame faults of a
:class:`~rths_hil.sim_backends.faults.Faults` plan.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from types import TracebackType
from typing import Any, ClassVar

from rths_hil.drivers.base import Status

from rths_hil.errors import InputError
from rths_hil.keys import Key

from ..base import Plant
from ..faults import Faults
from ..registry import twin_class

log = logging.getLogger(__name__)

__all__ = ["LISTEN_KEYS", "TwinController", "TwinEndpoint", "TwinStats", "listen"]

_LOOPBACK = ("127.", "::1", "localhost")

#: The settings of a twin that listens on TCP (:func:`listen`), as its
#: :attr:`TwinEndpoint.CONNECTION` declares them.
LISTEN_KEYS: dict[str, Key] = {
    "host": Key("str", "127.0.0.1", doc="twin: TCP address to listen on (loopback by default)"),
    "port": Key("int", 0, lo=0, hi=65535, doc="twin: TCP port to listen on (0: any free port)"),
    "allow_remote": Key(
        "bool",
        False,
        doc="twin: allow a host other than loopback (the twin is then reachable from the network)",
    ),
}
_ENABLED = int(Status.ENABLED)
_ESTOP_ACTIVE = int(Status.ESTOP_ACTIVE)
_WATCHDOG = int(Status.WATCHDOG)
_FAULT = int(Status.FAULT)


def listen(host: str, port: int, allow_remote: bool, who: str) -> socket.socket:
    """A listening TCP socket on ``host:port`` for a twin, loopback unless told otherwise.

    Parameters
    ----------
    host : str
        Bind address. Anything but a loopback address (``127.x.x.x``, ``::1``, ``localhost``)
        exposes the twin to the network and needs ``allow_remote``; then a warning names the
        address and port.
    port : int
        TCP port, 0–65535 (0: any free port).
    allow_remote : bool
        Whether a non-loopback ``host`` is allowed.
    who : str
        Endpoint name for messages (``modbus twin``).

    Raises
    ------
    InputError
        A port out of range, a non-loopback host without ``allow_remote``, or a bind failure.
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise InputError(f"{who}: port must be an integer in 0..65535, got {port!r}")
    host = str(host)
    remote = not host.startswith(_LOOPBACK)
    if remote and not allow_remote:
        raise InputError(
            f"{who}: host {host!r} would accept connections from the network; bind 127.0.0.1 "
            "or allow it explicitly (twin serve --allow-remote, driver.connection.allow_remote "
            "= true)"
        )
    try:
        lst = socket.create_server((host, port))
    except (OSError, OverflowError) as exc:
        raise InputError(f"{who}: cannot listen on {host}:{port}: {exc}") from None
    if remote:
        log.warning(
            "%s: listening on %s port %d: reachable from the network, not only this machine",
            who,
            host,
            lst.getsockname()[1],
        )
    return lst


@dataclass(slots=True)
class TwinStats:
    """Counters of a twin endpoint (what the controller saw)."""

    commands: int = 0
    steps: int = 0
    replies: int = 0
    repeats: int = 0
    stale: int = 0
    seq_gaps: int = 0
    estops: int = 0
    heartbeats: int = 0
    malformed: int = 0

    def as_dict(self) -> dict[str, int]:
        """All counters as a dict."""
        return asdict(self)


class TwinController:
    """The controller state machine around a plant (see the module docstring).

    Parameters
    ----------
    plant : Plant
        Anything with ``dt``, ``reset()`` and ``step(cmd) -> (disp, force)``.
    faults : Faults, optional
        Measurement and command faults to apply.
    seq_bits : int or None
        Width of the wire sequence number (16 on CAN and Modbus, ``None`` for full integers);
        wire values are extended to a running count.
    heartbeat_timeout : float or None
        Controller-side watchdog (s): the longest time without a valid command or heartbeat
        while enabled; ``None`` disables it.
    initial_position : float
        Where the actuator sits at rest (m; module docstring).
    """

    def __init__(
        self,
        plant: Plant,
        faults: Faults | None = None,
        seq_bits: int | None = None,
        heartbeat_timeout: float | None = None,
        initial_position: float = 0.0,
    ) -> None:
        self.plant = plant
        self.home = float(initial_position)
        self.faults = faults or Faults()
        self.stats = TwinStats()
        self._mask = (1 << seq_bits) - 1 if seq_bits else 0
        self.heartbeat_timeout = heartbeat_timeout
        #: The wire control mode the plant runs (``"displacement"`` or ``"force"``): what a
        #: command's value is, m or N (module docstring).
        self.control: str = str(getattr(plant, "control", None) or "displacement")
        self._offset = self.control != "force"  # the initial position offsets displacements
        self.lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        """Back to rest: plant reset, e-stop cleared, no step taken yet."""
        self.plant.reset()
        self.last_seq = -1
        self.enabled = False
        self.estop_latched = False
        self.watchdog_tripped = False
        self.displacement = self.home
        self.force = 0.0
        self.last_reply: tuple[int, float, float, int] | None = None
        self._last_heartbeat: float | None = None  # last valid command or heartbeat

    def _extend(self, raw: int) -> int:
        if not self._mask or self.last_seq < 0:
            return raw  # the first command sets the count
        mask = self._mask
        half = (mask + 1) >> 1
        ref = self.last_seq
        return ref + (((raw - ref) + half) & mask) - half

    def estop(self) -> None:
        """Latch the e-stop: hold position from now on (unless the ``estop_ignored`` fault)."""
        with self.lock:
            if self.faults.estop_ignored:
                return
            self.stats.estops += 1
            self.estop_latched = True
            self.enabled = False

    def heartbeat(self) -> None:
        """Record a heartbeat (keeps the watchdog fed)."""
        self.stats.heartbeats += 1
        self._last_heartbeat = time.monotonic()

    def check_watchdog(self) -> None:
        """Hold and latch the e-stop when no command or heartbeat came in time while enabled."""
        if self.heartbeat_timeout is None or self._last_heartbeat is None:
            return
        if not self.enabled and not self.estop_latched:
            return  # holding on purpose (enable=False): nothing to watch
        if time.monotonic() - self._last_heartbeat > self.heartbeat_timeout:
            with self.lock:
                if not self.watchdog_tripped:
                    log.warning(
                        "twin: no command or heartbeat for %.3f s, e-stop latched",
                        self.heartbeat_timeout,
                    )
                    self.stats.estops += 1
                    self.estop_latched = True
                    self.enabled = False
                    self.watchdog_tripped = True

    @property
    def watchdog_poll(self) -> float:
        """How often the endpoint must run :meth:`check_watchdog` (s)."""
        hb = self.heartbeat_timeout
        return 0.05 if hb is None else max(min(0.05, hb / 4.0), 0.001)

    def _arm(self) -> tuple[int, float, float, int]:
        """Sequence 0 with enable=False: a new run (see the module docstring).

        The reply reports the status before arming (e.g. a latched watchdog trip), so the run's
        record shows what the controller had to be re-armed from, and the position and force
        after arming: where the run starts from.
        """
        status = self.status()
        self.plant.reset()
        self.last_seq = -1  # the run's step 0 starts the count afresh
        self.enabled = False
        self.estop_latched = False
        self.watchdog_tripped = False
        self.displacement = self.home
        self.force = 0.0
        self.faults.rearm()
        self._last_heartbeat = time.monotonic()
        self.last_reply = None  # step 0 of the run is a new command, not a repeat
        return (0, self.displacement, self.force, status)

    def status(self) -> int:
        """Current :class:`~rths_hil.drivers.base.Status` flags (without per-sample flags)."""
        s = _ENABLED if self.enabled else 0  # plain ints: an IntFlag "|" builds an enum member
        if self.estop_latched:
            s |= _ESTOP_ACTIVE
        if self.watchdog_tripped:
            s |= _WATCHDOG
        if self.faults.runaway_from is not None and self.last_seq >= self.faults.runaway_from:
            s |= _FAULT
        return s

    def command(
        self, raw_seq: int, displacement: float, enable: bool
    ) -> tuple[int, float, float, int] | None:
        """Handle one command frame; return the feedback (seq, disp, force, status) or None.

        ``None`` means nothing is sent back (command lost, or older than the last one).
        """
        with self.lock:
            self.stats.commands += 1
            if raw_seq == 0 and not enable:
                return self._arm()
            seq = self._extend(raw_seq)
            if self.faults.command_lost(seq):
                return None
            if seq == self.last_seq and self.last_reply is not None:
                self.stats.repeats += 1
                return self.last_reply
            if seq < self.last_seq:
                self.stats.stale += 1
                return None
            extra = 0
            if self.last_seq >= 0 and seq > self.last_seq + 1:
                self.stats.seq_gaps += seq - self.last_seq - 1
                extra |= Status.SEQ_GAP
            self.last_seq = seq
            self._last_heartbeat = time.monotonic()  # a valid command feeds the watchdog
            if self.estop_latched:
                if not enable:
                    self.estop_latched = False  # acknowledged; next enable=True re-enables
                    self.watchdog_tripped = False
                self.enabled = False
            else:
                self.enabled = bool(enable)
            if self.enabled and math.isfinite(displacement):
                home = self.home
                if home and self._offset:
                    d, f = self.plant.step(displacement - home)
                    d += home
                else:
                    d, f = self.plant.step(displacement)
                self.stats.steps += 1
                d, f, invalid = self.faults.measure(seq, float(d), float(f), self.plant.dt)
                self.displacement, self.force = d, f
                if invalid:
                    extra |= Status.SENSOR_INVALID
            elif self.enabled:
                self.enabled = False  # a non-finite command disables (holds position)
            reply = (seq, self.displacement, self.force, self.status() | int(extra))
            self.last_reply = reply
            return reply


class TwinEndpoint(ABC):
    """A protocol endpoint serving a :class:`TwinController` from a daemon thread.

    Subclasses implement :meth:`_setup` (open the transport, fill :attr:`connection` and
    :attr:`where`), :meth:`_serve_once` (wait ≤ ``poll`` s for input and handle it),
    :meth:`_teardown`, :meth:`_write` (send one encoded frame) and :meth:`_corrupt`.
    """

    name: str = ""
    poll = 0.05
    #: The settings the endpoint takes (``start_twin``'s ``**connection`` but ``profile``):
    #: name → :class:`~rths_hil.keys.Key`, defaults as in ``__init__``. A run with a twin
    #: reads ``driver.connection`` against them and the driver's own ``CONNECTION``
    #: (:func:`rths_hil.drivers.registry.check_connection`) before the twin starts. ``None``
    #: (a lab's twin that declares none): the driver's keys are read, the others reach the
    #: constructor as given.
    CONNECTION: ClassVar[Mapping[str, Key] | None] = None

    def __init__(self, controller: TwinController) -> None:
        self.controller = controller
        self.faults = controller.faults
        self.connection: dict[str, Any] = {}
        self.where = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._gone = False
        self.error: BaseException | None = None
        self.inline = False
        # inline mode: a delayed reply (release time, frames, copies); until then the endpoint
        # serves nothing, as a stalled controller (a pause must not stall the bridge's thread)
        self._held: tuple[float, list[Any], int] | None = None

    @property
    def stats(self) -> TwinStats:
        """The controller's counters."""
        return self.controller.stats

    @property
    def plant(self) -> Plant:
        """The plant being driven."""
        return self.controller.plant

    @property
    def control(self) -> str:
        """The wire control mode of the plant (``"displacement"`` or ``"force"``): which
        set-point role the endpoint decodes."""
        return self.controller.control

    # -- how ``rths-hil twin serve`` maps its options onto this endpoint ----------------------
    #: Transports ``--transport`` accepts, the default first (empty: none to choose).
    transports: tuple[str, ...] = ()

    @classmethod
    def connection_from_args(cls, args: Any) -> dict[str, Any]:
        """Endpoint settings from ``rths-hil twin serve``'s options (``args``).

        Default: ``--transport`` among :attr:`transports` (the registry's entry for a built-in
        twin) and, for ``tcp``, ``--host``, ``--port`` and ``--allow-remote``.
        """
        _, entry = twin_class(args.driver)
        conn: dict[str, Any] = {}
        allowed = entry.transports
        if allowed:
            transport = args.transport or allowed[0]
            if transport not in allowed:
                raise InputError(
                    f"--transport {transport}: use {' or '.join(allowed)} with "
                    f"--driver {args.driver}"
                )
            conn["transport"] = transport
            if transport == "tcp":
                conn |= {
                    "host": args.host,
                    "port": 0 if args.port is None else args.port,
                    "allow_remote": args.allow_remote,
                }
        return conn

    @classmethod
    def profile_twin(cls) -> type[TwinEndpoint]:
        """The endpoint that speaks a controller profile of this protocol (``--profile``).

        Raises
        ------
        InputError
            No twin of this protocol speaks profiles.
        """
        raise InputError(f"twin {cls.name!r}: no twin of this protocol speaks a profile")

    @classmethod
    def serve_units(cls, args: Any) -> list[Any]:
        """The controllers ``twin serve`` starts behind one endpoint (default: one)."""
        return [None]

    @classmethod
    def unit_connection(cls, first: dict[str, Any], unit: Any, args: Any) -> dict[str, Any]:
        """Settings of a further unit joining the first one's endpoint (see
        :meth:`serve_units`)."""
        return dict(first)

    # -- lifecycle ------------------------------------------------------------------------------
    #: Whether :meth:`pump` can serve the transport from the caller's thread (synchronous,
    #: in-process transports only).
    supports_inline = False

    def start(self, threaded: bool = True) -> TwinEndpoint:
        """Open the transport and start serving; returns self.

        With ``threaded=False`` (transports with :attr:`supports_inline`) no thread is started:
        the caller serves pending frames with :meth:`pump`. The real-time loop uses this over
        python-can's in-process virtual bus (``twin.inline``), where the thread hand-off and
        GIL contention twice per step would otherwise dominate; the frames, codecs and
        controller are the same.
        """
        if self._thread is not None:
            return self
        self.inline = not threaded  # stays set after stop(): how the endpoint was served
        if not threaded:
            if not self.supports_inline:
                raise InputError(f"twin {self.name}: this transport cannot be served inline")
            self._setup()
            return self
        self._setup()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"twin-{self.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._teardown()

    def pump(self) -> int:
        """Serve every frame already waiting (inline mode); return how many were handled."""
        raise InputError(f"twin {self.name}: this transport cannot be served inline")

    def __enter__(self) -> TwinEndpoint:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def wait(self) -> None:
        """Block until :meth:`stop` is called from elsewhere (used by ``twin serve``)."""
        while not self._stop.wait(0.2):
            pass

    def _run(self) -> None:
        try:
            poll = min(self.poll, self.controller.watchdog_poll)
            while not self._stop.is_set():
                self._serve_once(poll)
                self.controller.check_watchdog()
        except BaseException as exc:  # pragma: no cover - surfaced through .error
            log.exception("twin %s endpoint stopped on an error", self.name)
            self.error = exc

    # -- feedback emission with frame faults ----------------------------------------------------
    def _go_away(self) -> None:
        """Disconnect fault: close the transport side the driver talks to."""
        self._gone = True

    def emit(self, reply: tuple[int, float, float, int] | None) -> None:
        """Send the feedback of one command, applying the frame and link faults."""
        if reply is None or self._gone:
            return
        seq = reply[0]
        faults = self.faults
        if faults.disconnected(seq):
            self._go_away()
            return
        self._send_feedback(reply, *faults.reply_plan(seq))

    def _send_feedback(
        self, reply: tuple[int, float, float, int], copies: int, pause: float, corrupt: bool
    ) -> None:
        """Send one feedback as ``copies`` copies after ``pause`` s, damaged if ``corrupt``."""
        frames = self._encode(*reply)
        if corrupt:
            frames = [self._corrupt(f) for f in frames]
        if pause:
            if self.inline:  # served from the bridge's thread: hold the reply, do not sleep
                self._held = (time.monotonic() + pause, frames, copies)
                return
            time.sleep(pause)
        for _ in range(copies):
            for frame in frames:
                self._write(frame)
        self.controller.stats.replies += copies

    def _paused(self) -> bool:
        """Inline mode: True while a delayed reply is held; sends it when its time has come."""
        held = self._held
        if held is None:
            return False
        if time.monotonic() < held[0]:
            return True
        self._held = None
        for _ in range(held[2]):
            for frame in held[1]:
                self._write(frame)
        self.controller.stats.replies += held[2]
        return False

    @abstractmethod
    def _encode(self, seq: int, displacement: float, force: float, status: int) -> list[Any]:
        """Encode one feedback into the frame(s) to send."""

    @abstractmethod
    def _corrupt(self, frame: Any) -> Any:
        """Return ``frame`` damaged in a way the driver's checks must detect."""

    @abstractmethod
    def _write(self, frame: Any) -> None:
        """Send one frame."""

    @abstractmethod
    def _setup(self) -> None:
        """Open the transport."""

    @abstractmethod
    def _serve_once(self, timeout: float) -> None:
        """Wait up to ``timeout`` for input and handle it."""

    @abstractmethod
    def _teardown(self) -> None:
        """Close the transport."""

"""The TCP server of the experimental site: one OpenSees (or OpenFresco) client at a time.

The server thread speaks the wire protocol (:mod:`.protocol`) and meets the loop in a
:class:`Mailbox`: a setTrialResponse stores the trial; a request for forces (getForce,
getDaqResponse) posts the latest trial as a *target* and waits until the loop's timing mode
(:mod:`.timing`) has executed it and posted the *measurement*; everything else (stiffness,
damping, mass, the last measurement again) is answered at once from the configuration or from
what the mailbox already holds.

Latency
-------
OpenSees' ``TCP_Socket`` leaves Nagle's algorithm on. A request of one 2 kB frame answered by
one 2 kB frame then meets Linux' delayed ACK: the client's next small write waits for an ACK
the server holds back for up to 40 ms. The server therefore sets ``TCP_NODELAY`` and re-arms
``TCP_QUICKACK`` after **every** ``recv`` (the kernel clears the flag on its own after a few
segments). ``benchmarks/bench_opensees.py`` measures OpenSeesPy steps per second with and
without the re-arm (benchmarks/results/bench_opensees.md).
"""

from __future__ import annotations

import contextlib
import logging
import math
import select
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from . import protocol as P

log = logging.getLogger(__name__)

__all__ = ["Mailbox", "SiteServer", "Target"]

#: Largest trial time accepted (s): a test's clock, not 1e12 s or infinity (ten days).
MAX_TRIAL_TIME = 864_000.0

_TCP_QUICKACK = getattr(socket, "TCP_QUICKACK", None)


@dataclass
class Target:
    """A trial the client asked the site to execute (actuator coordinates)."""

    seq: int
    displacement: np.ndarray  # actuator displacements, m
    velocity: np.ndarray | None  # actuator velocities, m/s (None when the client sends none)
    time: float  # the trial's analysis time (s; NaN when the client sends none)
    wall: float  # time.perf_counter() when the request arrived


@dataclass
class Mailbox:
    """Where the server thread and the loop meet (one lock, one condition).

    The server posts :attr:`target` (``seq`` increasing) and waits for :attr:`reply_seq` to
    reach it; the loop's timing mode takes the target, executes it and posts the measurement
    with :meth:`post_reply`. :attr:`closed` carries the reason the session ended (``"die"``
    for a clean end, otherwise a one-line fault).
    """

    cond: threading.Condition = field(default_factory=threading.Condition)
    target: Target | None = None
    reply_seq: int = 0
    measured_disp: np.ndarray | None = None
    measured_force: np.ndarray | None = None
    measured_time: float = 0.0
    closed: str | None = None
    fault: bool = False
    wall_reply: float = 0.0

    def post_reply(self, seq: int, disp: np.ndarray, force: np.ndarray, t: float) -> None:
        """The loop has executed target ``seq``: hand the measurement to the server."""
        with self.cond:
            self.measured_disp = disp
            self.measured_force = force
            self.measured_time = t
            self.reply_seq = seq
            self.wall_reply = time.perf_counter()
            self.cond.notify_all()

    def close(self, reason: str, fault: bool) -> None:
        """End the session (first reason wins)."""
        with self.cond:
            if self.closed is None:
                self.closed = reason
                self.fault = fault
            self.cond.notify_all()


class _Closed(Exception):
    pass


class SiteServer:
    """Listen on ``host:port``, accept one client, read its ID, serve it in a thread.

    Parameters
    ----------
    host, port : str, int
        Where to listen. ``127.0.0.1`` unless the configuration says otherwise (any other
        address is logged as a warning by the caller). ``port = 0`` picks a free port.
    protocol : {"elem-server", "generic-tcp"}
        The client flavour expected (:mod:`.protocol`).
    mapping : Mapping
        Element DOFs ↔ actuator channels and the matrices for the stiffness replies
        (:class:`rths_hil.openfresco.site.Mapping`).
    quickack : bool
        Re-arm ``TCP_QUICKACK`` after every ``recv`` (default; off only to measure its effect).
    frame_timeout : float
        Seconds the rest of a started frame may take before the frame counts as short.
    """

    def __init__(
        self,
        host: str,
        port: int,
        protocol: str,
        mapping,
        *,
        quickack: bool = True,
        frame_timeout: float = 0.5,
    ) -> None:
        if protocol not in P.PROTOCOLS:
            raise InputError(f"openfresco.protocol must be one of {P.PROTOCOLS}, got {protocol!r}")
        self.protocol = protocol
        self.mapping = mapping
        self.quickack = quickack and _TCP_QUICKACK is not None
        self.frame_timeout = float(frame_timeout)
        self.mailbox = Mailbox()
        self.session: P.SessionID | None = None
        self.peer: tuple | None = None
        self.counts: dict[str, int] = {}
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, int(port)))
        except OSError as exc:
            self._listener.close()
            where = f"{host}:{port}"
            raise InputError(f"openfresco: cannot listen on {where}: {exc.strerror}") from None
        self._listener.listen(1)
        self.host, self.port = self._listener.getsockname()[:2]
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        #: distinct trials allowed per OpenSees time step (0: no limit); see :meth:`_check_trial`
        self.max_trials = 0
        #: the loop step (s) OpenSees' time step must be a whole multiple of (None: not checked)
        self.loop_dt: float | None = None
        self._trials = 0  # distinct trials in the current time step
        self._last_t = 0.0  # analysis time of the latest trial (s)
        self._commits = 0  # commitState requests seen

    # ------------------------------------------------------------------------------------------
    def accept(self, timeout: float | None = None, stop=lambda: False) -> P.SessionID:
        """Wait for the client and read its ID; :class:`InputError` (one line) if it is wrong.

        ``timeout`` None waits until ``stop()`` returns True (polled every 0.2 s), then raises
        :class:`KeyboardInterrupt`.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if wait <= 0:
                raise InputError(
                    f"openfresco: no client connected to {self.host}:{self.port} within "
                    f"{timeout:g} s"
                )
            r, _, _ = select.select([self._listener], [], [], wait)
            if r:
                break
            if stop():
                raise KeyboardInterrupt
        sock, self.peer = self._listener.accept()
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._quickack()
        raw = bytearray(P.ID_BYTES)
        try:
            got = self._recv_exact(memoryview(raw), P.ID_BYTES, first_timeout=5.0)
        except _Closed as exc:
            got = int(str(exc) or 0)
            self._drop()
            raise InputError(
                f"openfresco: client {self.peer[0]}:{self.peer[1]} sent {got} of the "
                f"{P.ID_BYTES} bytes of its ID, then closed or stalled"
            ) from None
        except TimeoutError:
            self._drop()
            raise InputError(
                f"openfresco: client {self.peer[0]}:{self.peer[1]} connected but sent no ID "
                "within 5 s (is it an OpenSees genericClient or OpenFresco GenericTCP?)"
            ) from None
        try:
            n_act = self.mapping.n_actuators if self.protocol == "generic-tcp" else None
            session = P.SessionID.parse(bytes(raw[:got]), self.protocol, n_act)
            self.mapping.bind(session)
        except InputError as exc:
            self._drop()
            raise InputError(f"openfresco: {exc}") from None
        self.session = session
        log.info("openfresco: client %s:%d, ID %s", *self.peer[:2], session.as_tuple())
        return session

    def start(self) -> None:
        """Serve the accepted client in a daemon thread."""
        self._thread = threading.Thread(target=self._serve, name="openfresco-site", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Close the connection (the client sees it fail) and the listener."""
        self.mailbox.close("closed by the site", fault=False)
        self._drop()
        with contextlib.suppress(OSError):
            self._listener.close()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)

    def _drop(self) -> None:
        s, self._sock = self._sock, None
        if s is not None:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    # ------------------------------------------------------------------------------------------
    def _quickack(self) -> None:
        if self.quickack and self._sock is not None:
            self._sock.setsockopt(socket.IPPROTO_TCP, _TCP_QUICKACK, 1)

    def _recv_exact(self, view: memoryview, n: int, first_timeout: float | None = None) -> int:
        """Fill ``view[:n]``; raise :class:`_Closed` (bytes got) on EOF or a stalled frame."""
        sock = self._sock
        got = 0
        while got < n:
            limit = first_timeout if got == 0 else self.frame_timeout
            if limit is not None:
                r, _, _ = select.select([sock], [], [], limit)
                if not r:
                    raise _Closed(str(got)) if got else TimeoutError
            try:
                r = sock.recv_into(view[got:], n - got)
            except OSError:
                r = 0
            if self.quickack:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.IPPROTO_TCP, _TCP_QUICKACK, 1)
            if r == 0:
                raise _Closed(str(got))
            got += r
        return got

    def _send(self, frame: np.ndarray) -> None:
        self._sock.sendall(frame.data)

    def _serve(self) -> None:  # noqa: C901
        mb = self.mailbox
        ses = self.session
        m = self.mapping
        size = ses.data_size
        nbytes = ses.frame_bytes
        rbuf = bytearray(nbytes)
        rview = memoryview(rbuf)
        frame = np.frombuffer(rbuf, dtype=P.FRAME_DTYPE)
        out = np.zeros(size, dtype=P.FRAME_DTYPE)
        ctrl = ses.ctrl_offsets()
        daq = ses.daq_offsets()
        counts = self.counts
        elem = ses.protocol == "elem-server"
        has_vel = "vel" in ctrl
        trial_u = np.zeros(m.n_dofs)
        trial_v = np.zeros(m.n_dofs)
        trial_a = np.zeros(m.n_dofs)
        trial_t = float("nan")
        executed: tuple | None = None  # (trial displacement bytes, time) last executed
        seq = 0
        try:
            while mb.closed is None:
                try:
                    self._recv_exact(rview, nbytes)
                except _Closed as exc:
                    got = int(str(exc) or 0)
                    if mb.closed is not None:
                        return
                    if got:
                        mb.close(
                            f"openfresco: frame of {got} bytes, expected {nbytes} "
                            f"(dataSize {size} × 8) — the client sent a frame of the wrong size "
                            "or stalled mid-frame",
                            fault=True,
                        )
                    else:
                        mb.close("openfresco: the client disconnected mid-test", fault=True)
                    return
                code = frame[0]
                # a NaN or infinite code is no action (int() of it would raise)
                action = int(code) if math.isfinite(code) and code == int(code) else -1
                name = P.ACTIONS.get(action)
                if name is None:
                    mb.close(
                        f"openfresco: unknown action code {float(code)!r} in a {size}-value frame "
                        "(a frame of the wrong size shifts the next one)",
                        fault=True,
                    )
                    return
                counts[name] = counts.get(name, 0) + 1
                if action == P.SET_TRIAL:
                    if "disp" in ctrl:
                        trial_u[:] = frame[ctrl["disp"]]
                    if "vel" in ctrl:
                        trial_v[:] = frame[ctrl["vel"]]
                    if "accel" in ctrl:
                        trial_a[:] = frame[ctrl["accel"]]
                    trial_t = float(frame[ctrl["time"]][0]) if "time" in ctrl else float("nan")
                    if "time" in ctrl and not (
                        math.isfinite(trial_t) and abs(trial_t) <= MAX_TRIAL_TIME
                    ):
                        mb.close(
                            f"openfresco: trial time {trial_t!r} s is not a time of a test "
                            f"(finite, at most {MAX_TRIAL_TIME:g} s)",
                            fault=True,
                        )
                        return
                    if not np.all(np.isfinite(trial_u)):
                        mb.close(
                            f"openfresco: trial displacement {trial_u.tolist()} is not finite",
                            fault=True,
                        )
                        return
                    if not elem:  # OpenFresco executes on setTrialResponse
                        executed = None
                elif action in (P.GET_FORCE, P.GET_DAQ, P.EXECUTE):
                    key = (trial_u.tobytes(), trial_t)
                    if key != executed:
                        fault = self._check_trial(trial_t)
                        if fault is not None:  # before the trial reaches the actuator
                            mb.close(fault, fault=True)
                            return
                        seq += 1
                        t = Target(
                            seq,
                            m.to_actuators(trial_u),
                            m.to_actuators(trial_v) if has_vel else None,
                            trial_t,
                            time.perf_counter(),
                        )
                        with mb.cond:
                            mb.target = t
                            mb.cond.notify_all()
                            while mb.reply_seq < seq and mb.closed is None:
                                mb.cond.wait()
                        if mb.closed is not None:
                            return
                        executed = key
                    if action == P.EXECUTE:
                        continue
                    out[:] = 0.0
                    if action == P.GET_FORCE:
                        out[: m.n_dofs] = m.to_dofs(mb.measured_force)
                    elif elem:
                        out[daq["force"]] = m.to_dofs(mb.measured_force)
                    else:
                        self._pack_daq(out, daq, trial_u)
                    self._send(out)
                elif P.GET_DISP <= action <= P.GET_TIME:
                    out[:] = 0.0
                    if action == P.GET_DISP:
                        if mb.measured_disp is None:
                            out[: m.n_dofs] = trial_u
                        else:
                            out[: m.n_dofs] = m.dofs_from_measured(trial_u, mb.measured_disp)
                    elif action == P.GET_VEL:
                        out[: m.n_dofs] = trial_v
                    elif action == P.GET_ACCEL:
                        out[: m.n_dofs] = trial_a
                    else:  # GET_TIME
                        out[0] = mb.measured_time
                    self._send(out)
                elif action in (P.GET_INITIAL_STIFF, P.GET_TANGENT_STIFF, P.GET_DAMP, P.GET_MASS):
                    mat = m.matrix(action)
                    out[:] = 0.0
                    out[: mat.size] = mat.ravel(order="F")  # column-major, as OpenSees' Matrix
                    self._send(out)
                elif action == P.DIE:
                    mb.close("die", fault=False)
                    return
                elif action == P.COMMIT:  # the step is over: the next trial starts a new one
                    self._commits += 1
                    self._trials = 0
                # OPEN, SETUP, COMMIT: nothing to answer
        except OSError as exc:
            mb.close(f"openfresco: connection error: {exc}", fault=True)
        except Exception as exc:  # never leave the loop waiting on a dead thread
            log.exception("openfresco server thread failed")
            mb.close(f"openfresco: server error: {exc!r}", fault=True)

    def _check_trial(self, t: float) -> str | None:
        """A fault line when a new trial must not reach the actuator, else None.

        * **Repeated trials within one time step.** A trial whose analysis time ``t`` equals
          the previous trial's (or, for a client without a time block, a second trial before
          ``commitState``) is an iteration of OpenSees' solution algorithm: with Newton and an
          implicit Newmark every iteration would be imposed on the specimen (a one-step
          example sent 4–5 per step; docs/opensees.md). More than :attr:`max_trials` distinct
          trials in one step stop the site, before the extra trial moves the actuator.
        * **A time step that is not a whole number of loop periods.** With :attr:`loop_dt`
          set (lockstep and predictor–corrector timing), OpenSees' step ``Δt_OS`` is executed
          in ``round(Δt_OS / Δt)`` loop steps; off by more than 0.1 % it would compress or
          stretch the specimen's time (``dt = 0.005 s`` at 1024 Hz: 5 steps, −2.3 %).
        """
        finite = math.isfinite(t)
        if finite and t <= self._last_t + 1e-9 * max(1.0, abs(t)) and self._trials:
            self._trials += 1  # the same analysis time: an iteration
        elif finite:
            span = t - self._last_t
            self._trials = 1
            if self.loop_dt is not None and span > 0:
                msg = _dt_fault(span, self.loop_dt)
                if msg is not None:
                    return msg
            self._last_t = t
        elif self._commits:  # no time block: trials since the last commitState
            self._trials += 1
        else:
            self._trials = 1
        if self.max_trials and self._trials > self.max_trials:
            when = f"t = {t:.6g} s" if finite else "before its commitState"
            return (
                f"openfresco: OpenSees sent trial {self._trials} of one time step ({when}): "
                "its solution algorithm iterates (Newton with implicit Newmark?) and every "
                "iteration would move the actuator; use integrator('NewmarkExplicit', 0.5) "
                "with algorithm('Linear'), or openfresco.timing = 'predictor-corrector'"
            )
        return None

    def _pack_daq(self, out: np.ndarray, daq: dict[str, slice], trial_u: np.ndarray) -> None:
        mb = self.mailbox
        if "disp" in daq:
            out[daq["disp"]] = mb.measured_disp
        if "force" in daq:
            out[daq["force"]] = mb.measured_force
        if "time" in daq:
            out[daq["time"]] = mb.measured_time
        # velocity and acceleration are not measured by the site: zeros


def _dt_fault(span: float, loop_dt: float) -> str | None:
    """A fault line when OpenSees' step ``span`` (s) is not a whole number of loop periods
    ``loop_dt`` within 0.1 %, naming a ``loop.fs`` and an OpenSees ``dt`` that would fit."""
    r = span / loop_dt
    m = max(1, round(r))
    if abs(r - m) <= 1e-3 * r:
        return None
    fs = 1.0 / loop_dt
    return (
        f"openfresco: OpenSees' time step {span:.6g} s is {r:.3f} loop periods at loop.fs = "
        f"{fs:g} Hz, not a whole number (within 0.1 %): executed in {m} it would change the "
        f"specimen's time by {100.0 * (m / r - 1.0):+.1f} %; use loop.fs = {m / span:.6g} Hz "
        f"or an OpenSees dt of {m * loop_dt:.10g} s"
    )

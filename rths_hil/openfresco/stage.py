"""The experimental site as the runner's structure stage (``structure.kind = "openfresco"``).

The runner (:mod:`rths_hil.hybrid.runner`) asks its structure stage, once per loop step, for
the next targets given the measured forces (:class:`rths_hil.structures.stages.StructureStage`).
Here the answer comes from OpenSees: :class:`SiteStage` wraps an
:class:`~rths_hil.openfresco.site.ExperimentalSite` whose DOFs are the actuator channels (the
site maps OpenSees' element DOFs to them), so the channels use ``dof = i`` and compensation,
FEI, Kalman, safety and the crash-safe record work as in every run.

* :meth:`SiteStage.listen` binds (the CLI prints the ``genericClient`` line to paste), and
  :meth:`SiteStage.reset` waits for the client before the clock starts.
* A clean end (DIE, or the client closing after it) sets :attr:`finished`: the run completes.
* A fault (disconnect mid-test, a wrong frame, OpenSees too late) sets :attr:`finished` and
  :attr:`trip` (rule ``openfresco``, one line): the runner e-stops every channel, the actuators
  hold, and :meth:`close` then drops the connection (OpenSees reports its failed element).
* Per loop step, two columns of the crash-safe record (:attr:`SiteStage.record_columns`,
  written and flushed with the row): ``of_kind``, how the row's target was made (the codes of
  :data:`~rths_hil.openfresco.timing.KINDS`: 0 idle, 1 executed, 2 predicted, 3 corrected,
  4 held), and ``of_latency``, OpenSees' latency of the trial that arrived during the step
  (force reply → next request, s; NaN in steps without a new trial and for the first trial).
  At the end, the session's counts (actions, kinds, latency p50/max, how it ended) go to
  ``openfresco.json`` in the run directory.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..safety import Trip
from ..structures.stages import StageContext
from .site import ExperimentalSite
from .timing import IDLE, KINDS, SiteFault

log = logging.getLogger(__name__)

__all__ = ["SiteStage"]


def _never() -> bool:
    return False


_KIND_CODES = ", ".join(f"{i} {name}" for i, name in KINDS.items())


class SiteStage:
    """Structure stage driven by an OpenSees ``genericClient`` / OpenFresco ``GenericTCP``.

    Parameters
    ----------
    options : mapping
        The ``[openfresco]`` table.
    dt : float
        Loop step (s).
    n_dof : int
        Number of actuator channels.
    """

    #: The stage's record columns (:class:`rths_hil.structures.stages.StructureStage`): name,
    #: attribute, dtype, unit, description.
    record_columns = (
        ("of_kind", "kind", "<i8", "-", f"how the row's target was made ({_KIND_CODES})"),
        (
            "of_latency",
            "latency",
            "<f8",
            "s",
            "OpenSees' latency of the trial that arrived in this step, force reply to next "
            "request (NaN: no new trial, or the first)",
        ),
    )

    #: the targets come from OpenSees: nothing is known of them before the run starts
    external = True

    def __init__(self, options, dt: float, n_dof: int = 1) -> None:
        self.site = ExperimentalSite(options, dt, n_dof)
        self.dt = float(dt)
        self.n_dof = int(n_dof)
        self.v = [0.0] * self.n_dof
        self.r = [math.nan] * self.n_dof
        self.finished = False
        self.trip: Trip | None = None
        self.run_dir: Path | None = None
        self._chans: list = []  # the runner's channels, in DOF order
        self._stop: Callable[[], bool] = _never
        self._x = [0.0] * self.n_dof
        self.kind = IDLE  # of_kind of the row being written: how its target was made
        self.latency = math.nan  # of_latency: OpenSees' latency of a trial new in this step
        self._next_kind = IDLE  # kind of the target step() just returned (the next row's)
        self._closed = False

    # -- set-up -------------------------------------------------------------------------------
    @property
    def loop_mode(self) -> str:
        """``lockstep`` or ``paced``, as the timing mode needs."""
        return self.site.loop_mode

    def listen(self) -> tuple[str, int]:
        """Bind and listen (idempotent); ``(host, port)``."""
        if self.site.server is None:
            self.site.listen()
        return self.site.server.host, self.site.server.port

    def paste_lines(self) -> tuple[str, str]:
        """The OpenSeesPy and Tcl ``genericClient`` lines for this site."""
        return self.site.paste_lines()

    def attach(self, context: StageContext) -> None:
        """The test this stage serves: its channels (measurements, keep-alive), the operator
        stop and the run directory."""
        self.run_dir = Path(context.run_dir)
        self._chans = list(context.channels)
        self._stop = context.stop_requested

    def reset(self) -> list[float]:
        """Wait for the client and its ID; the targets of step 0 (rest)."""
        self.listen()
        stop = self._stop
        ses = self.site.accept(stop)
        log.info("openfresco: client connected, ID %s", ses.as_tuple())
        tm = self.site.timing
        tm.stop = stop
        tm.keepalive = self._keepalive
        tm.resume = self._resume
        self._x = [0.0] * self.n_dof
        self.kind = self._next_kind = IDLE
        self.latency = math.nan
        return list(self._x)

    def _keepalive(self) -> None:
        """While the loop waits for OpenSees: each channel's heartbeat (the actuator holds).

        The controllers' own watchdogs (the twins' heartbeat timeout, a real controller's) are
        fed by the heartbeat; an in-process twin is served so that it sees it.
        """
        for ch in self._chans:
            try:
                ch.keepalive()
            except Exception as exc:  # the next step's command and reply will tell
                log.warning("openfresco: heartbeat while waiting for OpenSees failed: %s", exc)

    def _resume(self) -> None:
        """After a wait for OpenSees: restart the feedback watchdogs' clocks.

        The loop sent no command while it waited (virtual time stood still), so no reply was
        due: the wait is not controller silence. The next command's reply is checked as usual.
        """
        for ch in self._chans:
            ch.restart_watchdog()

    # -- stepping -----------------------------------------------------------------------------
    def step(self, k: int, ag: float, force) -> list[float]:
        """Measured forces of step ``k`` in, targets of step ``k + 1`` out (see the module).

        Sets :attr:`kind` (row ``k``'s target, returned by the previous call) and
        :attr:`latency` (a trial taken in this call) for the record's row ``k``.
        """
        self.kind = self._next_kind
        self.latency = math.nan
        if self.finished:
            return self._x
        chans = self._chans
        disp = [ch.measured for ch in chans] if chans else self._x
        tm = self.site.timing
        n_kinds = len(tm.kinds) if tm is not None else 0
        n_targets = len(tm.targets) if tm is not None else 0
        try:
            c = self.site.step(k, np.asarray(disp, dtype=float), np.asarray(force, dtype=float))
        except SiteFault as exc:
            self.trip = Trip("openfresco", str(exc)).at(k * self.dt, k)
            self.finished = True
            log.warning("%s", exc)
            return self._x
        tm = self.site.timing
        if len(tm.targets) > n_targets:
            self.latency = tm.targets[-1][2]
        if c is None:
            self.finished = True
            return self._x
        if len(tm.kinds) > n_kinds:
            self._next_kind = tm.kinds[-1]
        x = c.tolist()
        self.v = [(a - b) / self.dt for a, b in zip(x, self._x, strict=True)]
        self._x = x
        return x

    # -- end ----------------------------------------------------------------------------------
    def close(self) -> None:
        """Drop the connection (after the runner's e-stop) and write the session's counts."""
        if self._closed:
            return
        self._closed = True
        self.site.close()
        if self.run_dir is None or self.site.timing is None:
            return
        summary = self.summary()
        (self.run_dir / "openfresco.json").write_text(json.dumps(summary, indent=1) + "\n")

    def summary(self) -> dict[str, Any]:
        """The site's counts (actions, command kinds, latencies) and how the session ended."""
        out = self.site.summary()
        out["fault"] = self.trip.reason if self.trip is not None else None
        out["finished"] = self.finished
        return out

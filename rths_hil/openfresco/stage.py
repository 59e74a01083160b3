"""The experimental site as the runner's structure stage (``structure.kind = "openfresco"``).

The runner (:mod:`rths_hil.hybrid.runner`) asks its structure stage, once per loop step, for
the next targets given the measured forces (:class:`rths_hil.hybrid.structures.StructureStage`).
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
* Per loop step the command kind (executed, predicted, corrected, held, idle) and per target
  OpenSees' latency are appended to ``openfresco.npz`` in the run directory at the end, with a
  summary in ``openfresco.json``; the kinds are also flushed to ``openfresco_kinds.u8`` every
  256 steps so a crashed run keeps them.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..safety import Trip
from .site import ExperimentalSite
from .timing import SiteFault

log = logging.getLogger(__name__)

__all__ = ["SiteStage"]


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

    def __init__(self, options, dt: float, n_dof: int = 1) -> None:
        self.site = ExperimentalSite(options, dt, n_dof)
        self.dt = float(dt)
        self.n_dof = int(n_dof)
        self.v = [0.0] * self.n_dof
        self.r = [math.nan] * self.n_dof
        self.finished = False
        self.trip: Trip | None = None
        self.runner: Any = None
        self.run_dir: Path | None = None
        self._x = [0.0] * self.n_dof
        self._kinds_file = None
        self._flushed = 0
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

    def attach(self, runner: Any) -> None:
        """The runner this stage serves (its channels' measurements, its stop flag, run dir)."""
        self.runner = runner
        self.run_dir = Path(runner.plan.run_dir)
        chans = runner.channels
        order = sorted(range(len(chans)), key=lambda i: chans[i].dof)
        self._chans = [chans[i] for i in order]

    def reset(self) -> list[float]:
        """Wait for the client and its ID; the targets of step 0 (rest)."""
        self.listen()
        runner = self.runner
        stop = (lambda: runner.stop_signal is not None) if runner is not None else (lambda: False)
        ses = self.site.accept(stop)
        log.info("openfresco: client connected, ID %s", ses.as_tuple())
        if self.run_dir is not None:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            self._kinds_file = open(self.run_dir / "openfresco_kinds.u8", "wb")
        self._x = [0.0] * self.n_dof
        return list(self._x)

    # -- stepping -----------------------------------------------------------------------------
    def step(self, k: int, ag: float, force) -> list[float]:
        """Measured forces of step ``k`` in, targets of step ``k + 1`` out (see the module)."""
        if self.finished:
            return self._x
        chans = getattr(self, "_chans", None)
        disp = [ch.meas for ch in chans] if chans else self._x
        try:
            c = self.site.step(k, np.asarray(disp, dtype=float), np.asarray(force, dtype=float))
        except SiteFault as exc:
            self.trip = Trip("openfresco", str(exc)).at(k * self.dt, k)
            self.finished = True
            log.warning("%s", exc)
            return self._x
        if c is None:
            self.finished = True
            return self._x
        x = c.tolist()
        self.v = [(a - b) / self.dt for a, b in zip(x, self._x, strict=True)]
        self._x = x
        if self._kinds_file is not None and k - self._flushed >= 256:
            self._flush()
        return x

    def _flush(self) -> None:
        kinds = self.site.timing.kinds if self.site.timing is not None else []
        n = len(kinds)
        if n > self._flushed and self._kinds_file is not None:
            self._kinds_file.write(bytes(kinds[self._flushed : n]))
            self._kinds_file.flush()
            self._flushed = n

    # -- end ----------------------------------------------------------------------------------
    def close(self) -> None:
        """Drop the connection (after the runner's e-stop) and write the site's record."""
        if self._closed:
            return
        self._closed = True
        self.site.close()
        if self._kinds_file is not None:
            self._flush()
            self._kinds_file.close()
        tm = self.site.timing
        if self.run_dir is None or tm is None:
            return
        targets = np.array(tm.targets, dtype=float).reshape(-1, 4)
        np.savez(
            self.run_dir / "openfresco.npz",
            kinds=np.asarray(tm.kinds, dtype=np.uint8),
            target_seq=targets[:, 0].astype(np.int64),
            target_step=targets[:, 1].astype(np.int64),
            target_latency=targets[:, 2],
            target_time=targets[:, 3],
        )
        summary = self.summary()
        (self.run_dir / "openfresco.json").write_text(json.dumps(summary, indent=1) + "\n")

    def summary(self) -> dict[str, Any]:
        """The site's counts (actions, command kinds, latencies) and how the session ended."""
        out = self.site.summary()
        out["fault"] = self.trip.reason if self.trip is not None else None
        out["finished"] = self.finished
        return out

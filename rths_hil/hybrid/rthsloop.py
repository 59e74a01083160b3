"""A configured test, ready to run: :class:`RTHSLoop` and :func:`run`.

:func:`run`, :class:`RTHSLoop` and :class:`~rths_hil.hybrid.result.RunResult` are what the
CLI, tuning, studies and tests call (also as ``rths_hil.hybrid.RTHSLoop`` …). The
configuration becomes a plan (:mod:`rths_hil.hybrid.plan`: structure, one channel per
actuator, record columns), the runner steps it (:mod:`rths_hil.hybrid.runner`), each actuator
is a channel (:mod:`rths_hil.hybrid.channel`: driver ⇄ twin, compensator, evaluators, safety
rules), and pacing and overrun attribution are in :mod:`rths_hil.hybrid.timing`. With several
actuators every channel's command is sent before any reply is awaited (``docs/channels.md``).

One loop ties together the numerical substructure (:class:`rths_hil.structures.sdof.CRStepper` or a
multi-DOF model), the compensator (:mod:`rths_hil.compensators.inverse`),
a bus driver (:mod:`drivers`)
talking to a twin (:mod:`rths_hil.sim_backends.twin`) or a real controller, the online evaluators
(streaming and exact :class:`rths_hil.fei.OnlineFEI`,
:class:`rths_hil.estimation.DelayGainEstimator`), the safety rules (:mod:`rths_hil.safety`)
and the crash-safe recorder (:mod:`rths_hil.records.recorder`).

Step order
----------
Logically every step ``k`` is: integrate the structure with the measured restoring force (CR)
→ ``target[k]`` → compensation ``command[k]`` → driver send → feedback (with timeout) → online
FEI and Kalman → safety → recorder. The CR algorithm is explicit in displacement (Chen & Ricles
2008): ``x[k+1]`` depends only on the state of step ``k``. The loop exploits this by rotating
the work so that the send is the first thing done at a deadline::

    deadline k:  send command[k] (already computed)        <- nothing before the send
                 receive feedback k (measured[k], force[k])
                 safety: watchdog, sequence, controller status, NaN, limits, stuck
                 CR: commit step k with force[k] -> target[k+1]; compensate -> command[k+1]
                 safety: target[k+1], velocity[k], command[k+1] checked *before* command[k+1]
                 is ever sent
                 streaming FEI (every sample), exact FEI (every exact_hop), Kalman
                 safety: FEI rule, Kalman rule, overruns
                 recorder: row k
    deadline k+1: send command[k+1] ...

so the command leaves at the deadline with no computation in front of it, and the integration
uses the force measured at the displacement it imposed (no extra step of lag).

Modes
-----
``paced``
    Wall clock. Deadline ``k`` is ``t0 + k·Δt`` (an absolute grid: no drift); ``t0``
    continues the start ramp's grid, or is one period (at least 2 ms) away when no ramp ran.
    The loop sleeps until ``spin`` before the deadline (at least 0.1 Δt when 0.2 Δt remain: a
    SCHED_FIFO thread that never sleeps is stopped ≈ 50 ms a second by the kernel's RT
    bandwidth limit), then busy-waits, then sends;
    ``lateness[k] = t_send − deadline`` is recorded, and ``ready[k]`` (when the previous step's
    work was done, minus the deadline) attributes each overrun to the machine or to the work
    (:func:`attribute_overruns`, measured against :func:`paced_floor`).
    **Overrun policy**: a step whose command leaves more than ``overrun_threshold·Δt`` after its
    deadline is an overrun. Steps are never skipped and the grid is never shifted (skipping
    would change the integration step; shifting would make the test slower than real time):
    after a long step the following ones start at once until the loop has caught up with the
    grid. ``safety.max_overruns`` consecutive overruns trip the e-stop. During a paced run the
    interpreter's thread switch interval is lowered to 100 µs (``sys.setswitchinterval``) so
    that the in-process twin, the exact-FEI worker and the loop hand the GIL over quickly, and
    the cyclic garbage collector is paused.
``lockstep``
    Virtual time: each step waits for its reply (``loop.lockstep_timeout``, 5 s by default)
    and starts the next one at once. Deterministic; for CI, tuning and what-if runs. Lateness
    is recorded as 0.

The exact-FEI cross-check runs synchronously in lockstep and in a worker thread when paced, so
its O(N log N) windows never sit on the step path.

On a trip (or an operator stop) the loop sends the e-stop through the driver, records the step
that tripped and the event (time, step, rule, values), confirms the latch with one status poll,
flushes the record and returns; the CLI prints one line and exits with 3 (130 for an operator
stop, SIGINT or SIGTERM).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..config import Config
from .plan import TestPlan, build_plan
from .result import RunResult
from .runner import Runner

__all__ = ["RTHSLoop", "run"]


class RTHSLoop:
    """A configured RTHS test, ready to :meth:`run`.

    Parameters
    ----------
    cfg : Config
        Resolved configuration (:func:`rths_hil.config.load_config`).
    run_dir : str or Path, optional
        Run directory; default from ``output.dir``.
    plant : Plant or dict, optional
        Use this plant in the twin instead of building one from ``[twin]`` (tests, what-ifs);
        with several channels ``{channel name: plant}``.
    live : callable, optional
        Called with a status dict every ``loop.console`` seconds (the console line).
    mode : {"paced", "lockstep"}, optional
        Overrides ``loop.mode``.
    duration : float, optional
        Overrides ``loop.duration`` (s; 0 = whole record).

    Notes
    -----
    Construction validates and plans everything (:func:`rths_hil.hybrid.plan.build_plan`);
    :meth:`run` opens the twins, the drivers and the recorder and steps
    (:class:`rths_hil.hybrid.runner.Runner`). After the run, :attr:`channels` holds the
    channels (their drivers and twins), :attr:`driver` and :attr:`twin` those of the first.
    """

    runner_class: type[Runner] = Runner

    def __init__(
        self,
        cfg: Config,
        run_dir: str | Path | None = None,
        *,
        plant: Any = None,
        live: Callable[[dict], None] | None = None,
        mode: str | None = None,
        duration: float | None = None,
    ) -> None:
        self.cfg = cfg
        self.plan: TestPlan = build_plan(cfg, run_dir, plant=plant, mode=mode, duration=duration)
        p = self.plan
        self.mode, self.fs, self.dt, self.n_steps = p.mode, p.fs, p.dt, p.n_steps
        self.run_dir = p.run_dir
        self.ag = p.ag
        self.ground_motion = p.ground_motion
        self.structure = p.structure
        self.twin_enabled = any(c.twin_enabled for c in p.channels)
        self.runner = self.runner_class(p, live=live)
        self.channels = self.runner.channels
        self.result: RunResult | None = None

    @property
    def live(self) -> Callable[[dict], None] | None:
        """The console callback (settable before :meth:`run`)."""
        return self.runner.live

    @live.setter
    def live(self, fn: Callable[[dict], None] | None) -> None:
        self.runner.live = fn

    @property
    def console_interval(self) -> float:
        """Seconds between console calls (``loop.console``; settable before :meth:`run`)."""
        return self.plan.console_interval

    @console_interval.setter
    def console_interval(self, value: float) -> None:
        self.plan.console_interval = float(value)

    @property
    def driver(self):
        """The first channel's driver (after :meth:`run`)."""
        return self.channels[0].driver

    @property
    def twin(self):
        """The first channel's twin endpoint (after :meth:`run`; None on hardware)."""
        return self.channels[0].twin

    def run(self) -> RunResult:
        """Run the test; return a :class:`RunResult` (never raises on a safety trip)."""
        self.result = self.runner.run()
        return self.result


def run(
    config: str | Path | Config | dict | None = None,
    overrides: Any = (),
    **kwargs: Any,
) -> RunResult:
    """Load a configuration (path, dict, :class:`Config` or the embedded default) and run it.

    ``overrides`` are ``--set`` strings or a dict of dotted keys
    (:func:`rths_hil.api.configure`); ``kwargs`` go to :class:`RTHSLoop` (``run_dir``,
    ``plant``, ``live``, ``mode``, ``duration``). The documented entry point for scripts and
    notebooks is :func:`rths_hil.run` (``docs/api.md``).
    """
    if isinstance(config, Config) and not overrides:
        cfg = config
    else:
        from ..api import configure

        cfg = configure(config, overrides or None)
    return RTHSLoop(cfg, **kwargs).run()

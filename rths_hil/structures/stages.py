"""Structure stages: the numerical substructure as the runner sees it.

A structure stage turns the measured restoring forces of the DOFs into the next targets of the
DOFs. It is the one place the runner asks "where do the actuators go next"; anything that can
answer it can drive a test: the paper's SDOF frame (:class:`SDOFStage`, Chen & Ricles' CR
integration), a shear building or a model given by its matrices (:class:`MDOFStage`, the CR
integrator in matrix form of :mod:`rths_hil.structures.mdof`), or an experimental site's client
(OpenSees/OpenFresco) whose analysis computes the targets.

The interface (:class:`StructureStage`)::

    stage.n_dof                      number of DOFs n
    stage.reset() -> x0              DOF displacements of step 0 (list of n floats)
    stage.step(k, ag, force) -> x    commit step k with the measured DOF forces Tᵀ·f (list of
                                     n floats, N) and the ground acceleration of step k
                                     (m/s²); return the DOF displacements of step k+1. At
                                     k = 0 nothing is committed: the explicit prediction from
                                     the initial state is returned (the force at rest is not
                                     used), as in CR's first step.
    stage.v, stage.r                 DOF velocities (m/s) and numerical restoring forces (N)
                                     of the last committed step (lists of n floats)
    stage.finished                   True when the structure ends the test early (an external
                                     analysis that stopped); the runner then stops, completed
    stage.trip                       a Trip when the stage ended the test by a fault
                                     (``finished`` too): the runner e-stops every channel
    stage.close()                    release what the stage holds (sockets, processes)
    stage.record_columns             the stage's own record columns (``()`` for none),
                                     ``(name, attribute, dtype, unit, description)`` each;
                                     the plan appends them to the record and the runner
                                     writes the stage's ``attribute`` into every row after
                                     ``step`` (the OpenSees site's ``of_kind``, ``of_latency``)
    stage.external                   the targets come from an external analysis: nothing is
                                     known of them before the run starts
    stage.attach(context)            called once before ``reset``: what the stage may use of
                                     the running test (:class:`StageContext`: the channels'
                                     measured displacements and keep-alive, the operator
                                     stop, the run directory)

Explicit integration is what makes the loop work: the targets of step k+1 are known before
the force of step k+1 is measured (Chen & Ricles 2008), so every command leaves at its deadline
with no computation in front of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from ..safety import Trip

__all__ = ["MDOFStage", "SDOFStage", "StageContext", "StructureStage", "TrialColumns"]


@dataclass
class StageContext:
    """What a structure stage may use of the running test (:meth:`StructureStage.attach`).

    Attributes
    ----------
    run_dir : Path
        The run directory (a stage may write its own summary there).
    channels : list of Channel
        The actuator channels (:class:`rths_hil.hybrid.channel.Channel`), in DOF order: their
        ``measured`` displacement of the current step, :meth:`keepalive` and
        :meth:`restart_watchdog` while the loop waits for an external analysis.
    stop_requested : callable
        True once the operator asked to stop (Ctrl-C, SIGTERM).
    """

    run_dir: Path
    channels: list[Any]
    stop_requested: Callable[[], bool]


@runtime_checkable
class StructureStage(Protocol):
    """What the runner needs from the numerical substructure (see the module docstring)."""

    n_dof: int
    v: list[float]
    r: list[float]
    finished: bool
    trip: Trip | None
    external: bool

    @property
    def record_columns(self) -> tuple[tuple[str, str, str, str, str], ...]:
        """The stage's own record columns: name, attribute, dtype, unit, description."""
        ...

    def attach(self, context: StageContext) -> None:
        """What the stage may use of the running test, before :meth:`reset`."""
        ...

    def reset(self) -> list[float]:
        """DOF displacements of step 0."""
        ...

    def step(self, k: int, ag: float, force: Sequence[float]) -> list[float]:
        """Commit step ``k`` with the measured DOF forces; the DOF displacements of step k+1."""
        ...

    def close(self) -> None:
        """Release resources (idempotent)."""
        ...


class _StepperStage:
    """A structure stepper (``step(ag, extra_force)``, ``x_next``, ``v``) as a stage of ``n_dof``
    DOFs, on its own (no context, nothing to release)."""

    trip: Trip | None = None
    external = False
    record_columns: tuple[tuple[str, str, str, str, str], ...] = ()

    def __init__(self, stepper, n_dof: int) -> None:
        self.stepper = stepper
        self._step = stepper.step
        self.n_dof = n_dof
        self.v = [0.0] * n_dof
        self.r = [0.0] * n_dof
        self.finished = False

    def attach(self, context: StageContext) -> None:
        pass

    def close(self) -> None:
        pass


class SDOFStage(_StepperStage):
    """The paper's SDOF frame: :class:`~rths_hil.structures.sdof.CRStepper` as a stage.

    Parameters
    ----------
    stepper : CRStepper
        The CR stepper (Chen & Ricles 2008; Bouc-Wen restoring force, the FEI paper Eq. 4.1–4.2).
    """

    def __init__(self, stepper) -> None:
        super().__init__(stepper, 1)

    def reset(self) -> list[float]:
        st = self.stepper
        self.v[0] = st.v
        self.r[0] = st.restoring_force
        return [st.x]

    def step(self, k: int, ag: float, force: Sequence[float]) -> list[float]:
        st = self.stepper
        if k == 0:
            return [st.x_next]
        x = self._step(ag, force[0])
        self.v[0] = st.v
        self.r[0] = st.restoring_force
        return [x]


class MDOFStage(_StepperStage):
    """A multi-DOF model (shear building, matrices) behind the stage interface.

    Parameters
    ----------
    stepper
        CR integrator in matrix form (:mod:`rths_hil.structures.mdof`): ``x_next``
        (n-vector known before
        the force is measured), ``step(ag, extra_force) -> x_next``, ``v`` and (if it has one)
        ``restoring_force``.
    """

    def __init__(self, stepper) -> None:
        super().__init__(stepper, len(stepper.x_next))

    def _state(self) -> None:
        st = self.stepper
        self.v = [float(x) for x in st.v]
        r = getattr(st, "restoring_force", None)
        self.r = [float(x) for x in r] if r is not None else [math.nan] * self.n_dof

    def reset(self) -> list[float]:
        self._state()
        return [float(x) for x in self.stepper.x]

    def step(self, k: int, ag: float, force: Sequence[float]) -> list[float]:
        import numpy as np

        st = self.stepper
        if k == 0:
            return [float(x) for x in st.x_next]
        x = self._step(ag, np.asarray(force, dtype=float))
        self._state()
        return x.tolist()


class TrialColumns:
    """A structure stage with each force channel's trial displacement as a record column.

    A force-controlled channel's ``target`` and ``command`` are forces; the structure's
    displacement along it, the one the force target is computed for
    (:attr:`rths_hil.hybrid.channel.Channel.trial`), is recorded beside them as
    ``trial_<channel>`` (``trial`` for a single channel; m), so that the compatibility error
    ``measured − trial`` can be read from the record. Everything else is the wrapped stage's.

    Parameters
    ----------
    stage : StructureStage
        The stage.
    columns : list of (channel name, column name)
        The force channels and their columns.
    """

    def __init__(self, stage: Any, columns: list[tuple[str, str]]) -> None:
        self.stage = stage
        self._names = [name for name, _ in columns]
        self._chans: list[Any] = []
        self.record_columns = tuple(stage.record_columns) + tuple(
            (
                col,
                f"trial_{j}",
                "<f8",
                "m",
                "force channel: the structure's trial displacement along the actuator, the "
                "one its force target is computed for",
            )
            for j, (_, col) in enumerate(columns)
        )

    def attach(self, context: StageContext) -> None:
        by_name = {ch.name: ch for ch in context.channels}
        self._chans = [by_name[n] for n in self._names]
        self.stage.attach(context)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("trial_") and name[6:].isdigit():
            return self._chans[int(name[6:])].trial
        return getattr(self.__dict__["stage"], name)

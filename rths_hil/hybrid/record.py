"""The run's record: the recorder with the run's metadata, and one row per step by column name.

:func:`open_recorder` creates the run directory's files (:class:`rths_hil.recorder.Recorder`)
with the plan's columns and what a reader needs to interpret them (channels, their suffixes
and transforms, drivers, twins). :func:`row_writer` fills each row from the column table
(:mod:`rths_hil.hybrid.columns`): a loop column from the step's :class:`StepValues`, a channel
column from the :class:`~rths_hil.hybrid.channel.Channel` attribute of its name, a structure
stage's column from the stage's attribute.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from operator import attrgetter
from types import SimpleNamespace
from typing import Any

from ..recorder import Recorder
from .channel import Channel
from .columns import layout
from .plan import TestPlan

__all__ = ["StepValues", "open_recorder", "row_writer"]


class StepValues:
    """The loop's values of the row being written (the ``loop`` columns of the table).

    Attributes
    ----------
    time : float
        Loop time k·Δt (s).
    step : int
        Step index k (also the sequence number sent with the step's commands).
    ground_accel : float
        Ground acceleration of step k (m/s²).
    lateness : float
        Send time minus deadline (s; 0 in lockstep).
    skew : float
        Latest minus earliest reply time over the channels (s; several channels only).
    dofs : list of float
        DOF displacements of step k (several DOFs only: ``u_1 … u_n``).
    """

    __slots__ = ("dofs", "ground_accel", "lateness", "skew", "step", "time")

    def __init__(self) -> None:
        self.time = 0.0
        self.step = 0
        self.ground_accel = 0.0
        self.lateness = 0.0
        self.skew = 0.0
        self.dofs: Sequence[float] = ()


def open_recorder(plan: TestPlan, channels: list[Channel]) -> Recorder:
    """The run's :class:`~rths_hil.recorder.Recorder`: the plan's columns and the run's metadata."""
    cfg = plan.cfg
    first = channels[0]
    return Recorder(
        plan.run_dir,
        plan.fs,
        config=cfg.as_dict(),
        flush_interval=cfg["output"]["flush_interval"],
        columns=plan.columns,
        extra_meta={
            "config_source": cfg.source,
            "mode": plan.mode,
            "planned_steps": plan.n_steps,
            "ground_motion": {
                "name": plan.ground_motion.name,
                "source": plan.ground_motion.source,
                "pga": plan.ground_motion.pga,
            },
            "driver": first.plan.driver_name,
            "twin": first.twin.connection if first.twin is not None else None,
            "window_s": first.plan.window_s,
            "fei_pair": first.plan.fei_pair,
            "n_dof": plan.n_dof,
            "channels": [
                {
                    "name": ch.name,
                    "suffix": ch.suffix,
                    "transform": ch.row,
                    "driver": ch.plan.driver_name,
                    "twin": ch.twin.connection if ch.twin is not None else None,
                    "window_s": ch.plan.window_s,
                    "fei_pair": ch.plan.fei_pair,
                }
                for ch in channels
            ],
        },
    )


def row_writer(
    rec: Recorder, channels: list[Channel], stage: Any, values: StepValues
) -> Callable[[], None]:
    """``write()``: append the row of the current step to ``rec``, every column by name.

    The columns are :func:`rths_hil.hybrid.columns.layout` of ``channels`` on the stage's
    DOFs, then the stage's own :attr:`~rths_hil.hybrid.structures.StructureStage.record_columns`
    (the order of :attr:`TestPlan.columns <rths_hil.hybrid.plan.TestPlan>`). Each column is
    read by a dotted name from one namespace, ``loop.<step value>``, ``ch<i>.<attribute>`` or
    ``stage.<attribute>``; one :func:`operator.attrgetter` reads the row up to the DOF columns
    (one C call, no Python work per column). The DOF displacements ``u_1 … u_n`` (several DOFs
    only) are the list :attr:`StepValues.dofs`; the stage's columns follow them.
    """
    index = {ch.name: i for i, ch in enumerate(channels)}
    single = len(channels) == 1
    names: list[str] = []  # the dotted source of every column before u_1 … u_n
    n_dofs = 0
    for col, ch, dof in layout([ch.name for ch in channels], stage.n_dof):
        if dof >= 0:
            n_dofs += 1
        elif n_dofs:
            raise AssertionError("the DOF columns are not the table's last")  # pragma: no cover
        elif ch is None:
            names.append(f"loop.{col.attribute}")
        else:
            names.append(f"ch{0 if single else index[ch]}.{col.attribute}")
    extra = [f"stage.{c[1]}" for c in stage.record_columns]
    if len(names) + n_dofs + len(extra) != len(rec.columns):
        raise AssertionError("record columns differ from the plan's")  # pragma: no cover
    sources = SimpleNamespace(loop=values, stage=stage)
    for i, ch in enumerate(channels):
        setattr(sources, f"ch{i}", ch)
    head = attrgetter(*names)  # ≥ 3 names: returns a tuple
    append = rec.append
    if not n_dofs and not extra:

        def write() -> None:
            append(*head(sources))

        return write
    tail = [attrgetter(name) for name in extra]

    def write_dofs_and_stage() -> None:
        row = list(head(sources))
        if n_dofs:
            row += values.dofs
        row += [get(sources) for get in tail]
        append(*row)

    return write_dofs_and_stage

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


def _getter(names: list[str]) -> Callable[[Any], tuple]:
    """A function returning the attributes ``names`` of an object as a tuple."""
    if len(names) == 1:
        name = names[0]
        return lambda obj: (getattr(obj, name),)
    return attrgetter(*names)


def row_writer(
    rec: Recorder, channels: list[Channel], stage: Any, values: StepValues
) -> Callable[[], None]:
    """``write()``: append the row of the current step to ``rec``, every column by name.

    The columns are :func:`rths_hil.hybrid.columns.layout` of ``channels`` on the stage's
    DOFs, then the stage's own :attr:`~rths_hil.hybrid.structures.StructureStage.record_columns`
    (the order of :attr:`TestPlan.columns <rths_hil.hybrid.plan.TestPlan>`). Consecutive columns
    of one object are read with one :func:`operator.attrgetter`.
    """
    by_name = {ch.name: ch for ch in channels}
    single = len(channels) == 1
    # (object, attribute) of every column, in file order
    sources: list[tuple[Any, str]] = []
    for col, ch, dof in layout([ch.name for ch in channels], stage.n_dof):
        if dof >= 0:
            if dof == 0:
                sources.append((values, "dofs"))  # u_1 … u_n: the whole list, once
        elif ch is None:
            sources.append((values, col.attribute))
        else:
            sources.append((channels[0] if single else by_name[ch], col.attribute))
    sources += [(stage, c[1]) for c in stage.record_columns]
    if sum(stage.n_dof if a == "dofs" else 1 for _, a in sources) != len(rec.columns):
        raise AssertionError("record columns differ from the plan's")  # pragma: no cover
    # consecutive columns of one object: one getter
    runs: list[tuple[list[str], Any]] = []
    for obj, attr in sources:
        if runs and runs[-1][1] is obj and attr != "dofs" and runs[-1][0] != ["dofs"]:
            runs[-1][0].append(attr)
        else:
            runs.append(([attr], obj))
    parts = [
        (attrgetter("dofs") if names == ["dofs"] else _getter(names), obj) for names, obj in runs
    ]
    append = rec.append

    def write() -> None:
        row: list = []
        for get, obj in parts:
            row += get(obj)
        append(*row)

    return write

"""The run's record: the recorder with the run's metadata, and one row per step by column name.

:func:`open_recorder` creates the run directory's files
(:class:`rths_hil.records.recorder.Recorder`)
with the plan's columns and what a reader needs to interpret them (channels, their suffixes
and transforms, drivers, twins). :func:`row_writer` fills each row from the column table
(:mod:`rths_hil.records.columns`): a loop column from the step's value of its name, a channel
column from the :class:`~rths_hil.hybrid.channel.Channel` attribute of its name, a structure
stage's column from the stage's attribute.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..errors import InputError
from ..hybrid.channel import Channel
from ..hybrid.plan import TestPlan
from .columns import layout
from .recorder import Recorder

__all__ = ["ROW_ARGUMENTS", "open_recorder", "row_writer"]


def open_recorder(plan: TestPlan, channels: list[Channel]) -> Recorder:
    """The run's :class:`~rths_hil.records.recorder.Recorder`: the plan's columns and metadata."""
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
                    # control.mode and the tracked quantity: its column and unit
                    "control": ch.control,
                    "tracked": "force" if ch.force_mode else "measured",
                    "tracked_unit": "N" if ch.force_mode else "m",
                }
                for ch in channels
            ],
        },
    )


#: The loop's values of a row, the parameters of the writer :func:`row_writer` returns: every
#: ``loop`` column of :data:`rths_hil.records.columns.TABLE` takes its value from the parameter
#: of its :attr:`~rths_hil.records.columns.Column.attribute`, ``u_1 … u_n`` from ``dofs``.
ROW_ARGUMENTS = ("time", "step", "ground_accel", "lateness", "skew", "dofs")


def row_writer(rec: Recorder, channels: list[Channel], stage: Any) -> Callable[..., None]:
    """``write(time, step, ground_accel, lateness, skew, dofs)``: append the step's row.

    Every column is named in the writer's code: a loop column is the parameter of its name
    (``seq`` is ``step``: the sequence number sent with step k is k), a channel column the
    :class:`~rths_hil.hybrid.channel.Channel` attribute of its name (``ch0.target``,
    ``ch1.measured`` …), a structure stage's column the stage's attribute (``stage.kind``); the
    DOF displacements ``u_1 … u_n`` (several DOFs only) are ``dofs``. The columns are
    :func:`rths_hil.records.columns.layout` of ``channels`` on the stage's DOFs, then the stage's
    own :attr:`~rths_hil.structures.stages.StructureStage.record_columns` (the order of
    :attr:`TestPlan.columns <rths_hil.hybrid.plan.TestPlan>`).

    The writer is compiled once per run from that list of names, as
    :func:`collections.namedtuple` compiles its class, so that a row costs one call with one
    attribute read per column and no intermediate tuples (the step's budget is a few tens of
    µs). Its source is the writer's ``source`` attribute.
    """
    index = {ch.name: i for i, ch in enumerate(channels)}
    single = len(channels) == 1
    values: list[str] = []
    for col, ch, dof in layout([ch.name for ch in channels], stage.n_dof):
        if dof >= 0:
            if dof == 0:
                values.append("*dofs")
        elif ch is None:
            if col.attribute not in ROW_ARGUMENTS:  # pragma: no cover - a new loop column
                raise AssertionError(f"loop column {col.name}: no row argument {col.attribute}")
            values.append(col.attribute)
        else:
            values.append(f"ch{0 if single else index[ch]}.{col.attribute}")
    for c in stage.record_columns:
        if not str(c[1]).isidentifier():
            raise InputError(f"structure stage column {c[0]}: {c[1]!r} is not an attribute name")
        values.append(f"stage.{c[1]}")
    n = sum(stage.n_dof if v == "*dofs" else 1 for v in values)
    if n != len(rec.columns):  # pragma: no cover
        raise AssertionError("record columns differ from the plan's")
    source = f"def write({', '.join(ROW_ARGUMENTS)}):\n    append({', '.join(values)})\n"
    namespace: dict[str, Any] = {"append": rec.append, "stage": stage}
    namespace.update({f"ch{i}": ch for i, ch in enumerate(channels)})
    exec(compile(source, "<record row>", "exec"), namespace)  # names from the column table
    write = namespace["write"]
    write.source = source
    return write

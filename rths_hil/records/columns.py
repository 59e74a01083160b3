"""The record's columns, defined once: name, dtype, unit, description and what fills each.

:data:`TABLE` lists every column of ``record.npy`` in file order. A column is either the
loop's (one per row: ``time``, ``step`` …) or a channel's (one per actuator: ``target``,
``measured`` …). A channel column is filled from the :class:`~rths_hil.hybrid.channel.Channel`
attribute of the same name, so the channel's state, the record and the readers speak one
vocabulary (as OpenFresco keeps "trial" and "daq" through every layer): ``target`` is the
structure's trial displacement, ``command`` what was sent after compensation, ``measured`` and
``force`` the controller's reply. A loop column is filled from the runner's step value of
:attr:`Column.source` (``seq`` is the step index: the sequence number sent with step k is k).

File order is the table's order; a run of consecutive channel columns is written once per
channel before the next loop column (``target_left … kf_delay_left, target_right …
kf_delay_right, lateness, feedback_ok_left, feedback_ok_right, seq, …``). A record of one
actuator names its channel columns plainly (``target``); a record of several suffixes each with
``_<channel name>`` (:func:`column_name`, the rule in one place for the writers and the readers:
report, studies, live view). A record of several DOFs ends with ``u_1 … u_n``, a structure
stage's own columns (:attr:`rths_hil.structures.stages.StructureStage.record_columns`) come
last.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

__all__ = [
    "TABLE",
    "Column",
    "channel_columns",
    "channel_suffix",
    "column_name",
    "layout",
    "single_channel_columns",
    "specs",
]

#: (name, numpy dtype, unit, description): one column of a record as ``meta.json`` lists it.
Spec = tuple[str, str, str, str]


def channel_suffix(channel: str | None) -> str:
    """Suffix of a channel's columns: ``""`` for the only channel, else ``_<name>``.

    Examples
    --------
    >>> channel_suffix("left"), channel_suffix(None)
    ('_left', '')
    """
    return f"_{channel}" if channel else ""


def column_name(base: str, channel: str | None = None) -> str:
    """Column of ``base`` for ``channel`` (``None`` or ``""`` for a single-channel record).

    Examples
    --------
    >>> column_name("measured", "left"), column_name("measured")
    ('measured_left', 'measured')
    """
    return base + channel_suffix(channel)


@dataclass(frozen=True)
class Column:
    """One column of the record.

    Attributes
    ----------
    name : str
        Column name (a channel column's base name, before the channel suffix).
    dtype : str
        NumPy type code (``<f8``, ``<i8``, ``|b1``).
    unit : str
        SI unit (``-`` for none).
    doc : str
        Description (in ``meta.json``).
    owner : {"loop", "channel", "multi", "dof"}
        ``loop``: one per row; ``channel``: one per actuator; ``multi``: one per row, only in
        a record of several channels; ``dof``: one per DOF (``u_1 … u_n``), only with several
        DOFs.
    source : str
        What fills it: the runner's step value (loop, multi, dof) or the channel attribute
        (channel) of that name; the column name unless given.
    doc_multi : str
        Description in a record of several channels, where it differs.
    """

    name: str
    dtype: str
    unit: str
    doc: str
    owner: str = "channel"
    source: str = ""
    doc_multi: str = ""

    @property
    def attribute(self) -> str:
        """The step value or :class:`~rths_hil.hybrid.channel.Channel` attribute filling it."""
        return self.source or self.name

    def spec(self, channel: str | None = None, multi: bool = False) -> Spec:
        """``(name, dtype, unit, description)`` of this column for ``channel``."""
        doc = self.doc_multi if multi and self.doc_multi else self.doc
        return (column_name(self.name, channel), self.dtype, self.unit, doc)


def _loop(name: str, dtype: str, unit: str, doc: str, source: str = "") -> Column:
    return Column(name, dtype, unit, doc, "loop", source)


#: Every column of a record, in file order (see the module docstring).
TABLE: tuple[Column, ...] = (
    _loop("time", "<f8", "s", "loop time of the step (k·Δt)"),
    _loop("step", "<i8", "-", "step index k"),
    _loop("ground_accel", "<f8", "m/s²", "ground acceleration applied at this step"),
    Column("target", "<f8", "m", "target (calculated) displacement from the structure stepper"),
    Column("command", "<f8", "m", "command sent to the actuator (after compensation)"),
    Column("measured", "<f8", "m", "measured actuator displacement (held when no reply)"),
    Column("force", "<f8", "N", "measured restoring force of the experimental substructure"),
    Column(
        "velocity",
        "<f8",
        "m/s",
        "velocity of the structure (integrator state)",
        doc_multi="velocity of the structure along the actuator (T·v)",
    ),
    Column(
        "restoring_force",
        "<f8",
        "N",
        "numerical substructure restoring force (Bouc-Wen)",
        doc_multi="numerical restoring force along the actuator (T·r)",
    ),
    Column("alpha", "<f8", "-", "compensation α of this step's command (1 + lead·fs)"),
    Column("fei_amplitude", "<f8", "-", "online FEI amplitude A (streaming, window ending here)"),
    Column("fei_delay", "<f8", "s", "online FEI equivalent delay d (streaming)"),
    Column("fei_f_eq", "<f8", "Hz", "online FEI equivalent frequency (streaming)"),
    Column("fei_valid", "|b1", "-", "the streaming window ending here is valid"),
    Column(
        "fei_held",
        "<f8",
        "-",
        "share of held measurements (missed replies) in the streaming window ending here",
    ),
    Column("fei_exact_amplitude", "<f8", "-", "exact online FEI A, latest completed window (held)"),
    Column("fei_exact_delay", "<f8", "s", "exact online FEI d, latest completed window (held)"),
    Column("fei_exact_valid", "|b1", "-", "the latest exact window is valid"),
    Column("kf_gain", "<f8", "-", "Kalman estimate of the actuator gain"),
    Column("kf_delay", "<f8", "s", "Kalman estimate of the actuator delay"),
    _loop("lateness", "<f8", "s", "paced mode: send time minus deadline (0 in lockstep)"),
    Column("feedback_ok", "|b1", "-", "a reply with the right sequence number arrived in time"),
    _loop("seq", "<i8", "-", "sequence number sent with the command", source="step"),
    Column("feedback_time", "<f8", "s", "time from the step's first send to this reply"),
    Column(
        "fei_exact_step",
        "<i8",
        "-",
        "step at which the window of the held exact FEI value ended (-1: none yet)",
    ),
    Column(
        "stability",
        "<f8",
        "-",
        "energy stability indicator S: energy the tracking error injected over the energy the "
        "structure's damping dissipated, in the window ending here (NaN: not valid)",
    ),
    Column(
        "skew",
        "<f8",
        "s",
        "latest minus earliest reply time of the step over the channels",
        owner="multi",
    ),
    Column("u", "<f8", "m", "displacement of DOF {i} (target)", owner="dof"),
)


def channel_columns() -> tuple[Column, ...]:
    """The per-channel columns, in file order (the :class:`Channel` attributes a row reads)."""
    return tuple(c for c in TABLE if c.owner == "channel")


def layout(channels: Sequence[str], n_dof: int) -> list[tuple[Column, str | None, int]]:
    """Every column of a record as ``(column, channel name or None, DOF index or -1)``.

    ``channels`` are the channel names (``[""]``: one unnamed channel). With one channel the
    channel columns carry no suffix (``channel`` is ``""``); a loop column has channel
    ``None``; the ``u_i`` columns (several DOFs only) have their 0-based DOF index.
    """
    names = list(channels) if len(channels) > 1 else [""]
    out: list[tuple[Column, str | None, int]] = []
    run: list[Column] = []  # consecutive channel columns: written once per channel

    def flush() -> None:
        for ch in names:
            out.extend((c, ch, -1) for c in run)
        run.clear()

    for col in TABLE:
        if col.owner == "channel":
            run.append(col)
            continue
        flush()
        if col.owner == "loop" or (col.owner == "multi" and len(names) > 1):
            out.append((col, None, -1))
        elif col.owner == "dof" and n_dof > 1:
            out.extend((col, None, i) for i in range(n_dof))
    flush()
    return out


def specs(channels: Sequence[str], n_dof: int) -> list[Spec]:
    """``(name, dtype, unit, description)`` of every column of :func:`layout`, in file order."""
    multi = len(channels) > 1
    out = []
    for col, ch, i in layout(channels, n_dof):
        if i >= 0:
            out.append((f"{col.name}_{i + 1}", col.dtype, col.unit, col.doc.format(i=i + 1)))
        else:
            out.append(col.spec(ch, multi))
    return out


def single_channel_columns() -> tuple[Spec, ...]:
    """The columns every single-channel record begins with, up to ``seq``.

    What :class:`rths_hil.records.recorder.Recorder` writes by default
    (:data:`rths_hil.records.recorder.COLUMNS`);
    a run adds ``feedback_time``, ``fei_exact_step`` and ``stability`` after them.
    """
    cols = specs([""], 1)
    end = [c[0] for c in cols].index("seq") + 1
    return tuple(cols[:end])

"""The record's columns, defined once (rths_hil.records.columns), and rows written by name."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rths_hil.hybrid.channel import Channel
from rths_hil.records.columns import TABLE, channel_columns, column_name, layout, specs
from rths_hil.records.recorder import COLUMNS, Recorder, read_run
from rths_hil.records.run import row_writer
from rths_hil.watch.source import find_channels


def test_every_channel_column_is_a_channel_attribute_of_its_name():
    slots = set(Channel.__slots__)
    for col in channel_columns():
        assert col.attribute == col.name
        assert col.name in slots, col.name


def test_file_order_of_two_channels_on_three_dofs():
    names = [s[0] for s in specs(["left", "right"], 3)]
    per = [c.name for c in channel_columns()]
    # the documented order, written out by hand from docs/records.md and docs/channels.md
    a = per[: per.index("kf_delay") + 1]
    c = per[per.index("feedback_time") :]
    expected = ["time", "step", "ground_accel"]
    expected += [f"{n}_left" for n in a] + [f"{n}_right" for n in a]
    expected += ["lateness", "feedback_ok_left", "feedback_ok_right", "seq"]
    expected += [f"{n}_left" for n in c] + [f"{n}_right" for n in c]
    expected += ["skew", "u_1", "u_2", "u_3"]
    assert names == expected
    assert len(set(names)) == len(names)
    assert find_channels(names) == ["left", "right"]


def test_single_channel_names_are_plain_and_start_with_the_recorder_default():
    names = [s[0] for s in specs(["only"], 1)]
    assert names[: len(COLUMNS)] == [c[0] for c in COLUMNS]
    assert names[len(COLUMNS) :] == ["feedback_time", "fei_exact_step", "stability"]
    assert column_name("measured", None) == "measured" == column_name("measured", "")
    assert column_name("measured", "left") == "measured_left"


def test_every_table_column_appears_in_a_multi_dof_multi_channel_layout():
    seen = {col.name for col, _, _ in layout(["a", "b"], 2)}
    assert seen == {c.name for c in TABLE}


@pytest.mark.parametrize("channels,n_dof", [([""], 1), (["a", "b"], 2)])
def test_row_writer_reads_each_column_by_name(tmp_path, channels, n_dof):
    """Every column of a written row holds the attribute of its name (values all distinct)."""
    cols = [*specs(channels, n_dof), ("of_kind", "<i8", "-", "stage column")]
    counter = iter(range(1, 10_000))
    chans = []
    for name in channels:
        ch = SimpleNamespace(name=name)
        for col in channel_columns():
            value = next(counter)
            typed = {"|b1": bool(value % 2), "<i8": value, "<f8": value + 0.5}[col.dtype]
            setattr(ch, col.name, typed)
        chans.append(ch)
    stage = SimpleNamespace(
        n_dof=n_dof, record_columns=(("of_kind", "kind", "<i8", "-", "stage column"),), kind=7
    )
    dofs = [10.0 * (i + 1) for i in range(n_dof)]
    with Recorder(tmp_path / "r", 1024.0, columns=cols) as rec:
        write = row_writer(rec, chans, stage)
        write(0.25, 3, -1.5, 1e-4, 2e-5, dofs)
    row = read_run(tmp_path / "r").record[0]
    assert row["time"] == 0.25 and row["step"] == 3 and row["seq"] == 3
    assert row["ground_accel"] == -1.5 and row["lateness"] == 1e-4
    assert row["of_kind"] == 7
    for ch in chans:
        sfx_name = ch.name if len(chans) > 1 else ""
        for col in channel_columns():
            assert row[column_name(col.name, sfx_name)] == getattr(ch, col.name), col.name
    if n_dof > 1:
        assert row["skew"] == 2e-5
        np.testing.assert_array_equal([row[f"u_{i + 1}"] for i in range(n_dof)], dofs)
    assert "ch0.target" in write.source and "of_kind" not in write.source


def test_a_stage_column_that_is_no_attribute_name_is_refused(tmp_path):
    from rths_hil.errors import InputError

    stage = SimpleNamespace(n_dof=1, record_columns=(("bad", "kind; x", "<i8", "-", "d"),))
    cols = [*specs([""], 1), ("bad", "<i8", "-", "d")]
    with Recorder(tmp_path / "r", 1024.0, columns=cols) as rec:
        with pytest.raises(InputError, match="not an attribute name"):
            row_writer(rec, [SimpleNamespace(name="")], stage)

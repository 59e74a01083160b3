"""An output directory where no file can be written is named for what it is, not as a disk
with "0 B free" (the record's size check saw a virtual file system)."""

from __future__ import annotations

import os

import pytest

from rths_hil.errors import InputError
from rths_hil.resources import check_disk
from tests.helpers.cli import one_line_exit_2


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="no /proc on this system")
def test_an_output_dir_under_proc(capsys):
    one_line_exit_2(
        ["run", "--lockstep", "--duration", "0.1", "--set", "output.dir=/proc/rths-x"], capsys,
        "cannot be written under /proc: a virtual file system with no room for files",
    )  # fmt: skip
    assert not os.path.exists("/proc/rths-x")


def test_a_real_directory_passes_and_a_huge_record_is_refused(tmp_path):
    check_disk(1024, tmp_path / "new" / "run", "a record")  # a missing leaf: its parent counts
    with pytest.raises(InputError, match=r"a record needs .* of disk; .* free: shorten it"):
        check_disk(1e18, tmp_path, "a record")

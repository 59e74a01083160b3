"""``--out DIR`` of run, tune and commission: one reading (rths_hil.cli.options.out_dir)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from rths_hil.cli.options import out_dir
from rths_hil.errors import InputError
from tests.helpers.cli import one_line_exit_2


def _args(out):
    return argparse.Namespace(out=out, out_pattern="runs/t-{timestamp}")


def test_given_directory_default_pattern_and_refusals(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert out_dir(_args("x/y"), empty=True) == Path("x/y")
    made = out_dir(_args(None), empty=True)
    assert re.fullmatch(r"runs/t-\d{8}-\d{6}", made.as_posix())
    with pytest.raises(InputError, match="--out is empty"):
        out_dir(_args("  "), empty=False)
    full = tmp_path / "full"
    full.mkdir()
    (full / "report.md").write_text("x")
    with pytest.raises(InputError, match="not an empty directory"):
        out_dir(_args(str(full)), empty=True)
    assert out_dir(_args(str(full)), empty=False, pattern="unused") == full  # run: a suffix later


@pytest.mark.parametrize("command", ["tune", "commission"])
def test_an_empty_out_is_refused_in_one_line(command, capsys):
    one_line_exit_2([command, "--out", ""], capsys, "--out is empty")

"""The CLI in this process: the bad-input contract (exit 2 with one line on stderr, never a
traceback) and whole commands whose output a test reads."""

from __future__ import annotations

import contextlib
import io
import logging
import subprocess

from rths_hil.cli import main


def one_line_exit_2(argv: list[str], capsys, *needles: str) -> str:
    """Run ``rths-hil ARGV`` in-process; assert exit 2, one stderr line holding every needle."""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own errors exit from the parser
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    for needle in needles:
        assert needle in err, err
    return err


def run_cli(argv: list[str]) -> subprocess.CompletedProcess:
    """``rths-hil ARGV`` in this process, its exit code, stdout and stderr as a terminal shows
    them: what it prints, and its log records of WARNING and above in the command's own format
    (``logging.basicConfig`` of :func:`rths_hil.cli.main` does nothing under pytest, whose
    handlers the root logger already has). A separate process would import the package again
    (~3 s here) for the same code; tests that signal or kill the command keep one."""
    out, err = io.StringIO(), io.StringIO()
    handler = logging.StreamHandler(err)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse's own errors exit from the parser
                code = exc.code
    finally:
        root.removeHandler(handler)
    return subprocess.CompletedProcess(["rths-hil", *argv], code, out.getvalue(), err.getvalue())

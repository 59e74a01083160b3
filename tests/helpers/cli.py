"""The CLI's bad-input contract: exit 2 with one line on stderr, never a traceback."""

from __future__ import annotations

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

"""The ``rths-hil`` console script and ``python -m rths_hil``: Ctrl-C deferred from the start.

A Ctrl-C while the command line and its sub-command are imported (a few tenths of a second, a
second on a loaded machine) would raise ``KeyboardInterrupt`` inside an import: a traceback,
and an interpreter left half set up. :func:`entry` defers the signal from its first line, before
anything of the command line is imported, and ends such a start with the operator-stop code
(130) and one line. Only Python's own start-up before this module (tens of milliseconds) is
left to the interpreter.

This module imports nothing of ``rths_hil`` at import time, so that it loads in microseconds.
"""

from __future__ import annotations

import signal
import sys

#: SIGINTs received while the command line was imported
_pending: list[int] = []


def _defer(signum: int, frame: object) -> None:
    _pending.append(signum)


def entry() -> None:
    """Import the command line with Ctrl-C deferred, then run it (:func:`rths_hil.cli.entry`)."""
    try:
        old = signal.signal(signal.SIGINT, _defer)
    except ValueError:  # not the main thread: nothing to defer
        old = None
    try:
        from .cli import entry as cli_entry  # the command line's imports
    finally:
        if old is not None:
            # what it was (Python's KeyboardInterrupt, or ignored when started so)
            signal.signal(signal.SIGINT, old)
    if _pending:
        print("rths-hil: interrupted", file=sys.stderr)
        sys.exit(130)
    cli_entry()

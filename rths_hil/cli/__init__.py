"""The ``rths-hil`` command line.

Each sub-command lives in its own module of this package and exposes
``register(subparsers) -> None`` that adds its parser and sets ``func`` (a callable taking the
parsed namespace and returning an exit code). Exit codes: 0 success, 2 bad input
(:class:`~rths_hil.errors.InputError`, argparse errors), 3 safety trip, 130 operator stop.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import re
import signal
import sys
from collections.abc import Sequence
from typing import NoReturn

from .. import __version__
from ..errors import InputError
from ..stopping import command_signals, stop_pending

log = logging.getLogger(__name__)

#: Sub-command modules, in the order they appear in ``rths-hil --help``.
COMMANDS: tuple[str, ...] = (
    "run",
    "evaluate",
    "simulate",
    "study",
    "twin",
    "export",
    "tune",
    "diagnose",
    "watch",
    "commission",
    "check-host",
)


_ROLE = re.compile(r":(?:func|class|mod|meth|data|attr|exc):`~?([^`]+)`")


def plain(text: str) -> str:
    """Help text without reST markup: ``:func:`x``` → ``x``, double and single backticks
    dropped (the docstrings the help is made of are reST; a terminal shows plain text)."""
    return _ROLE.sub(r"\1", text).replace("``", "").replace("`", "")


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line and exit code 2, and whose help is plain
    text (:func:`plain`)."""

    def format_help(self) -> str:
        return plain(super().format_help())

    def format_usage(self) -> str:
        return plain(super().format_usage())

    def error(self, message: str) -> NoReturn:  # pragma: no cover - exercised via CLI tests
        if message.endswith("expected one argument"):
            # "--window -3s": argparse takes a value starting with "-" for an option
            message += " (a value starting with '-' is written as --option=-value)"
        self.exit(2, f"{self.prog}: error: {message}\n")


def _command_in(argv: Sequence[str] | None) -> str | None:
    """The sub-command ``argv`` names (its first word that is not an option), if known."""
    words = [a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")]
    return words[0] if words and words[0] in COMMANDS else None


def build_parser(
    argv: Sequence[str] | None = None, *, only: bool = False
) -> argparse.ArgumentParser:
    """Build the top-level parser with every available sub-command.

    With ``only``, just the sub-command ``argv`` names when it names one: each sub-command
    imports what it needs when it registers (``evaluate`` scipy.signal, ``diagnose`` numba
    kernels …), seconds of start-up that ``twin serve`` and the others do not need.
    """
    parser = _Parser(prog="rths-hil", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"rths-hil {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    named = _command_in(argv) if only else None
    for name in (named,) if named else COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name.replace('-', '_')}")
        except ModuleNotFoundError as exc:
            if exc.name == f"{__name__}.{name.replace('-', '_')}":
                continue  # sub-command not built yet
            raise
        module.register(sub)
    return parser


_interrupted = False


def entry() -> None:
    """:func:`main`, then exit (the console script's, after :func:`rths_hil._entry.entry`
    imported this package with Ctrl-C deferred).

    After a Ctrl-C that :func:`main` caught (exit 130, one line), the interpreter may still
    remember the KeyboardInterrupt from code it ran while importing (CPython then ends the
    process by SIGINT, not with 130): the streams are flushed and the process exits 130 at once.
    """
    code = main()
    if _interrupted:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``rths-hil`` console script."""
    # Ctrl-C while the sub-commands are imported and the command line is read (the first second
    # of every command) is deferred: a KeyboardInterrupt inside an import leaves the interpreter
    # half set up and it then dies by the signal. The command then starts under
    # command_signals (Ctrl-C raises and is remembered) and stops with the operator-stop code.
    interrupted: list[int] = []
    try:
        old = signal.signal(signal.SIGINT, lambda *_: interrupted.append(1))
    except ValueError:  # not the main thread
        old = None
    try:
        parser = build_parser(argv, only=True)
        args = None if interrupted else parser.parse_args(argv)
        return _command(parser, args, interrupted)
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)


def _command(
    parser: argparse.ArgumentParser, args: argparse.Namespace | None, interrupted: list[int]
) -> int:
    """Run the parsed command (``args``; None: interrupted while the command line was read)."""
    command = getattr(args, "command", None)
    name = f"rths-hil {command}" if command else "rths-hil"
    try:
        with command_signals():  # replaces main's deferral; a Ctrl-C a library swallows is kept
            if interrupted or args is None:
                print("rths-hil: interrupted", file=sys.stderr)
                return 130
            logging.basicConfig(
                level=logging.WARNING - 10 * min(args.verbose, 2),
                format="%(levelname)s %(name)s: %(message)s",
            )
            if not getattr(args, "func", None):
                parser.print_help()
                return 2
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return _interrupted_exit(name)
    except Exception as exc:
        if stop_pending():  # the Ctrl-C, surfaced as another exception (an import's)
            log.debug("interrupted: %r", exc)
            return _interrupted_exit(name)
        if isinstance(exc, InputError):
            print(f"{name}: error: {exc}", file=sys.stderr)
            return 2
        if isinstance(exc, OSError) and exc.filename is not None:
            # a file-system error on a path the command was given (name too long, read-only,
            # disk full, not a directory …) is bad input: one line, not a traceback
            print(f"{name}: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
            return 2
        raise


def _interrupted_exit(name: str) -> int:
    """The operator stopped the command (Ctrl-C): one line, the operator-stop code."""
    global _interrupted
    _interrupted = True
    print(f"{name}: interrupted", file=sys.stderr)
    return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

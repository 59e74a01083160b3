"""The operator-stop signals: the test loop, ``commission``, ``check-host``, the studies.

``rths-hil run`` ends a test on Ctrl-C, SIGTERM or SIGHUP (every signal of
:data:`rths_hil.hybrid.runner.STOP_SIGNALS`) by its operator-stop path: the loop sees a flag at
its next step, holds, disables and hands the controllers back, and the command exits 130. The
loop and the other commands that drive a controller or run for long take that path through
:class:`OperatorStop`: the first signal sets :attr:`OperatorStop.signal` (the command finishes
the step it is in safely and keeps what it has done), a second one raises
:class:`KeyboardInterrupt` at once (the command's own error path: e-stop, exit 130).

Before a command enters one of those, Ctrl-C raises :class:`KeyboardInterrupt` as Python's own
handler does, and :func:`command_signals` also remembers it: a library that swallows the
exception (a ``ctypes`` callback — numba's compiled-code cache has one — reports it as
"Exception ignored" and goes on) does not lose the operator's stop. The next
:class:`OperatorStop` starts with that signal received (a test stops before it arms a controller),
the next :func:`interrupting` raises it again.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from types import FrameType, TracebackType
from typing import Any

__all__ = ["OperatorStop", "Stopped", "command_signals", "interrupting", "stop_pending"]

#: stop signals of the command so far that no :class:`OperatorStop` has taken yet (names)
_early: list[str] = []


def stop_pending() -> bool:
    """True when a stop signal of the command (:func:`command_signals`) was not taken by an
    :class:`OperatorStop`: the exception that ended the command was the operator's stop, as
    whatever it surfaced as (a ``KeyboardInterrupt`` raised inside an import or a class's
    ``__set_name__`` comes out as ``ImportError`` or ``RuntimeError``)."""
    return bool(_early)


def _take_early() -> str | None:
    """The first stop signal :func:`command_signals` remembered, forgotten as it is taken."""
    name = _early[0] if _early else None
    _early.clear()
    return name


@contextlib.contextmanager
def command_signals() -> Iterator[None]:
    """Ctrl-C raises :class:`KeyboardInterrupt` and is remembered, for one command (main
    thread only; elsewhere it changes nothing).

    A ``KeyboardInterrupt`` that ends in :data:`sys.unraisablehook` (raised in a callback from
    C, where nothing can catch it) is not printed: the signal is remembered, and the command
    stops by it at its next :class:`OperatorStop` or :func:`interrupting`. What is remembered is
    forgotten when the next command starts (:func:`stop_pending` reads it after this one).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        _early.append(signal.Signals(signum).name)
        raise KeyboardInterrupt

    def unraisable(args: Any) -> None:
        if not (isinstance(args.exc_type, type) and issubclass(args.exc_type, KeyboardInterrupt)):
            hook(args)

    _early.clear()
    old, hook = signal.getsignal(signal.SIGINT), sys.unraisablehook
    try:
        signal.signal(signal.SIGINT, handler)
        sys.unraisablehook = unraisable
        yield
    finally:
        sys.unraisablehook = hook
        if old is not None:  # (None: a handler not installed from Python, left as it is)
            signal.signal(signal.SIGINT, old)


class Stopped(Exception):
    """Raised by :meth:`OperatorStop.check` once a stop signal came (the signal's name)."""


class OperatorStop:
    """A context that catches the stop signals for the block it guards (main thread only).

    Examples
    --------
    >>> with OperatorStop() as stop:
    ...     stop.signal is None
    True
    """

    def __init__(self) -> None:
        #: name of the first stop signal received (``"SIGINT"``, ``"SIGTERM"`` …) or None
        self.signal: str | None = None
        self._old: list[tuple[int, object]] = []

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        if self.signal is not None:  # the second one: give up at once
            raise KeyboardInterrupt
        self.signal = signal.Signals(signum).name

    def __enter__(self) -> OperatorStop:
        from .hybrid.runner import STOP_SIGNALS

        # a Ctrl-C of the command's start-up that a library swallowed (command_signals)
        self.signal = self.signal or _take_early()
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                self._old.append((sig, signal.signal(sig, self._handler)))
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        while self._old:
            sig, old = self._old.pop()
            signal.signal(sig, old)  # type: ignore[arg-type]

    @property
    def stopped(self) -> bool:
        """True once a stop signal came."""
        return self.signal is not None

    def check(self) -> None:
        """Raise :class:`Stopped` when a stop signal came."""
        if self.signal is not None:
            raise Stopped(self.signal)


@contextlib.contextmanager
def interrupting() -> Iterator[list[str]]:
    """Every stop signal raises :class:`KeyboardInterrupt`, as Ctrl-C does (main thread only);
    yields a list that receives the signal's name."""
    from .hybrid.runner import STOP_SIGNALS

    got: list[str] = []

    def handler(signum: int, frame: FrameType | None) -> None:
        got.append(signal.Signals(signum).name)
        raise KeyboardInterrupt

    early = _take_early()  # a Ctrl-C of the command's start-up that a library swallowed
    if early is not None:
        got.append(early)
        raise KeyboardInterrupt
    old = []
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            old.append((sig, signal.signal(sig, handler)))
    try:
        yield got
    finally:
        for sig, h in reversed(old):
            signal.signal(sig, h)

"""The operator-stop signals: the test loop, ``commission``, ``check-host``, the studies.

``rths-hil run`` ends a test on Ctrl-C, SIGTERM or SIGHUP (every signal of
:data:`rths_hil.hybrid.runner.STOP_SIGNALS`) by its operator-stop path: the loop sees a flag at
its next step, holds, disables and hands the controllers back, and the command exits 130. The
loop and the other commands that drive a controller or run for long take that path through
:class:`OperatorStop`: the first signal sets :attr:`OperatorStop.signal` (the command finishes
the step it is in safely and keeps what it has done), a second one raises
:class:`KeyboardInterrupt` at once (the command's own error path: e-stop, exit 130).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType, TracebackType

__all__ = ["OperatorStop", "Stopped", "interrupting"]


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

    old = []
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            old.append((sig, signal.signal(sig, handler)))
    try:
        yield got
    finally:
        for sig, h in reversed(old):
            signal.signal(sig, h)

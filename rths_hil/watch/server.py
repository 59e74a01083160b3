"""The Bokeh server behind ``rths-hil watch``.

Bokeh's server serves the page, its own JavaScript and styles from the installed wheel
(``/static/…`` on the same host and port: no CDN, works air-gapped) and keeps one Bokeh document
per browser session in sync over a WebSocket. The server binds 127.0.0.1 unless told otherwise;
on any other address every page needs a random token in its URL (``?token=…``), sessions are
signed with a random secret so that a WebSocket cannot be opened without a page served with the
token, and a warning is printed.
"""

from __future__ import annotations

import errno
import logging
import secrets
import signal
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError
from .app import WatchContext, build_document
from .source import RunFollower

if TYPE_CHECKING:
    from bokeh.server.server import Server

__all__ = ["LOCAL_HOSTS", "WatchServer"]

log = logging.getLogger(__name__)

#: Addresses that need no token (the loopback interface).
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


class WatchServer:
    """A Bokeh server following one run directory.

    Parameters
    ----------
    run_dir : str or Path
        The run to follow (it may not exist yet).
    host : str
        Address to bind (default 127.0.0.1; anything else requires a token in the URL).
    port : int
        TCP port (0: any free port; see :attr:`port` after :meth:`start`).
    allow_stop : bool
        Offer the operator-stop button.
    notify : callable, optional
        Receives one-line messages for the terminal.
    """

    def __init__(
        self,
        run_dir: str | Path,
        host: str = "127.0.0.1",
        port: int = 8050,
        *,
        allow_stop: bool = True,
        notify: Callable[[str], None] | None = None,
    ) -> None:
        if not (0 <= int(port) <= 65535):
            raise InputError(f"--port must be in 0..65535, got {port}")
        self.run_dir = Path(run_dir)
        self.host = host
        self.port = int(port)
        self.token = None if host in LOCAL_HOSTS else secrets.token_urlsafe(24)
        self.follower = RunFollower(self.run_dir)
        self.ctx = WatchContext(self.follower, self.token, allow_stop, notify)
        self._server: Server | None = None

    @property
    def url(self) -> str:
        """The page's address (with the token when one is required)."""
        host = self.host
        if host in ("0.0.0.0", "::", ""):
            import socket

            host = socket.gethostname()
        if ":" in host:
            host = f"[{host}]"
        base = f"http://{host}:{self.port}/"
        return base + (f"?token={self.token}" if self.token else "")

    def start(self) -> None:
        """Bind and start serving (the Tornado IO loop is started by :meth:`run_forever`)."""
        from bokeh.application import Application
        from bokeh.application.handlers.function import FunctionHandler
        from bokeh.server.server import Server

        app = Application(FunctionHandler(build_document(self.ctx)))
        if self.port == 0:
            self.port = _free_port(self.host)
        kw: dict = {}
        if self.token is not None:
            wildcard = self.host in ("0.0.0.0", "::", "")
            if wildcard:  # the page may be opened by any of the machine's names or addresses
                logging.getLogger("bokeh.server.util").setLevel(logging.ERROR)
            kw.update(
                sign_sessions=True,
                secret_key=secrets.token_bytes(32),
                generate_session_ids=True,
                allow_websocket_origin=["*"] if wildcard else [f"{self.host}:{self.port}"],
            )
        else:
            kw.update(
                allow_websocket_origin=[f"{h}:{self.port}" for h in ("127.0.0.1", "localhost")]
            )
        try:
            server = Server(
                {"/": app},
                address=self.host,
                port=self.port,
                num_procs=1,
                keep_alive_milliseconds=10_000,
                **kw,
            )
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InputError(
                    f"port {self.port} on {self.host} is in use: choose another with --port"
                ) from None
            raise InputError(f"cannot listen on {self.host}:{self.port}: {exc.strerror}") from None
        self._server = server
        server.start()

    def run_forever(self) -> None:
        """Serve until SIGINT or SIGTERM."""
        from tornado.platform.asyncio import BaseAsyncIOLoop

        assert self._server is not None, "start() first"
        loop = self._server.io_loop
        assert isinstance(loop, BaseAsyncIOLoop)  # tornado ≥ 5: every IOLoop runs on asyncio
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.asyncio_loop.add_signal_handler(sig, loop.stop)
        try:
            loop.start()
        finally:
            self.stop()

    def stop(self) -> None:
        """Stop serving (idempotent)."""
        if self._server is not None:
            try:
                self._server.stop()
            except Exception:  # pragma: no cover - already stopped
                log.debug("server stop", exc_info=True)
            self._server = None


def _free_port(host: str) -> int:
    """A TCP port that is free on ``host`` now."""
    import socket

    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, 0))
        except OSError as exc:
            raise InputError(f"cannot listen on {host}: {exc.strerror}") from None
        return int(s.getsockname()[1])

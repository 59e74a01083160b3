"""Headless Chromium driven over the DevTools protocol (for tests, screenshots, benchmarks).

Starts the system's Chromium (Debian ``chromium``; ``$CHROMIUM`` overrides the path) with a
private profile and ``--remote-debugging-port=0``, reads the port it chose from the profile's
``DevToolsActivePort`` file and talks to the page target over a WebSocket (Tornado's client, a
dependency of Bokeh). Every request the page makes is kept (:attr:`Browser.requests`), so a
test can check that nothing but the watcher itself was asked for (no CDN).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tornado.websocket import WebSocketClientConnection

__all__ = ["Browser", "chromium_path"]


def chromium_path() -> str | None:
    """The Chromium executable (``$CHROMIUM``, else ``chromium`` or ``chromium-browser``)."""
    env = os.environ.get("CHROMIUM")
    if env:
        return env
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the browser gets SIGTERM when the process that started it dies (no orphans)."""
    with contextlib.suppress(Exception):
        import ctypes
        import signal

        ctypes.CDLL(None).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG


_FIND_BUTTON = """
(() => {
  const want = %s;
  const stack = [document];
  while (stack.length) {
    const node = stack.pop();
    for (const el of node.querySelectorAll('*')) {
      if (el.shadowRoot) stack.push(el.shadowRoot);
      if (el.tagName === 'BUTTON' && el.textContent.trim() === want) {
        const r = el.getBoundingClientRect();
        if (r.width > 0 && r.height > 0) return [r.x + r.width / 2, r.y + r.height / 2];
      }
    }
  }
  return null;
})()
"""


class Browser:
    """One headless Chromium with one page.

    Parameters
    ----------
    width, height : int
        Viewport in CSS pixels.
    offline : bool
        Resolve every host name except ``localhost``/``127.0.0.1`` to nothing (an air-gapped
        lab): a page that needs the internet visibly fails.
    """

    def __init__(self, width: int = 1200, height: int = 2600, offline: bool = True) -> None:
        exe = chromium_path()
        if exe is None:
            raise FileNotFoundError("no Chromium found (apt-get install chromium)")
        self.profile = tempfile.mkdtemp(prefix="rths-watch-chromium-")
        args = [
            exe,
            "--headless=new",
            "--remote-debugging-port=0",
            f"--user-data-dir={self.profile}",
            "--no-first-run",
            "--no-default-browser-check",
            "--disable-gpu",
            "--disable-extensions",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--mute-audio",
            f"--window-size={width},{height}",
        ]
        if os.geteuid() == 0:
            args.append("--no-sandbox")
        if offline:
            args.append("--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.*")
        args.append("about:blank")
        self.proc = subprocess.Popen(
            args,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=_die_with_parent,
        )
        self.loop = asyncio.new_event_loop()
        self.requests: list[str] = []
        self.events: list[dict] = []
        self._id = 0
        self.ws: WebSocketClientConnection | None = None
        try:
            port = self._port()
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                targets = json.loads(r.read())
            page = next(t for t in targets if t.get("type") == "page")
            from tornado.websocket import websocket_connect

            async def connect():
                return await websocket_connect(
                    page["webSocketDebuggerUrl"], max_message_size=256 * 2**20
                )

            self.ws = self.loop.run_until_complete(connect())
            self.call("Page.enable")
            self.call("Network.enable")
            self.call("Runtime.enable")
            self.call(
                "Emulation.setDeviceMetricsOverride",
                width=width,
                height=height,
                deviceScaleFactor=1,
                mobile=False,
            )
        except BaseException:
            self.close()
            raise

    def _port(self, timeout: float = 30.0) -> int:
        f = Path(self.profile) / "DevToolsActivePort"
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"chromium exited with code {self.proc.returncode}")
            with contextlib.suppress(OSError, ValueError, IndexError):
                return int(f.read_text().split()[0])
            time.sleep(0.05)
        raise TimeoutError("chromium did not open its DevTools port")

    # -- protocol ----------------------------------------------------------------------------------
    async def _call(self, method: str, params: dict, timeout: float) -> dict:
        ws = self.ws
        if ws is None:
            raise ConnectionError("DevTools connection closed")
        self._id += 1
        my = self._id
        await ws.write_message(json.dumps({"id": my, "method": method, "params": params}))
        t_end = time.monotonic() + timeout
        while True:
            left = t_end - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"DevTools: no answer to {method}")
            msg = await asyncio.wait_for(ws.read_message(), left)
            if msg is None:
                raise ConnectionError("DevTools connection closed")
            data = json.loads(msg)
            if data.get("id") == my:
                if "error" in data:
                    raise RuntimeError(f"DevTools {method}: {data['error']}")
                return data.get("result", {})
            self._event(data)

    def _event(self, data: dict) -> None:
        method = data.get("method", "")
        if method == "Network.requestWillBeSent":
            self.requests.append(data["params"]["request"]["url"])
        elif method == "Network.webSocketCreated":
            self.requests.append(data["params"]["url"])
        elif method:
            self.events.append(data)

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        """Send one DevTools command and return its result."""
        return self.loop.run_until_complete(self._call(method, params, timeout))

    def eval(self, expression: str, timeout: float = 30.0):
        """Evaluate JavaScript in the page and return its (JSON) value."""
        res = self.call(
            "Runtime.evaluate",
            timeout=timeout,
            expression=expression,
            returnByValue=True,
            awaitPromise=True,
        )
        if "exceptionDetails" in res:
            raise RuntimeError(f"page script failed: {res['exceptionDetails'].get('text')}")
        return res.get("result", {}).get("value")

    # -- page ------------------------------------------------------------------------------------
    def goto(self, url: str) -> None:
        """Open ``url`` (ConnectionError when the page cannot be loaded)."""
        res = self.call("Page.navigate", url=url)
        if res.get("errorText"):
            raise ConnectionError(f"{url}: {res['errorText']}")

    def wait_for(self, expression: str, timeout: float = 30.0, poll: float = 0.1):
        """Wait until ``expression`` is truthy in the page; return its value."""
        t_end = time.monotonic() + timeout
        last_err = None
        while time.monotonic() < t_end:
            try:
                v = self.eval(expression)
            except RuntimeError as exc:
                v, last_err = None, exc
            if v:
                return v
            time.sleep(poll)
        raise TimeoutError(f"page never satisfied {expression!r} ({last_err})")

    def model(self, name: str, attr: str):
        """An attribute of the Bokeh model called ``name`` in the page's document."""
        return self.eval(
            "(() => { const d = window.Bokeh && Bokeh.documents[0];"
            f" const m = d && d.get_model_by_name({json.dumps(name)});"
            f" if (!m) return null; const v = m[{json.dumps(attr)}];"
            " return (v && v.length !== undefined && typeof v !== 'string')"
            " ? Array.from(v) : v; })()"
        )

    def column(self, source: str, col: str) -> list:
        """A column of the Bokeh ColumnDataSource called ``source``."""
        return self.eval(
            "(() => { const d = window.Bokeh && Bokeh.documents[0];"
            f" const m = d && d.get_model_by_name({json.dumps(source)});"
            " if (!m) return null;"
            f" const c = m.data.get ? m.data.get({json.dumps(col)}) : m.data[{json.dumps(col)}];"
            " return c ? Array.from(c) : null; })()"
        )

    def click_button(self, label: str, timeout: float = 10.0) -> None:
        """Click the visible button labelled ``label`` with real mouse events."""
        xy = self.wait_for(_FIND_BUTTON % json.dumps(label), timeout=timeout)
        x, y = xy
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.call(
                "Input.dispatchMouseEvent",
                type=kind,
                x=x,
                y=y,
                button="left" if kind != "mouseMoved" else "none",
                clickCount=1 if kind != "mouseMoved" else 0,
            )

    def screenshot(self, path: str | Path | None = None) -> bytes:
        """A PNG of the viewport (also written to ``path``)."""
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            Path(path).write_bytes(data)
        return data

    def close(self) -> None:
        """Close the page and end Chromium (idempotent)."""
        if self.ws is not None:
            with contextlib.suppress(Exception):
                self.ws.close()
            self.ws = None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        with contextlib.suppress(Exception):
            self.loop.close()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""A scripted OpenFresco client (no OpenSees) against the bridge's experimental site."""

from __future__ import annotations

import contextlib
import socket
import threading

import numpy as np

import tests.helpers.opensees_site as S
from rths_hil.config import load_config
from rths_hil.hybrid import RTHSLoop
from rths_hil.openfresco import protocol as P

GENERIC_CLIENT_ID = (2, 2, 2, 0, 1, 0, 0, 0, 2, 0, 256)  # what OpenSeesPy 3.7 sends for nb = 2


def _loop(tmp_path, name, *overrides, config=S.SITE):
    cfg = load_config(
        config,
        [
            "openfresco.port=0",
            "openfresco.start_timeout=20s",
            "openfresco.client_timeout=20s",
            "output.plot=false",
            *overrides,
        ],
    )
    loop = RTHSLoop(cfg, tmp_path / name)
    _, port = loop.structure.listen()
    return loop, port


def _client(port, ident, script):
    """Connect, send the ID, then run ``script(sock)`` in a thread."""

    def run():
        s = socket.create_connection(("127.0.0.1", port), timeout=20)
        with contextlib.closing(s):
            s.sendall(np.asarray(ident, dtype=P.ID_DTYPE).tobytes())
            script(s)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def _frame(size, *values):
    out = np.zeros(size, dtype=P.FRAME_DTYPE)
    out[: len(values)] = values
    return out.tobytes()


def _recv(s, size):
    buf = b""
    while len(buf) < 8 * size:
        chunk = s.recv(8 * size - len(buf))
        assert chunk
        buf += chunk
    return np.frombuffer(buf, dtype=P.FRAME_DTYPE)

"""``--scheduler`` addresses that cannot be a Dask scheduler are one line, exit 2: an address
without its port, and a port where something else listens and never answers distributed's
handshake (which ``Client(timeout=...)`` does not bound: it waited for ever)."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from rths_hil.cli import main
from rths_hil.studies import executors

NEES = ["study", "robustness", "examples/nees711/nees711.toml", "--trials", "2"]


def error_exit_2(argv: list[str], capsys, needle: str) -> None:
    """Exit 2; the study's plan line, then one error line holding ``needle``; no traceback."""
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert "Traceback" not in "\n".join(err)
    assert err[-1].startswith("rths-hil study: error: ") and needle in err[-1], err
    assert len(err) <= 2, err


@pytest.mark.parametrize("address", ["127.0.0.1", "tcp://127.0.0.1", "localhost"])
def test_an_address_without_its_port(tmp_path, capsys, address):
    error_exit_2([*NEES, "--scheduler", address, "--out", str(tmp_path / "o")], capsys,
                 "expected 'local' or a scheduler address with its port")  # fmt: skip


@pytest.fixture()
def silent_listener():
    """A TCP port on 127.0.0.1 that accepts connections and never says anything."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(srv.accept()[0])
            except TimeoutError:
                continue
            except OSError:
                return

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    yield srv.getsockname()[1]
    stop.set()
    t.join(2)
    for c in held:
        c.close()
    srv.close()


# a 1 s handshake bound within 30 s: runs with the parallel tests
def test_a_port_where_no_scheduler_answers(tmp_path, capsys, monkeypatch, silent_listener):
    pytest.importorskip("distributed")
    monkeypatch.setattr(executors, "HANDSHAKE_TIMEOUT", 1.0)
    t0 = time.monotonic()
    error_exit_2(
        [*NEES, "--scheduler", f"tcp://127.0.0.1:{silent_listener}", "--out",
         str(tmp_path / "o")], capsys,
        f"no Dask scheduler answered at tcp://127.0.0.1:{silent_listener} within 1 s",
    )  # fmt: skip
    assert time.monotonic() - t0 < 30

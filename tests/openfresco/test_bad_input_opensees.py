"""The OpenSees site under a hostile raw client.

Each client is a raw socket speaking the genericClient protocol (as in test_openfresco.py):
no ID, NaN/Inf action codes, absurd trial times, trials with uneven time steps, a slow
OpenSees step and SIGTERM while the site waits.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time

import numpy as np
import pytest

from rths_hil.errors import InputError
from rths_hil.openfresco import protocol as P
from rths_hil.records.recorder import read_run
from tests.helpers.openfresco import GENERIC_CLIENT_ID, _client, _frame, _loop, _recv

# The refusals run the site in lockstep, in this process, with no figure of the wall clock
# beyond loose bounds (the 5 s ID wait under 15 s, a trip within 10 s): they run with the
# parallel tests. The slow OpenSees step against the 1 s watchdog and SIGTERM to this process
# run apart from them, one at a time (the "timing" marker, pyproject.toml; make test).
timing = pytest.mark.timing


def test_client_that_connects_and_sends_no_id(tmp_path):
    loop, port = _loop(tmp_path, "noid")
    s = socket.create_connection(("127.0.0.1", port))
    try:
        t0 = time.monotonic()
        with pytest.raises(InputError) as exc:
            loop.run()
        assert time.monotonic() - t0 < 15
    finally:
        s.close()
    msg = str(exc.value)
    assert "sent no ID within 5 s" in msg and "\n" not in msg


@pytest.mark.parametrize("code", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_action_code_trips_in_one_line(tmp_path, code):
    def script(s):
        s.sendall(_frame(256, code))
        time.sleep(2.0)

    loop, port = _loop(tmp_path, "code")
    _client(port, GENERIC_CLIENT_ID, script)
    result = loop.run()
    assert result.status == "trip" and result.exit_code == 3
    assert result.trip.rule == "openfresco"
    assert f"unknown action code {code!r}" in result.trip.reason
    assert "\n" not in result.trip.reason and "Error" not in result.trip.reason


@pytest.mark.parametrize("t_trial", [1e12, float("inf"), float("nan")])
def test_absurd_trial_time_is_refused(tmp_path, t_trial):
    def script(s):
        s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001, 0, 0, 0, 0, t_trial))
        s.sendall(_frame(256, P.GET_FORCE))
        time.sleep(3.0)

    loop, port = _loop(tmp_path, "ttime")
    _client(port, GENERIC_CLIENT_ID, script)
    t0 = time.monotonic()
    result = loop.run()
    assert time.monotonic() - t0 < 10  # no unbounded ramp
    assert result.status == "trip" and result.trip.rule == "openfresco"
    assert f"trial time {t_trial!r} s" in result.trip.reason
    rec = read_run(tmp_path / "ttime").record
    assert np.abs(rec["command"]).max() == 0.0  # the actuator never moved toward it


def test_trial_time_step_over_a_minute_is_refused(tmp_path):
    def script(s):
        s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001, 0, 0, 0, 0, 1 / 256))
        s.sendall(_frame(256, P.GET_FORCE))
        _recv(s, 256)
        s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001, 0, 0, 0, 0, 1e5))
        s.sendall(_frame(256, P.GET_FORCE))
        time.sleep(3.0)

    loop, port = _loop(tmp_path, "tstep")
    _client(port, GENERIC_CLIENT_ID, script)
    result = loop.run()
    assert result.status == "trip" and result.trip.rule == "openfresco"
    assert "a time step over 60 s" in result.trip.reason


def test_command_path_stays_within_the_trials_envelope(tmp_path):
    """Trials within ±1 mm at alternating long (0.3 s) and short (3 ms) time steps: the
    three-point slope over the short step, used over the long one, made the cubic Hermite
    overshoot to 13 mm; with monotone (Fritsch–Carlson) slopes it stays within ±1 mm."""
    ds = [-0.001, -0.0005, 0.0005, 0.001]
    sent = []

    def script(s):
        t = 0.0
        for i in range(40):
            t += 0.3 if i % 2 == 0 else 3 / 1024
            sent.append(ds[i % 4])
            s.sendall(_frame(256, P.SET_TRIAL, 0.0, ds[i % 4], 0, 0, 0, 0, t))
            s.sendall(_frame(256, P.GET_FORCE))
            _recv(s, 256)
            s.sendall(_frame(256, P.COMMIT))
        s.sendall(_frame(256, P.DIE))

    loop, port = _loop(tmp_path, "envelope")
    th = _client(port, GENERIC_CLIENT_ID, script)
    result = loop.run()
    th.join(5)
    assert result.status == "completed", result.trip
    rec = read_run(tmp_path / "envelope").record
    assert len(sent) == 40
    assert np.abs(rec["target"]).max() <= 0.001 + 1e-12
    assert np.abs(rec["command"]).max() <= 0.001 + 1e-12
    # every trial is still reached exactly (the path passes through the targets)
    for d in ds:
        assert np.isclose(rec["target"], d, atol=1e-12).any()


def test_hermite_segments_between_two_trials_stay_between_them():
    """Unit check of the slope limiter on random slopes: the segment never leaves [c0, d]."""
    from rths_hil.openfresco.timing import _monotone_slopes

    rng = np.random.default_rng(0)
    s = np.linspace(0.0, 1.0, 201)[:, None]
    for _ in range(500):
        c0, d = rng.normal(size=3), rng.normal(size=3)
        span = rng.uniform(1e-3, 1.0)
        v0, v1 = _monotone_slopes(c0, d, span, rng.normal(size=3) * 50, rng.normal(size=3) * 50)
        h00 = (1 + 2 * s) * (1 - s) ** 2
        h10 = s * (1 - s) ** 2
        h01 = s * s * (3 - 2 * s)
        h11 = s * s * (s - 1)
        p = h00 * c0 + h10 * span * v0 + h01 * d + h11 * span * v1
        tol = 1e-12 * (1 + np.abs(c0) + np.abs(d))
        assert np.all(p >= np.minimum(c0, d) - tol) and np.all(p <= np.maximum(c0, d) + tol)


@timing
def test_slow_opensees_step_holds_instead_of_tripping_the_watchdog(tmp_path):
    """An OpenSees step of 2.5 s with a 1 s lockstep watchdog and client_timeout 20 s: the
    site holds the actuator (heartbeats) and the run completes."""

    def script(s):
        for i in range(1, 4):
            s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001 * i, 0, 0, 0, 0, i / 256))
            s.sendall(_frame(256, P.GET_FORCE))
            _recv(s, 256)
            s.sendall(_frame(256, P.COMMIT))
            if i == 2:
                time.sleep(2.5)
        s.sendall(_frame(256, P.DIE))

    loop, port = _loop(tmp_path, "slow", "loop.lockstep_timeout=1s")
    th = _client(port, GENERIC_CLIENT_ID, script)
    result = loop.run()
    th.join(5)
    assert result.status == "completed", result.trip
    rec = read_run(tmp_path / "slow").record
    assert rec["target"].max() == pytest.approx(0.003)


@timing
def test_sigterm_while_the_site_waits_for_opensees(tmp_path):
    def script(s):
        s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001, 0, 0, 0, 0, 1 / 256))
        s.sendall(_frame(256, P.GET_FORCE))
        _recv(s, 256)
        s.sendall(_frame(256, P.COMMIT))
        time.sleep(15.0)  # OpenSees busy

    loop, port = _loop(tmp_path, "term")
    _client(port, GENERIC_CLIENT_ID, script)
    timer = threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGTERM))
    timer.start()
    t0 = time.monotonic()
    try:
        result = loop.run()
    finally:
        timer.cancel()
    assert time.monotonic() - t0 < 5  # not the 15 s of the client's wait
    assert result.status == "operator_stop" and result.exit_code == 130
    events = read_run(tmp_path / "term").events
    # the operator-stop path of every signal (its e-stop or hand-back is the runner's business)
    assert any(e["kind"] == "operator_stop" and e["signal"] == "SIGTERM" for e in events)
    assert events[-1]["kind"] == "end" and events[-1]["status"] == "operator_stop"

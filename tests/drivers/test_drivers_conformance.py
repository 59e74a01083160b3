"""One conformance suite for every driver, against its twin over a real transport.

Transports: the python-can virtual bus (and SocketCAN vcan0 where the host has it), python-can's
``serial`` and ``slcan`` interfaces over the CAN twin's null-modem pair of pseudo-terminals,
Modbus TCP on 127.0.0.1 and Modbus RTU over an os.openpty pseudo-terminal pair, the COBS/CRC serial
protocol over an os.openpty pair and over a TCP socket (pyserial socket://).

The expected feedback is computed independently of the twin's streaming code: the offline
Lagrange fractional delay (``fractional_delay``, a 4-tap FIR) of the command as quantised by
the bus, times the gain, and a linear spring for the force; the bus's fixed-point resolution is
the tolerance.
"""

from __future__ import annotations

import math
import socket
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from rths_hil.drivers.base import Status
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.delay import fractional_delay
from rths_hil.sim_backends.faults import Faults
from rths_hil.sim_backends.plant import TwinPlant
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.errors import InputError

# Lockstep exchanges with generous waits (TIMEOUT): they run with the parallel tests. The tests
# whose result depends on how soon a reply comes (a wait of 0.1 s or less, an elapsed time)
# run apart from them, one at a time (the "timing" marker, pyproject.toml; make test).

DT = 1.0 / 1024.0
DELAY, GAIN, STIFFNESS = 0.0033, 0.9, 2.0e5
TIMEOUT = 0.5  # generous: the CI machine is shared


def _socketcan_reason() -> str | None:
    if not hasattr(socket, "AF_CAN"):
        return "socket.AF_CAN missing on this platform"
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return f"SocketCAN unsupported here (AF_CAN socket: {exc})"
    try:
        s.bind(("vcan0",))
    except OSError as exc:
        return f"no vcan0 interface ({exc}); create it with 'ip link add vcan0 type vcan'"
    finally:
        s.close()
    return None


@dataclass
class Transport:
    id: str
    driver: str
    twin_kwargs: dict[str, Any] = field(default_factory=dict)
    cmd_lsb: float | None = 1e-7
    disp_lsb: float | None = 1e-7
    force_lsb: float | None = 0.01
    corrupt_reason: str = "bad_crc"
    skip: str | None = None


TRANSPORTS = [
    Transport("can-virtual", "can", {"interface": "virtual"}, force_lsb=0.5,
              corrupt_reason="bad_length"),
    Transport("can-socketcan", "can", {"interface": "socketcan", "channel": "vcan0"},
              force_lsb=0.5, corrupt_reason="bad_length", skip=_socketcan_reason()),
    Transport("can-serial-pty", "can", {"interface": "serial"}, force_lsb=0.5,
              corrupt_reason="bad_length"),
    Transport("can-slcan-pty", "can", {"interface": "slcan"}, force_lsb=0.5,
              corrupt_reason="bad_length"),
    Transport("modbus-tcp", "modbus", {"transport": "tcp"}),
    Transport("modbus-rtu", "modbus", {"transport": "rtu"}),
    Transport("serial-pty", "serial", {"transport": "pty"}, None, None, None),
    Transport("serial-tcp", "serial", {"transport": "tcp"}, None, None, None),
]  # fmt: skip


@pytest.fixture(params=TRANSPORTS, ids=[t.id for t in TRANSPORTS])
def transport(request: pytest.FixtureRequest) -> Transport:
    t: Transport = request.param
    if t.skip:
        pytest.skip(t.skip)
    return t


def plant() -> TwinPlant:
    return default_plant(DELAY, GAIN, STIFFNESS, DT)


class Rig:
    """A twin and a driver connected to it."""

    def __init__(self, t: Transport, faults: Faults | None = None, **twin_extra: Any) -> None:
        self.t = t
        self.twin = start_twin(t.driver, plant(), faults=faults, **t.twin_kwargs, **twin_extra)
        try:
            self.driver = create_driver(t.driver, **self.twin.connection)
            self.driver.open()
        except BaseException:
            self.twin.stop()
            raise

    def close(self) -> None:
        self.driver.close()
        self.twin.stop()

    def step(self, seq: int, cmd: float, enable: bool = True, timeout: float = TIMEOUT):
        self.driver.send(seq, cmd, enable)
        return self.driver.receive(timeout)


@pytest.fixture
def rig_factory(transport: Transport):
    rigs: list[Rig] = []

    def make(faults: Faults | None = None, **kw: Any) -> Rig:
        r = Rig(transport, faults, **kw)
        rigs.append(r)
        return r

    yield make
    for r in rigs:
        r.close()


def commands(n: int) -> np.ndarray:
    t = np.arange(n) * DT
    return 0.004 * np.sin(2 * np.pi * 3.0 * t) + 0.001 * np.sin(2 * np.pi * 11.0 * t)


def quantise(x: np.ndarray, lsb: float | None) -> np.ndarray:
    return x if lsb is None else np.round(x / lsb) * lsb


def reference(cmd: np.ndarray, t: Transport) -> tuple[np.ndarray, np.ndarray]:
    """Independent expected (displacement, force) for commands ``cmd`` from rest."""
    x = GAIN * fractional_delay(quantise(cmd, t.cmd_lsb), DELAY, 1.0 / DT)
    return x, STIFFNESS * x


def tol(lsb: float | None) -> float:
    return 1e-9 if lsb is None else 0.5 * lsb + 1e-12


# -- round trip, sequence continuity -----------------------------------------------------------
def test_round_trip_matches_independent_reference(rig_factory, transport: Transport) -> None:
    rig = rig_factory()
    n = 300
    cmd = commands(n)
    fbs = [rig.step(k, float(c)) for k, c in enumerate(cmd)]
    assert all(fb is not None for fb in fbs)
    assert [fb.seq for fb in fbs] == list(range(n))
    disp = np.array([fb.displacement for fb in fbs])
    force = np.array([fb.force for fb in fbs])
    x_ref, f_ref = reference(cmd, transport)
    # The delayed sine really moves: a wrong delay of one sample would exceed the tolerance.
    assert np.max(np.abs(x_ref)) > 3e-3
    np.testing.assert_allclose(disp, x_ref, rtol=0, atol=tol(transport.disp_lsb) + 1e-12)
    f_tol = STIFFNESS * 1e-15 + (tol(transport.force_lsb) if transport.force_lsb else 1e-6)
    np.testing.assert_allclose(force, f_ref, rtol=0, atol=f_tol)
    assert all(fb.status == Status.ENABLED for fb in fbs)
    s = rig.driver.stats
    assert (s.sent, s.received, s.timeouts, s.malformed, s.seq_gaps) == (n, n, 0, 0, 0)
    assert rig.twin.stats.steps == n


def test_sequence_numbers_wrap_the_wire_width(rig_factory) -> None:
    rig = rig_factory()
    start = 65530  # 16-bit wire counters (CAN, Modbus) wrap inside this run
    seqs = list(range(start, start + 20))
    fbs = [rig.step(k, 0.001) for k in seqs]
    assert [fb.seq for fb in fbs] == seqs
    assert rig.twin.stats.steps == 20
    assert rig.driver.stats.seq_gaps == 0


@pytest.mark.timing  # the copy must come within 0.1 s
def test_duplicate_command_does_not_step_twice(rig_factory) -> None:
    rig = rig_factory()
    for k in range(10):
        rig.step(k, 0.002)
    fb1 = rig.step(10, 0.003)
    steps = rig.twin.stats.steps
    rig.driver.send(10, 0.003)  # same sequence number again (a retransmission)
    assert rig.driver.receive(0.1) is None  # the answer is a duplicate: counted, not delivered
    assert rig.twin.stats.steps == steps
    assert rig.twin.stats.repeats == 1
    assert rig.driver.stats.duplicates == 1
    fb2 = rig.step(11, 0.003)
    assert fb2.seq == 11 and fb1.seq == 10


# -- e-stop -----------------------------------------------------------------------------------
def test_estop_reaches_twin_and_twin_holds(rig_factory) -> None:
    rig = rig_factory()
    cmd = commands(80)
    fb = None
    for k in range(60):
        fb = rig.step(k, float(cmd[k]))
    held = fb.displacement
    steps = rig.twin.stats.steps
    rig.driver.estop()
    after = [rig.step(k, 0.05) for k in range(60, 75)]  # a large command must be ignored
    assert all(f is not None and f.status & Status.ESTOP_ACTIVE for f in after)
    assert all(not f.status & Status.ENABLED for f in after)
    assert all(f.displacement == held for f in after)
    assert rig.twin.stats.steps == steps
    assert rig.twin.stats.estops == 1
    assert rig.driver.stats.estops == 1
    # enable=True alone does not clear the latch; enable=False acknowledges it.
    assert rig.step(75, 0.0).status & Status.ESTOP_ACTIVE
    ack = rig.step(76, 0.0, enable=False)
    assert not ack.status & Status.ESTOP_ACTIVE and not ack.status & Status.ENABLED
    resumed = rig.step(77, 0.0)
    assert resumed.status == Status.ENABLED
    assert rig.twin.stats.steps == steps + 1


# -- timeouts and injected faults -------------------------------------------------------------
@pytest.mark.timing  # an elapsed time
def test_timeout_returns_none_and_counts(rig_factory) -> None:
    rig = rig_factory()
    t0 = time.perf_counter()
    assert rig.driver.receive(0.05) is None  # nothing sent: nothing comes
    elapsed = time.perf_counter() - t0
    assert 0.045 <= elapsed < 0.5
    assert rig.driver.stats.timeouts == 1


def run(rig: Rig, n: int, short: set[int] | range = frozenset(), timeout: float = TIMEOUT):
    """Run ``n`` steps; the steps in ``short`` (expected to time out) wait only 0.1 s."""
    cmd = commands(n)
    return [rig.step(k, float(cmd[k]), timeout=0.1 if k in short else timeout) for k in range(n)]


def test_fault_drop_feedback(rig_factory) -> None:
    rig = rig_factory(Faults(drop={5, 6}))
    fbs = run(rig, 12, short={5, 6})
    assert fbs[5] is None and fbs[6] is None
    assert [f.seq for f in fbs if f is not None] == [0, 1, 2, 3, 4, 7, 8, 9, 10, 11]
    s = rig.driver.stats
    assert (s.timeouts, s.seq_gaps, s.received) == (2, 2, 10)
    assert rig.twin.stats.steps == 12  # the commands arrived; only the answers were lost


def test_fault_drop_command(rig_factory) -> None:
    rig = rig_factory(Faults(drop_command={5}))
    fbs = run(rig, 8, short={5})
    assert fbs[5] is None
    assert fbs[6].status & Status.SEQ_GAP  # the controller saw the hole
    assert not fbs[7].status & Status.SEQ_GAP
    assert rig.twin.stats.steps == 7 and rig.twin.stats.seq_gaps == 1
    assert rig.driver.stats.seq_gaps == 1


@pytest.mark.timing  # 0.15 s late against a 0.1 s wait
def test_fault_delay_gives_timeout_then_late_frame(rig_factory) -> None:
    # the answer to step 5 comes 0.15 s late: after step 5's timeout (0.1 s), before step 6's
    rig = rig_factory(Faults(delay={5: 0.15}))
    fbs = run(rig, 8, short={5})
    assert fbs[5] is None
    assert [f.seq for f in fbs if f is not None] == [0, 1, 2, 3, 4, 6, 7]
    s = rig.driver.stats
    assert s.late == 1 and s.timeouts == 1 and s.seq_gaps == 1


def test_fault_corrupt_is_detected(rig_factory, transport: Transport) -> None:
    rig = rig_factory(Faults(corrupt={4}))
    fbs = run(rig, 8, short={4})
    assert fbs[4] is None
    assert all(f is not None for i, f in enumerate(fbs) if i != 4)
    s = rig.driver.stats
    assert s.malformed == 1
    assert s.malformed_reasons == {transport.corrupt_reason: 1}


def test_fault_duplicate_is_skipped(rig_factory) -> None:
    rig = rig_factory(Faults(duplicate={3}))
    fbs = run(rig, 6)
    assert [f.seq for f in fbs] == list(range(6))
    assert rig.driver.stats.duplicates == 1
    assert rig.driver.stats.received == 6


def test_fault_stuck_sensor(rig_factory, transport: Transport) -> None:
    n, k0 = 120, 60
    rig = rig_factory(Faults(stuck_from=k0))
    fbs = run(rig, n)
    x_ref, f_ref = reference(commands(n), transport)
    disp = np.array([f.displacement for f in fbs])
    np.testing.assert_allclose(disp[:k0], x_ref[:k0], atol=tol(transport.disp_lsb))
    assert np.all(disp[k0:] == disp[k0 - 1])
    assert np.ptp(x_ref[k0:]) > 1e-3  # the actuator kept moving while the sensor did not
    # the force sensor is not stuck
    force = np.array([f.force for f in fbs])
    np.testing.assert_allclose(force[k0:], f_ref[k0:], atol=(transport.force_lsb or 1e-6))


def test_fault_runaway(rig_factory, transport: Transport) -> None:
    n, k0, rate = 100, 40, 0.05
    rig = rig_factory(Faults(runaway_from=k0, runaway_rate=rate))
    fbs = run(rig, n)
    x_ref, _ = reference(commands(n), transport)
    disp = np.array([f.displacement for f in fbs])
    drift = np.where(np.arange(n) >= k0, rate * DT * (np.arange(n) - k0 + 1), 0.0)
    np.testing.assert_allclose(disp, x_ref + drift, atol=tol(transport.disp_lsb) + 1e-12)
    assert all(f.status & Status.FAULT for f in fbs[k0:])
    assert not any(f.status & Status.FAULT for f in fbs[:k0])


def test_fault_nan_feedback_is_delivered_not_raised(rig_factory) -> None:
    rig = rig_factory(Faults(nan={7}))
    fbs = run(rig, 10)
    assert math.isnan(fbs[7].displacement)
    assert fbs[7].status & Status.SENSOR_INVALID
    assert all(math.isfinite(f.displacement) for i, f in enumerate(fbs) if i != 7)
    assert rig.driver.stats.invalid_values == 1


def test_fault_disconnect(rig_factory, transport: Transport) -> None:
    rig = rig_factory(Faults(disconnect_from=5))
    fbs = run(rig, 8, short=range(5, 8))
    assert all(f is not None for f in fbs[:5])
    assert fbs[5:] == [None, None, None]
    s = rig.driver.stats
    assert s.timeouts == 3
    if transport.driver != "can":  # a CAN node that falls silent is only a timeout
        assert s.disconnects >= 1


@pytest.mark.timing  # 0.05 s waits
def test_random_frame_faults_never_raise(rig_factory) -> None:
    rig = rig_factory(Faults(p_drop=0.05, p_corrupt=0.05, p_duplicate=0.05, seed=11))
    fbs = run(rig, 200, timeout=0.05)
    got = [f for f in fbs if f is not None]
    s = rig.driver.stats
    assert s.received == len(got) and s.timeouts == 200 - len(got)
    assert 150 < len(got) < 200
    assert s.malformed > 0 and s.duplicates > 0
    assert all(f.seq == k for k, f in enumerate(fbs) if f is not None)


def test_invalid_commands_are_refused(rig_factory) -> None:
    rig = rig_factory()
    with pytest.raises(InputError, match="not finite"):
        rig.driver.send(0, math.nan)
    with pytest.raises(InputError, match="sequence"):
        rig.driver.send(-1, 0.0)
    assert rig.driver.stats.sent == 0


@pytest.mark.timing  # an elapsed time
@pytest.mark.parametrize("interface", ["serial", "slcan"])
def test_can_over_a_serial_line_reports_the_far_end_gone(interface, caplog) -> None:
    """The served CAN twin's pseudo-terminals closed under a connected driver (the twin process
    killed): receive returns at once with a disconnect, and python-can's notifier thread
    ends after one warning instead of retrying the dead line forever or dying with a traceback."""
    import threading

    twin = start_twin("can", plant(), interface=interface)
    drv = create_driver("can", **twin.connection)
    drv.open()
    try:
        assert drv.arm(1.0) is not None
        for k in range(10):
            drv.send(k, 0.001, True)
            assert drv.receive(1.0) is not None
        twin.stop()  # closes both pseudo-terminals
        time.sleep(0.3)
        t = time.perf_counter()
        drv.send(10, 0.001, True)
        assert drv.receive(0.2) is None
        assert time.perf_counter() - t < 0.25
        assert drv.stats.disconnects + drv.stats.send_errors >= 1
        path = drv.channel
        readers = [t for t in threading.enumerate() if "Notifier" in t.name and path in t.name]
        assert not readers, readers
        gone = [r for r in caplog.records if "reading the bus failed" in r.getMessage()]
        assert len(gone) == 1, [r.getMessage() for r in caplog.records]
    finally:
        drv.close()
        twin.stop()

"""The bridge against a Modbus TCP servo controller written independently of it
(``modbus_servo.py``: its own register map, one transaction at a time, pauses of its own, its
own plant in real time), through a profile written from the docs (``modbus_servo.toml``).

What the bridge did to the controller is read from the controller itself: over a Modbus
connection of the test's own (pymodbus's client) and from the controller's history at exit.
"""

from __future__ import annotations

import json
import logging
import re
import socket
import statistics
import struct
import threading
import time
from pathlib import Path

import pytest
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.api import open_run
from tests.helpers.cli import run_cli
from tests.partners.modbus_fixtures import PROFILE

pytestmark = pytest.mark.timing

ROOT = Path(__file__).resolve().parents[2]
READY, ENABLED, FAULT, WATCHDOG, ESTOP = 0x01, 0x02, 0x08, 0x20, 0x80


def run_bridge(partner, out: Path, *sets: str, duration: float = 1.0) -> tuple[int, str]:
    """``rths-hil run`` (paced) against the partner, as a lab runs it (in this process: the
    partner is the other process); its exit code and what it printed."""
    argv = [
        "run", "--no-plot", "--confirm-hardware", "--out", str(out), "--duration", str(duration),
        "--set", "twin.enabled=false", "--set", "driver.name=modbus",
        "--set", f'driver.profile="{PROFILE}"',
        "--set", f'driver.connection={{host="127.0.0.1", port={partner.port}}}',
        "--set", "loop.console=0",
    ]  # fmt: skip
    for s in sets:
        argv += ["--set", s]
    r = run_cli(argv)
    return r.returncode, r.stdout + r.stderr


def events(out: Path, kind: str) -> list[dict]:
    lines = (out / "events.jsonl").read_text().splitlines()
    return [e for e in map(json.loads, lines) if e["kind"] == kind]


# ------------------------------------------------------------------------------------------
# item 2: the docs' default profile (pipelined) with a one-at-a-time server
# ------------------------------------------------------------------------------------------
def test_pipelining_is_probed_at_open_and_falls_back_to_one_at_a_time(modbus_servo, caplog):
    """The partner drops the second of two requests written together: the driver finds out
    when it opens, sends one request at a time, says so, and arms; the project's own twin of
    the same profile answers pipelined requests, and there the driver keeps pipelining."""
    partner = modbus_servo(pause_rate=0)
    with caplog.at_level(logging.WARNING):
        drv = create_driver("modbus", profile=str(PROFILE), **partner.connection)
        with drv:
            assert drv.link_note is not None and "one request at a time" in drv.link_note
            fb = drv.arm(0.5)
            assert fb is not None and fb.displacement == 0.0
    assert any("answers one request at a time" in r.getMessage() for r in caplog.records)
    assert partner.stop()["dropped"] >= 1  # the probe's second request

    twin = start_twin("modbus", default_plant(), profile=str(PROFILE), port=0)
    try:
        with create_driver("modbus", **twin.connection) as drv:
            assert drv.link_note is None and drv._reply is not None  # still pipelined
            assert drv.arm(0.5) is not None
    finally:
        twin.stop()


def test_a_slow_one_at_a_time_link_is_timed_at_open_and_named_against_the_period(modbus_servo):
    """The partner takes 3 ms to serve each transaction (a slow controller stack), one at a
    time. The driver times single reads when it opens: their median lies within the test's
    own round trips (pymodbus's client on a second connection, just before and just after).
    A step's FC 16 + FC 4 then need about 6 ms: at 256 Hz (3.9 ms period) the driver's link
    check warns and names the highest rate that leaves a quarter of the period free; below
    that rate it is silent."""
    partner = modbus_servo(pause_rate=0, service_time=0.003)
    client = partner.client()

    def own_median() -> float:
        times = []
        for _ in range(24):
            sent = time.perf_counter()
            assert not client.read_input_registers(2048, count=5).isError()
            times.append(time.perf_counter() - sent)
        return statistics.median(times)

    before = own_median()
    with create_driver("modbus", profile=str(PROFILE), **partner.connection) as drv:
        after = own_median()
        assert drv.round_trip is not None
        median, p90 = drv.round_trip
        assert 0.003 <= median <= p90
        assert 0.75 * min(before, after) <= median <= 1.25 * max(before, after)
        warning = drv.link_check(256.0)
        assert warning is not None and "2 requests (FC 16 + FC 4)" in warning
        highest = float(re.search(r"At most (\d+) Hz", warning).group(1))
        assert highest == pytest.approx(0.75 / (2 * median), abs=1.0)
        assert drv.link_check(0.9 * highest) is None
        assert drv.link_check(1.1 * highest) is not None


# ------------------------------------------------------------------------------------------
# item 3: the e-stop reaches the controller whatever is outstanding
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("own_connection", [True, False])
def test_estop_reaches_a_busy_controller_and_is_read_back(modbus_servo, own_connection):
    """Every request makes the partner's network stack pause 20–40 ms: a step's request is
    in progress when the e-stop is sent, and a request written on that connection meanwhile
    would be dropped. The e-stop goes over its own connection (or waits for the outstanding
    answer), is read back, and the controller's status, read by the test, is 0x80: the
    e-stop latched, not its watchdog (0xA0)."""
    partner = modbus_servo(pause_rate=1e6)  # a pause before every request
    drv = create_driver(
        "modbus", profile=str(PROFILE), estop_connection=own_connection, **partner.connection
    )
    with drv:
        assert drv.arm(1.0) is not None
        drv.send(0, 0.0, True)  # the set-point, the enable coil, the read: one at a time
        assert drv.receive(0.5) is not None
        drv.heartbeat()
        drv.send(1, 0.0, True)  # its set-point write is in the partner's pause now
        time.sleep(0.002)
        t0 = time.monotonic()
        drv.estop()
        took = time.monotonic() - t0
        assert drv.estop_word == ESTOP, hex(drv.estop_word or 0)
        assert partner.status() == ESTOP
        # the poll the runner confirms with goes to an idle controller
        drv.send(2, 0.0, True)
        fb = drv.receive(0.5)
        assert fb is not None and fb.status & 0x02  # the bridge's ESTOP_ACTIVE flag
    state = partner.stop()
    assert [x["cause"] for x in state["latches"]] == ["estop"]
    assert took < 0.3


def test_estop_to_a_killed_controller_ends_at_once_unconfirmed(modbus_servo, caplog):
    """The controller's process killed: the e-stop finds both connections closed, says it is
    not confirmed and returns (no 0.5 s of retries into closed sockets)."""
    partner = modbus_servo(pause_rate=0)
    drv = create_driver("modbus", profile=str(PROFILE), **partner.connection)
    with drv, caplog.at_level(logging.WARNING):
        assert drv.arm(1.0) is not None
        partner.proc.kill()
        partner.proc.wait()
        time.sleep(0.05)
        drv.send(0, 0.0, True)
        drv.receive(0.05)
        t0 = time.monotonic()
        drv.estop()
        took = time.monotonic() - t0
    assert drv.estop_word is None and took < 0.3, took
    assert any("not confirmed: no status read back" in r.getMessage() for r in caplog.records)


def test_trip_mid_run_estops_the_controller_not_its_watchdog(modbus_servo, tmp_path):
    """A paced run with the docs' default profile trips mid-run (a displacement limit the
    test reaches) while the partner pauses now and then: its status, read by the test over
    its own connection, is the e-stop (0x80), its only latch, and the
    run's e-stop is confirmed."""
    # its watchdog at 1 s (a parameter of the controller): a stall of this loaded machine
    # must not latch it before the trip; the e-stop is under test here
    partner = modbus_servo(pause_rate=8, watchdog=1.0)
    out = tmp_path / "trip"
    sets = ("safety.displacement_limit=0.15mm", "loop.fs=512", "loop.heartbeat=0.05")
    sets += ("safety.watchdog_timeout=0.25",)  # (a starved process is not the trip here)
    rc, text = run_bridge(partner, out, *sets, duration=2.0)
    assert rc == 3, text
    assert partner.status() == ESTOP
    state = partner.stop()
    assert [x["cause"] for x in state["latches"]] == ["estop"], state["latches"]
    s = open_run(out).summary()
    assert s["status"] == "trip" and s["estop_confirmed"] is True
    assert "e-stop to the controller" in text and "latched, status register 0x0080" in text


# ------------------------------------------------------------------------------------------
# item 4: no start jump
# ------------------------------------------------------------------------------------------
def test_no_motion_at_the_enable_edge_from_plus_5_mm(modbus_servo, tmp_path):
    """The partner powers up at +5 mm with its set-point register at 0.0 (it follows the
    register from the enable edge). Polled at 1 kHz over the test's own connection until
    0.2 s after it reports ENABLED, the axis moves at most 0.1 mm in the 50 ms after the
    enable edge; the set-point it holds at the edge is where the axis was (written before the
    enable), and arming wrote none."""
    partner = modbus_servo(position=0.005, pause_rate=0)
    samples: list[tuple[float, float]] = []
    stop = threading.Event()

    def poll() -> None:
        client = ModbusPoller(partner)
        nxt = time.monotonic()
        enabled_at = None
        while not stop.is_set():
            t0 = time.monotonic()
            got = client.read()
            if got is not None:
                samples.append(((t0 + time.monotonic()) / 2, got[0]))
                if got[1] & ENABLED and enabled_at is None:
                    enabled_at = t0
            if enabled_at is not None and t0 > enabled_at + 0.2:
                return  # (the partner serves the bridge alone from here)
            nxt += 0.001
            time.sleep(max(0.0, nxt - time.monotonic()))

    t = threading.Thread(target=poll, daemon=True)
    t.start()
    out = tmp_path / "jump"
    sets = ('start.mode="offset"', "end.hold=0", "loop.fs=256")
    rc, text = run_bridge(partner, out, *sets, duration=0.2)
    stop.set()
    t.join(2)
    assert rc == 0, text
    state = partner.stop()
    (edge,) = state["enable_edges"]
    assert edge["setpoint"] == pytest.approx(0.005, abs=1e-6)  # written before the enable
    t_edge = edge["monotonic"]
    window = [(ts - t_edge, p) for ts, p in samples if t_edge <= ts <= t_edge + 0.050]
    # the poll saw the window (at 1 kHz when this loaded machine lets it: 8 to 50 samples
    # here); a jump towards the register's 0.0 would be 3 mm off after 20 ms (12 ms delay,
    # 8 ms lag), so samples late in the window are what must be there
    assert len(window) >= 5 and window[-1][0] > 0.035, window
    moved = max(abs(p - 0.005) for _, p in window)
    assert moved <= 1e-4, f"{moved * 1e3:.3f} mm"
    assert state["setpoint_writes"] > 0 and all(a["t"] < edge["t"] for a in state["ack_writes"])


class ModbusPoller:
    """The test's own connection reading the partner's position and status: the FC 4 request
    built once by pymodbus (its framer), its answer decoded by pymodbus, on a plain socket (a
    poll at 1 kHz costs the test little)."""

    def __init__(self, partner) -> None:
        from pymodbus.framer import FramerSocket
        from pymodbus.pdu import DecodePDU
        from pymodbus.pdu.register_message import ReadInputRegistersRequest

        self.framer = FramerSocket(DecodePDU(False))
        req = ReadInputRegistersRequest(address=2048, count=5, dev_id=1, transaction_id=7)
        self.frame = self.framer.buildFrame(req)
        self.sock = socket.create_connection(("127.0.0.1", partner.port), 1.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.settimeout(0.1)

    def read(self) -> tuple[float, int] | None:
        """(position m, status register), or None for a dropped request."""
        try:
            self.sock.sendall(self.frame)
            data = self.sock.recv(256)
        except TimeoutError:
            return None
        used, _, _, pdu_bytes = self.framer.decode(data)
        if not used or not pdu_bytes:
            return None
        regs = self.framer.decoder.decode(pdu_bytes).registers
        pos = struct.unpack(">f", struct.pack(">HH", *regs[:2]))[0] * 1e-3
        return pos, regs[4]


# ------------------------------------------------------------------------------------------
# item 8: the controller's own terms; the paced hand-back
# ------------------------------------------------------------------------------------------
def test_watchdog_trip_names_the_status_register_and_the_link_its_requests(modbus_servo, tmp_path):
    """Without heartbeats the partner's own watchdog latches 200 ms after the enable: the
    trip reason gives its status register as the controller has it (0x00A0: watchdog and
    e-stop), and the link-budget line names the requests this profile sends (FC 16 + FC 4)."""
    partner = modbus_servo(pause_rate=0)
    out = tmp_path / "wd"
    sets = ("loop.heartbeat=0", "loop.fs=512", "safety.watchdog_timeout=0.25")  # (a stall
    # of this loaded machine is not the trip under test)
    rc, text = run_bridge(partner, out, *sets, duration=1.0)
    assert rc == 3, text
    (trip,) = events(out, "trip")
    assert "status register 0x00A0 (e-stop, watchdog)" in trip["reason"], trip
    assert "FC 16 + FC 4" in text and "FC 23" not in text, text
    assert partner.status() == WATCHDOG | ESTOP


def test_a_link_too_slow_for_the_rate_is_said_at_arming_and_costs_what_it_said(
    modbus_servo, tmp_path
):
    """The partner takes 2 ms per transaction: at 512 Hz a step's FC 16 + FC 4 need about
    4 ms of a 1.95 ms period. ``run`` says so before it arms (terminal and record, with the
    highest rate that fits), and the run then misses about the share of replies the link
    cannot carry (at least a third: the link carries at most one step's pair in two), held
    as degradation: the enable, the set-points and a read every few steps still go out, and
    the run completes (before, each step's write went out ahead of the read and the enable
    again, no read ever did, and the reply watchdog tripped)."""
    partner = modbus_servo(pause_rate=0, service_time=0.002)
    out = tmp_path / "slow"
    sets = ("loop.fs=512", "safety.watchdog_timeout=0.2")
    rc, text = run_bridge(partner, out, *sets, duration=1.0)
    (link,) = events(out, "link")
    assert "2 requests (FC 16 + FC 4)" in link["warning"] and "at 512 Hz" in link["warning"]
    assert link["warning"] in text
    highest = float(re.search(r"At most (\d+) Hz", link["warning"]).group(1))
    # at most 0.75 / (2 × 2.0 ms): the partner's service time is a floor of the round trip
    # (its accuracy against the test's own round trips is test_a_slow_one_at_a_time_link_...;
    # a starved machine measures longer ones, hence no lower bound here)
    assert highest <= 190
    assert rc == 0, text
    s = open_run(out).summary()
    assert s["status"] == "completed" and s["steps"] == 512
    assert s["steps"] / 3 <= s["missed_replies"] < s["steps"], s


def test_paced_512_hz_default_profile_completes_and_hands_back_disabled(modbus_servo, tmp_path):
    """The docs' default profile (pipeline = true), paced at 512 Hz against the partner with
    its pauses: the run completes and the controller is handed back disabled, not latched
    (status 0x01, READY only, read over the test's own connection)."""
    # this 2-core machine, shared and loaded, starves a process now and then (the bridge
    # 100 ms, the partner 250 ms seen here): the partner's watchdog and the bridge's reply
    # watchdog at 0.5 s, so that what is tested is the run and its hand-back
    partner = modbus_servo(pause_rate=2, watchdog=0.5)
    out = tmp_path / "paced"
    sets = ("loop.fs=512", "loop.heartbeat=0.05", "safety.watchdog_timeout=0.5")
    rc, text = run_bridge(partner, out, *sets, duration=2.0)
    assert rc == 0, text
    assert "answers one request at a time" in text
    (arm,) = events(out, "arm")  # the fallback is in the record, not only on the terminal
    assert "one request at a time" in arm["link"]
    assert partner.status() == READY
    s = open_run(out).summary()
    assert s["status"] == "completed" and s["steps"] == 1024
    (hb,) = events(out, "handback")
    assert hb["disabled"] and not hb["latched"]
    assert partner.stop()["latches"] == []


# ------------------------------------------------------------------------------------------
# item 7: one request at a time, a missed reply does not cost the next step its reply too
# ------------------------------------------------------------------------------------------
def test_the_last_steps_outstanding_read_is_the_next_steps_measurement(modbus_servo):
    """Every request makes the partner pause 20–40 ms. Step 0's read is still outstanding when
    step 1 is sent: its answer — the controller samples when it serves the read, during step
    1 — is step 1's measurement, not an answer discarded as late while step 1 waits for a read
    of its own one more transaction (here one more pause) later."""
    partner = modbus_servo(pause_rate=1000)  # (a pause before every request)
    drv = create_driver("modbus", profile=str(PROFILE), **partner.connection)
    with drv:
        assert drv.arm(2.0) is not None
        drv.send(0, 0.0, True)  # the enable edge: set-point, enable, read
        assert drv.receive(1.0) is not None
        drv.send(1, 0.0, True)  # a steady step: the set-point write, then its read
        t0 = time.perf_counter()
        assert drv.receive(0.001) is None  # the write is paused at the partner
        while drv.receive(0.001) is None:  # until the write's answer came: the read is out
            assert time.perf_counter() - t0 < 0.2
            if drv._pending and drv._pending[0][0] & 15 == 1:
                break
        late = drv.stats.late
        drv.send(2, 0.0, True)  # step 1's read still outstanding
        t1 = time.perf_counter()
        fb = drv.receive(0.2)
        wait = time.perf_counter() - t1
    assert fb is not None and fb.seq == 2
    assert drv.stats.late == late  # step 1's answer was not thrown away
    # one pause (the read's, under way already), not three (read, write, a read of its own)
    assert wait < 0.045, f"{wait * 1e3:.1f} ms"


def test_pipelined_the_last_steps_outstanding_read_is_the_next_steps_measurement(modbus_servo):
    """The partner's firmware with a request queue (``--serve queue``) takes 20 ms over each
    transaction. Pipelined, step 1's set-point write and read are both still queued when step 2
    goes out: step 2 writes its set-point alone, and step 1's read, answered after step 1's
    write, is step 2's measurement. With a read of its own, step 2 would wait two more
    transactions (its write and its read) and the bridge would stay a step behind a controller
    that needs most of the period (the missed replies of a paced run, one after the other)."""
    service = 0.02
    partner = modbus_servo(pause_rate=0, service_time=service, serve="queue")
    drv = create_driver("modbus", profile=str(PROFILE), **partner.connection)
    with drv:
        assert drv.link_note is None and drv._reply is not None  # it answers pipelined requests
        assert drv.arm(2.0) is not None
        drv.send(0, 0.0, True)  # the enable edge: set-point, enable, set-point and read
        assert drv.receive(1.0) is not None
        drv.send(1, 0.0, True)  # a steady step: write and read in one segment
        assert drv.receive(0.001) is None  # both queued at the partner
        late = drv.stats.late
        drv.send(2, 0.0, True)  # step 1's read still outstanding
        t1 = time.perf_counter()
        fb = drv.receive(0.2)
        wait = time.perf_counter() - t1
        drv.send(3, 0.0, True)  # step 2 read nothing of its own: step 3 reads anew
        fb3 = drv.receive(0.2)
    assert fb is not None and fb.seq == 2
    assert drv.stats.late == late  # step 1's answer was not thrown away
    # the rest of step 1's write and its read (2 transactions), not 4 (and step 2's write)
    assert wait < 3 * service, f"{wait * 1e3:.1f} ms"
    assert fb3 is not None and fb3.seq == 3
    history = partner.stop()
    assert history["dropped"] == 0

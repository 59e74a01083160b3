"""CANopen driver and twin (CiA 402 / CiA 408 through the ``canopen`` library, virtual bus).

The twin is a ``canopen`` LocalNode with the shipped EDS; the driver a RemoteNode. Checked: the
SDO identity check at start-up (pass and each refusal in one line), the device FSA walked by the
driver as the twin reports it (status words and the bridge's flags), a lockstep run that tracks
(FEI amplitude within 1 %, as over the CAN twin), an EMCY that trips the loop naming its code,
the twin's heartbeat consumer latching when the bridge falls silent, bad EDS / profile / PDO
input refused in one line with exit 2, the link budget against frame sizes worked by hand, and
frame faults (drop, corrupt, delay) counted by the driver.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from canopen.profiles.p402 import State402
from rths_hil.drivers.base import Status
from rths_hil.drivers.can.linkbudget import can_frame_bits
from rths_hil.drivers.canopen import CANopenDriver, axes_that_fit, link_load
from rths_hil.drivers.registry import create_driver, protocol
from rths_hil.sim_backends.endpoints.canopen import EMCY_FOLLOWING_ERROR, default_eds
from rths_hil.sim_backends.faults import Faults
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.cli import main
from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.hybrid import RTHSLoop
from rths_hil.linkbudget import link_load as budget
from rths_hil.records.recorder import read_run
from tests.helpers.loop import run_loop

# The object dictionary, the state machines, refusals and lockstep runs (waits of 1 s and more)
# run with the parallel tests; the tests of heartbeats, of a wait of 0.1 s or less, of an EMCY
# within a few steps and the paced run run apart from them, one at a time (the "timing"
# marker, pyproject.toml; make test).

ROOT = Path(__file__).resolve().parents[2]
ENABLED, ESTOP, FAULT = int(Status.ENABLED), int(Status.ESTOP_ACTIVE), int(Status.FAULT)


def _open(twin, **extra):
    drv = create_driver("canopen", **{**twin.connection, **extra})
    drv.open()
    return drv


@pytest.mark.parametrize("profile", ["cia402", "cia408"])
def test_identity_check_passes_and_refuses(profile):
    number = int(profile[3:])
    with start_twin("canopen", default_plant(), device_profile=profile) as twin:
        code = int(str(number), 16)  # the shipped EDS's product code: 0x402 / 0x408
        drv = _open(twin, product_code=code, vendor_id=0)
        try:  # read by SDO from the twin's object dictionary
            assert drv.identity["device_type"] & 0xFFFF == number
            assert drv.identity["product_code"] == code
        finally:
            drv.close()


def test_identity_check_refuses_wrong_product_and_wrong_profile():
    with start_twin("canopen", default_plant(), device_profile="cia402") as twin:
        with pytest.raises(InputError, match=r"product_code is 0x00000402.*expects 0x00000999"):
            _open(twin, product_code=0x999)
        # the 408 driver on a 402 device: device type names the profile it found
        with pytest.raises(
            InputError, match=r"device type 0x00020192 \(profile 402\), not CiA 408"
        ):
            _open(twin, device_profile="cia408", eds=default_eds("cia408"))


def test_cia402_state_machine_on_the_twin():
    with start_twin("canopen", default_plant(), device_profile="cia402") as twin:
        drv = _open(twin)
        armed = drv.arm(1.0)
        assert armed is not None and armed.status == 0
        assert twin.history == ["SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON"]
        assert twin.mode == 8  # cyclic synchronous position, written at start-up
        fb = None
        for k in range(50):
            drv.send(k, 0.0, True)
            fb = drv.receive(1.0)
            assert fb is not None and fb.seq == k
        assert twin.state == "OPERATION ENABLED" and fb.status == ENABLED
        assert twin.statusword() & 0x6F == State402.SW_MASK["OPERATION ENABLED"][1]
        # quick stop: latched, repeated while enable=True, acknowledged by enable=False
        drv.estop()
        drv.send(50, 0.0, True)
        fb = drv.receive(1.0)
        assert twin.state == "QUICK STOP ACTIVE" and fb.status == ESTOP
        drv.send(51, 0.0, False)
        fb = drv.receive(1.0)
        assert twin.state == "SWITCH ON DISABLED" and fb.status == 0
        for k in range(52, 56):  # enable again: shutdown → switch on → enable operation
            drv.send(k, 0.0, True)
            fb = drv.receive(1.0)
        assert fb.status == ENABLED
        drv.close()  # the protocol's own disable: shutdown, then disable voltage
        assert twin.history[-7:] == [
            "QUICK STOP ACTIVE", "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON",
            "OPERATION ENABLED", "READY TO SWITCH ON", "SWITCH ON DISABLED",
        ]  # fmt: skip
        assert twin.node.nmt.state == "STOPPED"


def test_cia408_state_machine_on_the_twin():
    with start_twin("canopen", default_plant(), device_profile="cia408") as twin:
        drv = _open(twin)
        assert drv.arm(1.0) is not None and twin.state == "HOLD"
        assert twin.mode == 1  # device mode 0x6042: set-point via the bus
        for k in range(20):
            drv.send(k, 0.0, True)
            fb = drv.receive(1.0)
        assert twin.state == "ACTIVE" and fb.status == ENABLED
        assert twin.statusword() & 0x0F == 0b1111
        drv.estop()  # HOLD, latched by the driver
        drv.send(20, 0.0, True)
        assert drv.receive(1.0).status == ESTOP and twin.state == "HOLD"
        drv.send(21, 0.0, False)
        assert drv.receive(1.0).status == 0 and twin.state == "HOLD"
        drv.close()
        assert twin.history == ["INIT", "HOLD", "ACTIVE", "HOLD", "DISABLED"]


def _run(tmp_path, profile, *overrides, name="run"):
    path = ROOT / "examples" / "controllers" / f"{profile}.toml"
    r = run_loop(tmp_path / name, path, "loop.mode=lockstep", *overrides)
    return r.loop, r.result, r.run


@pytest.mark.parametrize("profile", ["cia402", "cia408"])
def test_lockstep_run_tracks(tmp_path, profile):
    _, res, run = _run(tmp_path, profile, "loop.duration=6")
    assert res.status == "completed", res.trip
    rec = run.record
    assert len(rec) == 6 * 1024
    fei = rec["fei_amplitude"][~np.isnan(rec["fei_amplitude"])]
    assert fei.size > 500
    assert np.abs(fei[-200:] - 1.0).max() < 0.01
    # one SYNC per step of the record (the runner's start and end phases may add a few)
    assert 0 <= res.driver_stats["syncs"] - len(rec) <= 4
    assert res.driver_stats["received"] >= len(rec) - 2


@pytest.mark.timing  # the EMCY within 2 steps
def test_emcy_trips_the_loop_naming_the_code(tmp_path):
    at = 1024
    _, res, _ = _run(
        tmp_path, "cia402", f"twin.faults=runaway_from={at}; runaway_rate=0.5", "loop.duration=3"
    )
    assert res.status == "trip" and res.trip.rule == "controller"
    assert "FAULT" in res.trip.reason
    assert f"EMCY 0x{EMCY_FOLLOWING_ERROR:04X}" in res.trip.reason
    assert abs(res.trip.step - at) <= 2
    assert any(s.startswith("0x8611") for s in res.driver_stats["emcy"])


@pytest.mark.timing
@pytest.mark.parametrize("inline", [False, True])
def test_twin_latches_when_the_bridge_heartbeat_stops(inline):
    """Served on its thread or inline (the steps pumped from this thread, the SDO exchanges by
    the twin's thread): when the bridge falls silent the twin's thread takes over, and the
    heartbeat consumer latches the device in FAULT with EMCY 0x8130."""
    # 0.25 s: a bridge descheduled for tens of ms on a loaded 2-core machine is not a dead one
    timeout = 0.25
    twin = start_twin(
        "canopen",
        default_plant(),
        device_profile="cia402",
        heartbeat_timeout=timeout,
        threaded=not inline,
    )
    with twin:
        assert twin.inline is inline
        drv = _open(twin, heartbeat_period=0.02)  # start-up by SDO: served by the thread
        drv.arm(1.0)
        for k in range(30):
            drv.send(k, 0.0, True)
            if inline:
                n = twin.pump()  # this step's RPDO and SYNC (+ heartbeats), answered at once
                assert n >= 2 or k == 0  # (step 0: the thread, not yet standing by, may be first)
                assert drv.receive(0.0) is not None  # the TPDO set is in: nothing to wait for
            else:
                assert drv.receive(1.0) is not None
            time.sleep(0.002)
        assert twin.state == "OPERATION ENABLED"
        t0 = time.monotonic()  # the bridge falls silent: no heartbeat, no SYNC
        while twin.state != "FAULT" and time.monotonic() - t0 < 2.0:
            time.sleep(0.005)
        latency = time.monotonic() - t0
        assert twin.state == "FAULT"
        assert latency < timeout + 0.25  # the consumer time plus its poll, on a loaded machine
        assert twin.controller.watchdog_tripped
        drv.send(30, 0.0, True)  # the next reply reports it; the EMCY names the code
        fb = drv.receive(1.0)
        assert fb.status & FAULT and fb.status & int(Status.WATCHDOG)
        assert "0x8130" in drv.fault_text()
        assert drv.arm(1.0) is not None and twin.state == "SWITCHED ON"  # reset at arming
        drv.close()


def _run_refused(argv: list[str], capsys) -> list[str]:
    """``rths-hil run ARGV`` in this process: exit 2, no traceback; the error lines."""
    code = main(["run", *argv])
    stderr = capsys.readouterr().err
    assert code == 2, stderr
    assert "Traceback" not in stderr
    return [x for x in stderr.splitlines() if "error" in x]


@pytest.mark.parametrize(
    "setting, message",
    [
        (
            "device_profile=cia999",
            "driver.connection.device_profile: must be one of cia402, cia408, got 'cia999'",
        ),
        ("eds=missing.eds", "eds: no such file"),
        ("force_object=0x2999", "has no object 0x2999:00 (force_object)"),
        ("node_id=0", "driver.connection.node_id: must be ≥ 1, got 0"),
        ("counts_per_m=0", "driver.connection.counts_per_m: must be > 0 counts/m, got 0"),
    ],
)
def test_bad_connection_is_one_line_exit_2(tmp_path, setting, message, capsys):
    cfg = ROOT / "examples" / "controllers" / "cia402.toml"
    sets = ["--set", f"driver.connection.{setting}", "--set", f"output.dir={tmp_path}/r"]
    err = _run_refused([str(cfg), "--lockstep", "--duration", "0.5", *sets], capsys)
    assert len(err) == 1 and message in err[0], err


def test_eds_whose_pdo_does_not_fit_is_refused(tmp_path):
    eds = Path(default_eds("cia402")).read_text()
    # the target position as a 64-bit integer: control word + target = 80 bits > 8 bytes
    head = "[607A]\nParameterName=Target position\nObjectType=0x7\nDataType="
    eds = eds.replace(head + "0x0004", head + "0x0015")
    (tmp_path / "big.eds").write_text(eds)
    with pytest.raises(InputError, match=r"RPDO1 does not fit in 8 bytes: .* = 80 bits"):
        CANopenDriver(eds=str(tmp_path / "big.eds"))


def test_link_budget_counts_sync_pdos_and_heartbeats():
    # one axis at 1024 Hz: SYNC (0 bytes) + RPDO (6) + TPDO1 (6) + TPDO2 (4), heartbeats 1 byte
    per_step = can_frame_bits(0) + 2 * can_frame_bits(6) + can_frame_bits(4)
    hb = 2 * can_frame_bits(1) * 10.0  # the bridge's and the device's, 10 Hz each
    ld = budget(
        "canopen", {"bitrate": 1_000_000, "interface": "socketcan"}, 1, 1024, heartbeat_hz=10.0
    )
    assert ld.load == pytest.approx((per_step * 1024 + hb) / 1e6)
    two = link_load({"bitrate": 1_000_000, "interface": "socketcan"}, 2, 1024, heartbeat_hz=10.0)
    # one SYNC and one bridge heartbeat for the bus, the PDOs and device heartbeats per axis
    assert two.load == pytest.approx(
        ((can_frame_bits(0) + 2 * (per_step - can_frame_bits(0))) * 1024 + 3 * hb / 2) / 1e6
    )
    assert axes_that_fit(1024) == 2 and two.load < 0.8
    assert axes_that_fit(512) == 4


@pytest.mark.timing  # 0.3 s late against a 0.1 s wait
@pytest.mark.parametrize(
    "faults, counter",
    [("drop=40", "timeouts"), ("corrupt=40", "malformed"), ("delay=40:0.3", "timeouts")],
)
def test_frame_faults_are_counted(faults, counter):
    with start_twin("canopen", default_plant(), faults=Faults.parse(faults)) as twin:
        drv = _open(twin)
        drv.arm(1.0)
        missed = []
        for k in range(60):
            drv.send(k, 0.0, True)
            if drv.receive(0.1) is None:
                missed.append(k)
        drv.close()
        assert missed and missed[0] == 40
        assert getattr(drv.stats, counter) >= 1
        assert drv.stats.received >= 60 - 3


def test_pdo_bytes_follow_the_cia301_little_endian_layout():
    """The driver's RPDO and the twin's TPDOs, encoded through the library's PDO maps, are the
    CiA 301 layout written independently with struct: the mapped objects in order,
    little-endian (RPDO1 UNSIGNED16 control word + INTEGER32 target; TPDO1 UNSIGNED16 status
    word + INTEGER32 position; TPDO2 INTEGER32 force); the driver decodes TPDOs built so."""
    import struct

    with start_twin("canopen", default_plant()) as twin:
        drv = _open(twin)
        drv.arm(1.0)
        for k in range(5):
            drv.send(k, 0.0, True)
            drv.receive(1.0)
        for word, counts in ((0x000F, 12345), (0x0002, -(2**31) + 1), (0x0006, 2**31 - 1)):
            drv._rpdo(5, word, counts)
            drv._bus.sync()
            assert bytes(drv._rpdo_msg.data) == struct.pack("<Hi", word, counts)
            assert drv._rpdo_msg.arbitration_id == 0x201
        frames = twin._encode(7, -0.0123456, 4567.89, 0)
        assert [f.arbitration_id for f in frames] == [0x181, 0x281]
        assert bytes(frames[0].data) == struct.pack("<Hi", twin.statusword(), -123456)
        assert bytes(frames[1].data) == struct.pack("<i", 456789)
        # the driver's decoding (its TPDO callback) of TPDOs packed by struct
        drv._q.clear()
        drv._delivered_sync, drv._awaiting = -2, 9
        drv._synced()  # the SYNC of step 9
        for m, data in ((drv.node.tpdo[1], struct.pack("<Hi", 0x0237, -7654321)),
                        (drv.node.tpdo[2], struct.pack("<i", -31415))):  # fmt: skip
            m.data = bytearray(data)
            drv._on_tpdo(m)
        fb = drv._q.pop()
        assert fb.seq == 9
        assert fb.displacement == pytest.approx(-0.7654321, abs=1e-12)
        assert fb.force == pytest.approx(-314.15, abs=1e-9)
        assert fb.status == ENABLED
        drv.close()


def test_canopen_bus_sharing_rules():
    """Several axes may share a bus (one SYNC for all), each with its own node id and the
    bus's bit rate; a repeated node id or a differing bit rate is refused in one line; twins
    without a named channel each get a bus of their own."""
    check_sharing = protocol("canopen").check_sharing
    same = {"interface": "socketcan", "channel": "can0"}
    check_sharing([(0, "x", {**same, "node_id": 1}, False),
                   (1, "y", {**same, "node_id": 2}, False)])  # fmt: skip
    with pytest.raises(
        InputError, match=r"'x' and 'y' are both CANopen node 3 on bus socketcan:can0"
    ):
        check_sharing([(0, "x", {**same, "node_id": 3}, False),
                       (1, "y", {**same, "node_id": 3}, False)])  # fmt: skip
    with pytest.raises(InputError, match=r"differ in driver.connection.bitrate"):
        check_sharing(
            [(0, "x", {**same, "node_id": 1, "bitrate": 1_000_000}, False),
             (1, "y", {**same, "node_id": 2, "bitrate": 500_000}, False)]
        )  # fmt: skip
    check_sharing([(0, "x", {}, True), (1, "y", {}, True)])


TWO_AXES = ROOT / "examples" / "controllers" / "cia402_two_axes.toml"


def test_two_axes_on_one_bus_share_one_sync_per_step(tmp_path):
    """Two CiA 402 axes (nodes 1 and 2) on one bus: one SYNC per step clocks both (each twin
    counts one SYNC per step, not two), each axis gets its own TPDOs (the 10 ms and 20 ms
    actuators show their own delays without compensation), the run completes in lockstep."""
    cfg = load_config(
        TWO_AXES, ["loop.console=0", "output.plot=false", "compensation.enabled=false"]
    )
    loop = RTHSLoop(cfg, tmp_path / "two", mode="lockstep", duration=8.0)
    res = loop.run()
    assert res.status == "completed", res.trip
    assert res.steps == 8 * 1024 and res.missed_replies == 0
    a, b = loop.channels
    assert [c.driver.node_id for c in loop.channels] == [1, 2]
    assert (a.driver.interface, a.driver.channel) == ("virtual", "rths-canopen-two-axes")
    assert (b.driver.interface, b.driver.channel) == (a.driver.interface, a.driver.channel)
    for ch in loop.channels:
        # SYNCs seen by each device since it went operational: one per step (+ start/end)
        assert 0 <= ch.twin.n - res.steps <= 6, (ch.twin.n, res.steps)
        assert 0 <= ch.driver.stats.syncs - res.steps <= 6
        assert ch.driver.stats.malformed == 0
    rec = read_run(tmp_path / "two").record
    for sfx, delay in (("_storey1", 0.010), ("_storey3", 0.020)):
        v = rec["fei_valid" + sfx]
        assert v.sum() > 1000
        assert abs(float(np.median(rec["fei_delay" + sfx][v])) - delay) < 1.5e-3


def test_two_axes_with_one_node_id_are_refused(tmp_path, capsys):
    argv = [str(TWO_AXES), "--lockstep", "--duration", "0.5",
            "--set", "actuators.storey3.driver.connection.node_id=1",
            "--set", f"output.dir={tmp_path}/r"]  # fmt: skip
    err = _run_refused(argv, capsys)
    assert len(err) == 1 and "both CANopen node 1 on bus virtual:rths-canopen-two-axes" in err[0]


@pytest.mark.timing  # the EMCY within 3 steps
def test_two_axes_a_fault_on_one_stops_both(tmp_path):
    """A runaway on node 2 (EMCY 0x8611) trips the loop naming that node; both axes on the
    bus are e-stopped: the healthy one confirms its quick stop, the faulty one holds in FAULT."""
    at = 1500
    cfg = load_config(
        TWO_AXES,
        ["loop.console=0", "output.plot=false",
         f"actuators.storey3.twin.faults=runaway_from={at}; runaway_rate=0.5"],
    )  # fmt: skip
    loop = RTHSLoop(cfg, tmp_path / "fault", mode="lockstep", duration=4.0)
    res = loop.run()
    assert res.status == "trip" and res.trip.rule == "controller", res.trip
    assert "canopen node 2" in res.trip.reason and "EMCY 0x8611" in res.trip.reason
    assert abs(res.trip.step - at) <= 3
    events = read_run(tmp_path / "fault").events
    stops = {e["channel"]: e for e in events if e["kind"] == "estop"}
    assert set(stops) == {"storey1", "storey3"}
    assert stops["storey1"]["confirmed"]  # the healthy axis latched its quick stop
    a, b = loop.channels  # the latches are left as they are after an e-stop
    assert a.twin.state == "QUICK STOP ACTIVE" and a.twin.history[-2] == "OPERATION ENABLED"
    assert b.twin.state == "FAULT"  # the faulty axis holds in FAULT (its quick stop ignored)


@pytest.mark.timing
def test_bridge_heartbeat_goes_on_after_an_estop_until_the_nodes_are_closed():
    """Two axes on one bus, each device's heartbeat consumer 0.25 s. While the loop steps the
    bridge's heartbeat goes with its steps (a loop that stops stepping lets the consumer run
    out: the test above). After an e-stop the loop stops on purpose and the bridge closes the
    nodes one after the other: the heartbeat goes on (the library's periodic task) until the
    last node is closed, so neither device adds a heartbeat fault (EMCY 0x8130) to the e-stop,
    however long the closing takes; arming again hands the heartbeat back to the steps."""
    timeout, period = 0.25, 0.05
    ch = {"channel": "rths-canopen-hb-hold", "heartbeat_timeout": timeout}
    with (
        start_twin("canopen", default_plant(), node_id=1, **ch) as t1,
        start_twin("canopen", default_plant(), node_id=2, **ch) as t2,
    ):
        d1, d2 = _open(t1, heartbeat_period=period), _open(t2, heartbeat_period=period)
        assert d1._bus is d2._bus  # one bus, one heartbeat producer
        for d in (d1, d2):
            assert d.arm(1.0) is not None
        for k in range(30):
            for d in (d1, d2):
                d.send(k, 0.0, True)
            for d in (d1, d2):
                assert d.receive(1.0) is not None
            time.sleep(0.002)
        assert t1.state == t2.state == "OPERATION ENABLED"
        d1.estop()
        d2.estop()
        n0 = t1.controller.stats.heartbeats
        time.sleep(4 * timeout)  # e.g. the e-stop confirmed, the record closed
        d2.close()  # node 2 first: node 1 waits longer
        time.sleep(4 * timeout)
        for twin in (t1, t2):
            assert twin.state == "QUICK STOP ACTIVE", twin.history
            assert not twin.controller.watchdog_tripped
        assert "0x8130" not in d1.fault_text()
        # ≈ 8 · timeout / period heartbeats in the wait (half of them on a loaded machine)
        assert t1.controller.stats.heartbeats - n0 >= 0.5 * 8 * timeout / period
        assert d1.arm(1.0) is not None and t1.state == "SWITCHED ON"  # a new run
        n1 = t1.controller.stats.heartbeats
        time.sleep(4 * period)
        assert t1.controller.stats.heartbeats - n1 <= 1  # (the arming one) the steps produce it
        d1.close()


@pytest.mark.timing
def test_a_late_device_on_a_shared_bus_costs_its_own_step_only():
    """Two axes on one bus; node 2's device answers one SYNC 0.45 s late (its thread held), the
    receive waits 0.3 s. Node 2 misses that step only; its late TPDOs, arriving after the next
    SYNC, are that step's feedback by the documented rule (a TPDO after the next SYNC is the
    next step's) and its own answer to that SYNC is then counted twice as a duplicate; every
    later step of both axes is delivered, node 1 never misses, and neither axis files a TPDO
    for the other (the values of each follow its own set-point)."""
    ch = {"channel": "rths-canopen-late-device"}
    with (
        start_twin("canopen", default_plant(), node_id=1, **ch) as t1,
        start_twin("canopen", default_plant(), node_id=2, **ch) as t2,
    ):
        d1, d2 = _open(t1), _open(t2)
        for d in (d1, d2):
            assert d.arm(1.0) is not None
        slow_sync, orig = 12, t2._on_sync

        def late_sync(cob, data, ts):
            if t2.n == slow_sync:
                time.sleep(0.45)
            orig(cob, data, ts)

        t2._on_sync = late_sync
        missed: dict[int, list[int]] = {1: [], 2: []}
        last: dict[int, float] = {}
        for k in range(80):
            d1.send(k, 0.0, True)
            d2.send(k, -0.0005 if k >= 5 else 0.0, True)
            for i, d in ((1, d1), (2, d2)):
                fb = d.receive(0.3)
                if fb is None:
                    missed[i].append(k)
                else:
                    assert fb.seq == k
                    last[i] = fb.displacement
        assert missed[1] == []
        assert len(missed[2]) == 1 and missed[2][0] in (slow_sync, slow_sync + 1), missed
        assert d2.stats.duplicates == 2 and d1.stats.duplicates == 0
        assert d2.stats.received == 79 and d1.stats.received == 80
        # each axis reads its own device: node 2 moved towards -0.5 mm, node 1 stayed at 0
        assert last[2] < -1e-4 and abs(last[1]) < 1e-5
        for d in (d1, d2):
            d.close()


@pytest.mark.timing  # answers read at once
def test_the_sync_goes_with_the_last_axis_rpdo_on_the_bus():
    """The bus sends the step's SYNC as soon as every axis on it has written its RPDO (not at
    the first receive): one axis, with its RPDO; two axes, with the second one's — one SYNC a
    step either way, and an inline twin finds the whole step on the bus when pumped."""
    ch = {"channel": "rths-canopen-sync-rule"}
    with (
        start_twin("canopen", default_plant(), node_id=1, threaded=False, **ch) as t1,
        start_twin("canopen", default_plant(), node_id=2, threaded=False, **ch) as t2,
    ):
        d1 = _open(t1)
        bus = d1._bus
        assert d1.arm(1.0) is not None
        s0 = bus.syncs
        d1.send(0, 0.0, False)
        assert bus.syncs == s0 + 1  # the only axis: its RPDO, then the SYNC
        t1.pump()
        assert d1.receive(0.0) is not None
        assert bus.syncs == s0 + 1  # the receive sent none
        d2 = _open(t2)
        assert d2._bus is bus and d2.arm(1.0) is not None
        s1 = bus.syncs
        d1.send(1, 0.0, False)
        assert bus.syncs == s1  # node 2 has not written its RPDO yet
        d2.send(0, 0.0, False)
        assert bus.syncs == s1 + 1
        for twin, drv in ((t1, d1), (t2, d2)):
            twin.pump()
            assert drv.receive(0.0) is not None
        assert bus.syncs == s1 + 1
        assert t1.n == 2 and t2.n == 1  # SYNCs each device stepped on since it started
        d2.close()
        d1.close()


@pytest.mark.timing  # paced
def test_an_inline_twin_serves_the_steps_on_the_loops_thread(tmp_path, monkeypatch):
    """A paced run of the CiA 402 example as shipped (``twin.inline``): the steps' SYNCs are
    handled on the loop's thread (no hand-off to the twin's thread per step), the SDO writes
    of start-up, arming and close on the twin's own thread."""
    import threading

    from rths_hil.sim_backends.endpoints.canopen import CANopenTwin

    seen: dict[str, list[str]] = {"sync": [], "sdo": []}
    on_sync, on_write = CANopenTwin._on_sync, CANopenTwin._on_write

    def spy_sync(self, *a):
        seen["sync"].append(threading.current_thread().name)
        on_sync(self, *a)

    def spy_write(self, *a, **kw):
        seen["sdo"].append(threading.current_thread().name)
        on_write(self, *a, **kw)

    monkeypatch.setattr(CANopenTwin, "_on_sync", spy_sync)
    monkeypatch.setattr(CANopenTwin, "_on_write", spy_write)
    path = ROOT / "examples" / "controllers" / "cia402.toml"
    r = run_loop(tmp_path / "r", path, "loop.mode=paced", "loop.duration=1")
    assert r.result.status == "completed", r.result.trip
    assert r.loop.channels[0].twin.inline
    main = threading.current_thread().name
    on_main = seen["sync"].count(main)
    assert on_main >= r.result.steps  # every step's SYNC (+ the start and end phases')
    assert len(seen["sync"]) - on_main <= 2  # before the first pump the thread may be first
    assert seen["sdo"] and set(seen["sdo"]) == {"twin-canopen"}


def test_an_answer_that_comes_before_the_sync_call_returns_is_its_steps():
    """Read by a notifier thread (every interface but virtual and SocketCAN), a device's
    TPDOs can arrive before the thread that sent the SYNC runs again. Here they arrive inside
    the SYNC's send (another thread files them, as the notifier would): they must be the
    step's feedback, not a duplicate of the step before it."""
    import threading

    with start_twin("canopen", default_plant(), device_profile="cia402") as twin:
        drv = _open(twin)
        assert drv.arm(1.0) is not None
        bus = drv._bus
        send = bus.send
        counts = [1000]

        def fast_device(msg):
            ok = send(msg)
            if msg.arbitration_id == 0x80:  # the SYNC: TPDO1 (status word, position), TPDO2
                counts[0] += 1

                def answer():
                    drv._tpdo_in(0, (0x0237, counts[0]))
                    drv._tpdo_in(1, (0,))

                t = threading.Thread(target=answer)
                t.start()
                t.join()
            return ok

        bus.send = fast_device
        try:
            for k in range(5):
                drv.send(k, 0.0, False)
                fb = drv.receive(1.0)
                assert fb is not None and fb.seq == k
                assert fb.displacement == counts[0] / drv.counts_per_m  # the fast answer
        finally:
            bus.send = send
        drv.close()


def _error_field(drv) -> int:
    """0x1003:1's error code read by SDO (the driver reads the bus only in its SDO phases)."""
    drv._listen(True)
    try:
        return drv._sdo_read(0x1003, 1) & 0xFFFF
    finally:
        drv._listen(False)


@pytest.mark.timing
def test_arming_tells_a_heartbeat_fault_from_a_device_fault_by_the_error_field():
    """A new bridge finds the device in FAULT: from the pre-defined error field 0x1003 it tells
    the heartbeat consumer's fault (the bridge before it stopped: EMCY 0x8130, reported as the
    latched watchdog that arming acknowledges) from a fault of the device itself (a following
    error, EMCY 0x8611: FAULT, which the loop refuses to start on)."""
    faults = Faults.parse("runaway_from=20; runaway_rate=0.5")
    with start_twin("canopen", default_plant(), faults=faults, heartbeat_timeout=0.25) as twin:
        first = _open(twin)
        assert first.arm(1.0) is not None
        for k in range(60):
            first.send(k, 0.0, True)
            first.receive(0.5)
        assert twin.state == "FAULT" and twin.history.count("FAULT") == 1
        first._shutdown_network()  # the bridge gone without a word (no disable, no NMT stop)
        second = _open(twin)
        assert _error_field(second) == EMCY_FOLLOWING_ERROR
        fb = second.arm(1.0)
        assert fb.status & FAULT and not fb.status & int(Status.WATCHDOG)
        assert twin.state == "SWITCHED ON"  # reset all the same: the loop refuses to start
        second.close()

    with start_twin("canopen", default_plant(), heartbeat_timeout=0.25) as twin:
        first = _open(twin, heartbeat_period=0.02)
        assert first.arm(1.0) is not None
        for k in range(20):
            first.send(k, 0.0, True)
            assert first.receive(0.5) is not None
        first._shutdown_network()
        t0 = time.monotonic()
        while twin.state != "FAULT" and time.monotonic() - t0 < 2.0:
            time.sleep(0.01)
        second = _open(twin)
        assert _error_field(second) == 0x8130
        fb = second.arm(1.0)
        assert fb.status & ESTOP and fb.status & int(Status.WATCHDOG)
        assert not fb.status & FAULT
        second.close()

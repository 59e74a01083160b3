"""OpenFresco-compatible experimental site: protocol, mapping, timing, and the real client.

The OpenSees tests run examples/opensees/two_storey.py (OpenSeesPy's genericClient) in a
subprocess against the bridge's full chain — CAN driver ⇄ twin, compensation, FEI, safety,
crash-safe record — and compare with the same OpenSees model whose damper is a numerical
element (zeroLength elastic + viscous).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time

import numpy as np
import pytest

import tests.helpers.opensees_site as S
from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.hybrid import RTHSLoop
from rths_hil.metrics import j2_nrms
from rths_hil.openfresco import protocol as P
from rths_hil.openfresco.server import Mailbox, Target
from rths_hil.openfresco.site import Mapping
from rths_hil.openfresco.timing import (
    CORRECTED,
    EXECUTED,
    HELD,
    IDLE,
    KINDS,
    PREDICTED,
    Lockstep,
    PredictorCorrector,
    SiteFault,
)
from rths_hil.records.recorder import read_run
from tests.helpers.openfresco import GENERIC_CLIENT_ID, _client, _frame, _loop, _recv

# The lockstep site (OpenSeesPy as another process) waits for each trial as long as it takes:
# those tests run with the parallel tests. The paced ones (ramp-hold, predictor-corrector in
# real time) run apart from them, one at a time (the "timing" marker, pyproject.toml; make test).
timing = pytest.mark.timing

# ---------------------------------------------------------------------------------------------
# protocol and mapping


def _gc_id() -> bytes:
    return P.client_id(GENERIC_CLIENT_ID[:5], GENERIC_CLIENT_ID[5:10])


def test_genericclient_id_parses_and_lays_out_the_blocks():
    ses = P.SessionID.parse(
        P.client_id(GENERIC_CLIENT_ID[:5], GENERIC_CLIENT_ID[5:10]), "elem-server"
    )
    assert ses.nb == 2 and ses.data_size == 256 and ses.frame_bytes == 2048
    assert ses.ctrl_offsets() == {
        "disp": slice(1, 3),
        "vel": slice(3, 5),
        "accel": slice(5, 7),
        "time": slice(7, 8),
    }
    assert ses.daq_offsets() == {"force": slice(0, 2)}


@pytest.mark.parametrize(
    ("ints", "protocol", "words"),
    [
        ((2, 2, 2, 0, 1, 0, 0, 0, 2, 0, 3), "elem-server", "dataSize 3 is smaller"),
        ((1, 0, 0, 0, 0, 1, 0, 0, 1, 0, 256), "elem-server", "not an OpenSees genericClient"),
        ((2, 2, 2, 0, 1, 0, 0, 0, 2, 0, -5), "elem-server", "negative"),
        ((2, 2, 2, 0, 1, 0, 0, 0, 2, 0, 1 << 30), "elem-server", "outside"),
        ((0, 0, 0, 0, 0, 1, 0, 0, 1, 0, 256), "generic-tcp", "must control displacements"),
        ((1, 0, 0, 0, 0, 3, 0, 0, 1, 0, 256), "generic-tcp", "DAQ disp size 3"),
    ],
)
def test_wrong_ids_give_one_line(ints, protocol, words):
    raw = np.asarray(ints, dtype=P.ID_DTYPE).tobytes()
    with pytest.raises(InputError) as exc:
        P.SessionID.parse(raw, protocol)
    msg = str(exc.value)
    assert words in msg and "\n" not in msg


def test_basic_system_mapping_and_matrix_replies():
    m = Mapping(1, None, [1.19e6], [], [])
    m.bind(
        P.SessionID.parse(
            P.client_id(GENERIC_CLIENT_ID[:5], GENERIC_CLIENT_ID[5:10]), "elem-server"
        )
    )
    np.testing.assert_array_equal(m.T, [[-1.0, 1.0]])
    assert m.to_actuators(np.array([0.002, 0.005]))[0] == pytest.approx(0.003)  # u2 − u1
    np.testing.assert_allclose(m.to_dofs(np.array([10.0])), [-10.0, 10.0])  # (−F, +F)
    K = m.matrix(P.GET_TANGENT_STIFF)
    np.testing.assert_allclose(K, 1.19e6 * np.array([[1.0, -1.0], [-1.0, 1.0]]))
    np.testing.assert_array_equal(m.matrix(P.GET_DAMP), np.zeros((2, 2)))
    # displacement reply: the trial corrected by the measurement (minimum norm)
    u = m.dofs_from_measured(np.array([0.0, 0.003]), np.array([0.0029]))
    assert u[1] - u[0] == pytest.approx(0.0029)


def test_default_mapping_of_several_actuators():
    """n actuators: n + 1 element DOFs → the basic system of n elements in series; n DOFs →
    actuator i on element DOF i; anything else needs openfresco.transform."""

    def ses(nb):
        return P.SessionID.parse(P.client_id((nb, nb, nb, 0, 1), (0, 0, 0, nb, 0)), "elem-server")

    m = Mapping(2, None, [1.0e6, 2.0e6])
    m.bind(ses(3))
    np.testing.assert_array_equal(m.T, [[-1.0, 1.0, 0.0], [0.0, -1.0, 1.0]])
    np.testing.assert_allclose(m.to_actuators(np.array([1.0, 3.0, 6.0])), [2.0, 3.0])
    # forces of two elements in series: (−f1, f1 − f2, f2)
    np.testing.assert_allclose(m.to_dofs(np.array([10.0, 4.0])), [-10.0, 6.0, 4.0])
    np.testing.assert_allclose(
        m.matrix(P.GET_TANGENT_STIFF), [[1e6, -1e6, 0], [-1e6, 3e6, -2e6], [0, -2e6, 2e6]]
    )
    m.bind(ses(2))
    np.testing.assert_array_equal(m.T, np.eye(2))
    with pytest.raises(InputError, match=r"give openfresco\.transform"):
        m.bind(ses(4))


def test_site_channels_default_to_their_own_dof_and_record_the_site_columns(tmp_path):
    """Without dof/transform, channel i of an openfresco site is on site DOF i; the record
    gets of_kind and of_latency after the other columns (and only for a site)."""
    from rths_hil.hybrid.plan import build_plan

    plan = build_plan(load_config(S.SITE_TWO, ["openfresco.port=0"]), tmp_path / "plan")
    np.testing.assert_array_equal(plan.transform, np.eye(2))
    names = [c[0] for c in plan.columns]
    assert names[-2:] == ["of_kind", "of_latency"] and names[-4:-2] == ["u_1", "u_2"]
    other = build_plan(load_config(S.ROOT / "examples" / "can.toml"), tmp_path / "other")
    assert not any(c[0].startswith("of_") for c in other.columns)


def test_transform_rows_are_checked():
    with pytest.raises(InputError, match="rows"):
        Mapping(2, [1.0, -1.0, 0.5])  # 3 values are not 2 rows
    m = Mapping(2, [-1, 1, 0, 0, -1, 1], [1e6, 2e6])
    ses = P.SessionID.parse(P.client_id((3, 3, 3, 0, 1), (0, 0, 0, 3, 0)), "elem-server")
    m.bind(ses)
    np.testing.assert_allclose(m.to_actuators(np.array([1.0, 3.0, 6.0])), [2.0, 3.0])
    with pytest.raises(InputError, match="4 DOFs"):
        m.bind(P.SessionID.parse(P.client_id((4, 4, 4, 0, 1), (0, 0, 0, 4, 0)), "elem-server"))


# ---------------------------------------------------------------------------------------------
# timing modes against a scripted mailbox (the server's side of the handshake)


def _drive(timing, f, k_sub, n_targets, late_every=0, late_by=0, dt=1 / 1024):
    """Post the next target (time (seq)·k_sub·dt, displacement f(t)) once the previous force
    was returned — at once, or ``late_by`` steps late every ``late_every`` targets."""
    mb = timing.mb
    cmds, seq, hold = [], 0, 0
    k = 0
    while seq < n_targets or mb.reply_seq < seq:
        if mb.reply_seq == seq and seq < n_targets:
            if late_every and seq and seq % late_every == 0 and hold < late_by:
                hold += 1
            else:
                hold = 0
                seq += 1
                t = seq * k_sub * dt
                mb.target = Target(seq, np.array([f(t)]), None, t, time.perf_counter())
        c = timing.step(k, timing.cmd.copy(), np.zeros(1))
        cmds.append(float(c[0]))
        k += 1
        assert k < 50 * n_targets * k_sub
    return np.array(cmds)


def test_predictor_corrector_is_exact_on_a_quadratic_path():
    dt = 1 / 1024
    timing = PredictorCorrector(Mailbox(), 1, dt, order=2)

    def f(t):
        return 0.01 + 0.3 * t - 2.0 * t * t

    cmds = _drive(timing, lambda t: f(t) - f(0.0) if t > 0 else 0.0, 4, 40)
    # from the third target on the predictor's parabola is the path itself: command = f(τ)
    tau = np.arange(1, len(cmds) + 1) * dt
    exact = f(tau) - f(0.0)
    np.testing.assert_allclose(cmds[16:], exact[16:], rtol=0, atol=1e-12)
    assert timing.kinds.count(EXECUTED) == 40  # each target hit on time, exactly
    assert len(timing.targets) == 40


def test_predictor_corrector_slows_smoothly_when_late_and_faults_past_the_bound():
    dt = 1 / 1024

    def f(t):
        return 0.005 * math.sin(2 * math.pi * 1.0 * t)

    timing = PredictorCorrector(Mailbox(), 1, dt, order=2, hold_after=0.01, estop_after=0.2)
    cmds = _drive(timing, f, 4, 60, late_every=10, late_by=30)
    assert HELD in timing.kinds
    # no jump, no spike: the command's speed changes by at most a quarter of the path's
    # top speed per step (a stall from full speed takes ≥ 4 steps)
    v_path = 2 * math.pi * 0.005 * dt
    assert np.abs(np.diff(cmds)).max() < 1.05 * v_path
    assert np.abs(np.diff(cmds, 2)).max() < 0.25 * v_path
    # the command never runs ahead of the path's amplitude
    assert np.abs(cmds).max() < 0.0051
    stalled = PredictorCorrector(Mailbox(), 1, dt, order=2, hold_after=0.01, estop_after=0.05)
    with pytest.raises(SiteFault, match="late with its next trial"):
        _drive(stalled, f, 4, 20, late_every=5, late_by=10_000)


def test_lockstep_hermite_ramp_is_exact_on_a_straight_path():
    """Lockstep blocks in step() until the next trial: the client is a thread here."""
    dt = 1 / 1024
    mb = Mailbox()
    timing = Lockstep(mb, 1, dt, start_timeout=5, client_timeout=5)

    def client():
        for seq in range(1, 11):
            t = seq * 4 * dt
            with mb.cond:
                mb.target = Target(seq, np.array([0.02 * t]), None, t, time.perf_counter())
                mb.cond.notify_all()
                while mb.reply_seq < seq:
                    mb.cond.wait(5)
        mb.close("die", fault=False)

    threading.Thread(target=client, daemon=True).start()
    cmds, k = [], 0
    while (c := timing.step(k, timing.cmd.copy(), np.zeros(1))) is not None:
        cmds.append(float(c[0]))
        k += 1
    assert len(cmds) == 40 and timing.kind_counts()["executed"] == 40
    np.testing.assert_allclose(cmds, 0.02 * dt * np.arange(1, 41), atol=1e-15)


# ---------------------------------------------------------------------------------------------
# the whole chain with a scripted client (no OpenSees): flavours and faults


def test_generic_tcp_flavour_round_trip(tmp_path):
    """OpenFresco's expControl GenericTCP: ID, then 3 (ctrl disp), 6 (DAQ disp+force), 99."""
    replies = []

    def script(s):
        for i in range(1, 6):
            d = 0.001 * i
            s.sendall(_frame(256, P.SET_TRIAL, d))
            s.sendall(_frame(256, P.GET_DAQ))
            replies.append(_recv(s, 256)[:2].copy())
        s.sendall(_frame(256, P.DIE))

    loop, port = _loop(
        tmp_path, "gtcp", "openfresco.protocol=generic-tcp", "openfresco.ramp_time=0.25s"
    )
    th = _client(port, (1, 0, 0, 0, 0, 1, 0, 0, 1, 0, 256), script)
    result = loop.run()
    th.join(5)
    assert result.status == "completed"
    assert len(replies) == 5
    for i, (disp, force) in enumerate(replies, start=1):
        assert disp == pytest.approx(0.001 * i, rel=1e-6)  # ideal actuator: measured = trial
        # Kelvin–Voigt specimen k·d + c·v: the path runs at 1 mm per 0.25 s ramp (no time
        # block: openfresco.ramp_time), v = 4 mm/s; CAN carries the force in 0.5 N steps
        assert force == pytest.approx(1.19e6 * 0.001 * i + 2.0e3 * 0.004, abs=0.5)
    summary = loop.structure.summary()
    assert summary["actions"]["getDaqResponse"] == 5


@timing
def test_ramp_hold_executes_each_trial_in_real_time(tmp_path):
    """ramp-hold (paced loop): ramp 50 ms, hold 20 ms, then the force; hold while waiting."""
    forces, t_req = [], []

    def script(s):
        for i in range(1, 4):
            s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001 * i, 0, 0, 0, 0, i / 256))
            t0 = time.perf_counter()
            s.sendall(_frame(256, P.GET_FORCE))
            forces.append(_recv(s, 256)[:2].copy())
            t_req.append(time.perf_counter() - t0)
            s.sendall(_frame(256, P.COMMIT))
        s.sendall(_frame(256, P.DIE))

    loop, port = _loop(
        tmp_path,
        "ramphold",
        "openfresco.timing=ramp-hold",
        "openfresco.ramp_time=50ms",
        "openfresco.hold_time=20ms",
        "safety.max_overruns=1000000",
        "fei.exact_hop=0",  # no exact-FEI worker process to start for a 0.3 s run
    )
    th = _client(port, GENERIC_CLIENT_ID, script)
    result = loop.run()
    th.join(5)
    assert result.status == "completed" and result.mode == "paced", result.trip
    for i, f in enumerate(forces, start=1):
        # held still for 20 ms: the dashpot is at rest, the force is k·(u2 − u1) as (−F, +F)
        assert f[1] == pytest.approx(1.19e6 * 0.001 * i, abs=0.5) and f[0] == -f[1]
    assert min(t_req) >= 0.065  # 70 ms of ramp and hold in real time (one step of slack)
    kinds = loop.structure.summary()["kinds"]
    assert kinds["executed"] == 3 * (51 + 20) and kinds["held"] > 0


def test_wrong_id_is_one_line_at_start_up(tmp_path):
    loop, port = _loop(tmp_path, "badid")
    _client(port, (7, 7, 7, 7, 7, 7, 7, 7, 7, 7, 7), lambda s: time.sleep(1))
    with pytest.raises(InputError) as exc:
        loop.run()
    msg = str(exc.value)
    assert "not an OpenSees genericClient" in msg and "\n" not in msg


@pytest.mark.parametrize("fault", ["short_frame", "disconnect"])
def test_frame_of_wrong_size_or_disconnect_trips_and_keeps_the_record(tmp_path, fault):
    def script(s):
        for i in range(1, 4):  # three good steps
            t = i / 256
            s.sendall(_frame(256, P.SET_TRIAL, 0.0, 0.001 * i, 0, 0, 0, 0, t))
            s.sendall(_frame(256, P.GET_FORCE))
            _recv(s, 256)
            s.sendall(_frame(256, P.COMMIT))
        if fault == "short_frame":
            s.sendall(_frame(100, P.SET_TRIAL, 0.0, 0.004, 0, 0, 0, 0, 4 / 256))
            time.sleep(2.0)  # then waits, as a client expecting no reply would

    loop, port = _loop(tmp_path, fault)
    _client(port, GENERIC_CLIENT_ID, script)
    result = loop.run()
    assert result.status == "trip" and result.exit_code == 3
    assert result.trip.rule == "openfresco"
    reason = result.trip.reason
    assert "\n" not in reason
    if fault == "short_frame":
        assert "frame of 800 bytes, expected 2048" in reason
    else:
        assert "disconnected mid-test" in reason
    rec = read_run(tmp_path / fault)
    assert len(rec.record) == result.steps  # every step up to the trip is on disk
    assert np.isfinite(rec.record["of_latency"]).sum() == 2  # trials 2 and 3 (1 has none)
    assert rec.record["measured"][-1] == pytest.approx(0.003, rel=1e-6)  # the actuator held
    assert any(e["kind"] == "estop" for e in rec.events)


# ---------------------------------------------------------------------------------------------
# the real client: OpenSeesPy's genericClient


@pytest.fixture(scope="module")
def accel(tmp_path_factory):
    return S.write_accel(tmp_path_factory.mktemp("gm") / "accel.txt")


@pytest.mark.parametrize("model", ["sdof", "frame"])
def test_lockstep_equals_the_numerical_model(tmp_path, accel, model):
    """Issue test 1: genericClient served by the site (ideal actuator, linear specimen) =
    the same model with the specimen as zeroLength elastic + viscous, within 0.5 % NRMS."""
    dt, dur = 1 / 256, 5.0
    ref = S.reference(tmp_path, model, dt, dur, accel)
    result, stage, floors, proc = S.hybrid(tmp_path, S.SITE, model, dt, dur, accel, name=model)
    assert result.status == "completed", result.trip
    assert proc.returncode == 0, proc.stderr
    assert floors.shape == ref.shape
    for j in range(1, ref.shape[1]):
        nrms = j2_nrms(ref[:, j], floors[:, j])
        print(f"{model} floor {j}: NRMS {nrms:.3f} %")
        assert nrms <= 0.5
    s = stage.summary()
    n = round(dur / dt)
    assert s["actions"]["getForce"] == n and s["actions"]["DIE"] == 1
    assert s["kinds"]["executed"] == result.steps - 1  # every loop step ramps a trial
    # the record's site columns: row 0's target is the rest before any trial, every later
    # one a ramp toward a trial; a latency in each step a trial arrived (but the first)
    rec = read_run(tmp_path / model).record
    assert rec["of_kind"][0] == IDLE and np.all(rec["of_kind"][1:] == EXECUTED)
    lat = rec["of_latency"]
    assert np.isfinite(lat).sum() == n - 1 and np.nanmin(lat) > 0
    assert np.all(np.isfinite(lat[rec["step"] % 4 == 0][1:n]))  # 4 loop steps per trial


def test_two_channels_in_lockstep_equal_the_numerical_model(tmp_path, accel):
    """Both storey dampers as one genericClient of three DOFs, two channels (the site's
    default mapping: channel i = u_{i+1} − u_i, on site DOF i): each floor within 0.5 % NRMS
    of the model with both dampers numerical."""
    dt, dur = 1 / 256, 5.0
    ref = S.reference(tmp_path, "frame", dt, dur, accel, "--dampers", "2")
    result, stage, floors, proc = S.hybrid(
        tmp_path, S.SITE_TWO, "frame", dt, dur, accel, extra=("--dampers", "2"), name="two"
    )
    assert result.status == "completed", result.trip
    assert proc.returncode == 0
    np.testing.assert_array_equal(stage.site.mapping.T, [[-1, 1, 0], [0, -1, 1]])
    for j in (1, 2):
        nrms = j2_nrms(ref[:, j], floors[:, j])
        print(f"two channels, floor {j}: NRMS {nrms:.3f} %")
        assert nrms <= 0.5
    rec = read_run(tmp_path / "two").record
    # each channel drove its own storey's drift: the twins' specimens (1.19 and 0.8 MN/m)
    # would give other forces on the other storey
    drift = np.diff(np.column_stack([np.zeros(len(floors)), floors[:, 1:]]), axis=1)
    for i, name in enumerate(("storey1", "storey2")):
        assert np.abs(rec[f"measured_{name}"]).max() == pytest.approx(
            np.abs(drift[:, i]).max(), rel=0.01
        )
    k = (1.19e6, 0.8e6)
    for i, name in enumerate(("storey1", "storey2")):
        f, d = rec[f"force_{name}"], rec[f"measured_{name}"]
        assert np.polyfit(d, f, 1)[0] == pytest.approx(k[i], rel=0.02)
    assert np.all(rec["of_kind"][1:] == EXECUTED)
    assert np.isfinite(rec["of_latency"]).sum() == round(dur / dt) - 1


@timing
@pytest.mark.parametrize("dt", [1 / 1024, 1 / 256])
def test_real_time_with_a_20ms_actuator(tmp_path, accel, dt):
    """Issue test 2: paced 1024 Hz loop, twin with a 20 ms delay, compensation on,
    predictor–corrector; NRMS ≤ 3 %, OpenSees' latency recorded, no e-stop.

    The loop's own overrun rule (site_realtime.toml: 64 consecutive late steps) is relaxed:
    on a 2-core machine shared with other work the paced loop and OpenSees' process compete
    for the CPUs, and runs of late steps longer than 64 happen (measured at a load of 8–11
    on two cores, three runs: the longest run of consecutive overruns 20, 28 and 1908 steps
    at element step 1/1024 s, 2, 23 and 78 at 1/256 s) while tracking stays within 1 % NRMS.
    What this test checks is the site, not the machine's real-time capability
    (benchmarks/bench_loop.py measures that)."""
    # 2 s of El Centro, its first strong pulses: NRMS 0.35–0.40 % here, a tenth of the bound
    dur = 2.0
    ref = S.reference(tmp_path, "frame", dt, dur, accel)
    result, _, floors, _ = S.hybrid(
        tmp_path,
        S.SITE_RT,
        "frame",
        dt,
        dur,
        accel,
        # overruns: see the docstring; a late OpenSees (a busy machine) holds, not e-stops
        overrides=("safety.max_overruns=1000000", "openfresco.estop_after=1s"),
        name=f"rt{round(1 / dt)}",
    )
    assert result.status == "completed", result.trip
    for j in range(1, ref.shape[1]):
        nrms = j2_nrms(ref[:, j], floors[:, j])
        print(f"real time 1/{round(1 / dt)} s, floor {j}: NRMS {nrms:.2f} %")
        assert nrms <= 3.0
    rec = read_run(tmp_path / f"rt{round(1 / dt)}").record
    lat = rec["of_latency"][np.isfinite(rec["of_latency"])]
    assert lat.size >= round(dur / dt) - 1  # one per OpenSees step (the first has none)
    assert lat.max() > 0
    kinds = np.bincount(rec["of_kind"], minlength=5)
    assert kinds[EXECUTED] + kinds[CORRECTED] > 0 and kinds[PREDICTED] > 0
    print(
        f"latency p50 {np.median(lat) * 1e3:.2f} ms, max {lat.max() * 1e3:.1f} ms; "
        f"overruns {result.overruns} (longest run {_longest_run(result)} steps); kinds "
        f"{ {KINDS[i]: int(kinds[i]) for i in KINDS} }"
    )


def _longest_run(result) -> int:
    """The longest run of consecutive overruns (what safety.max_overruns bounds)."""
    over = result.lateness > result.overrun_threshold
    best = cur = 0
    for o in over:
        cur = cur + 1 if o else 0
        best = max(best, cur)
    return best


def test_opensees_killed_mid_test_trips_with_one_line(tmp_path, accel):
    """Issue test 3 with the real client: the OpenSees process dies mid-analysis."""
    from rths_hil.config import load_config as _load

    cfg = _load(S.SITE, ["openfresco.port=0", "output.plot=false"])
    loop = RTHSLoop(cfg, tmp_path / "killed")
    _, port = loop.structure.listen()
    import subprocess

    proc = subprocess.Popen(
        [*S.opensees_args("frame", 1 / 256, 20.0, accel), "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )

    def kill_later():  # once OpenSees is 100 steps into its analysis
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            tm = loop.structure.site.timing
            if tm is not None and len(tm.targets) >= 100:
                break
            time.sleep(0.01)
        proc.kill()

    threading.Thread(target=kill_later, daemon=True).start()
    result = loop.run()
    proc.wait(10)
    assert result.status == "trip" and result.exit_code == 3
    assert result.trip.rule == "openfresco"
    assert "disconnected mid-test" in result.trip.reason
    rec = read_run(tmp_path / "killed")
    assert len(rec.record) == result.steps > 400  # ≥ 100 OpenSees steps of 4 loop steps
    # the site's columns are part of each row: on disk up to the trip like the rest
    assert np.all(rec.record["of_kind"][1:] == EXECUTED)
    assert np.isfinite(rec.record["of_latency"]).sum() >= 99
    assert any(e["kind"] == "estop" for e in rec.events)


# ---------------------------------------------------------------------------------------------
# OpenSees pitfalls: iterations on the specimen, a time step that is not whole loop periods


def test_newton_iterations_stop_before_the_second_trial_moves_the_actuator(tmp_path, accel):
    """Implicit Newmark + Newton (OpenSees' usual default) sends several trials per step, each
    of which would be imposed on the specimen: the site stops at the second trial of the first
    step, with one line naming the fix, and only the first trial was ever executed."""
    result, stage, _, _ = S.hybrid(
        tmp_path, S.SITE, "sdof", 1 / 256, 1.0, accel,
        extra=("--integrator", "Newmark", "--algorithm", "Newton"), name="newton",
    )  # fmt: skip
    assert result.status == "trip" and result.exit_code == 3
    assert result.trip.rule == "openfresco"
    reason = result.trip.reason
    assert "trial 2 of one time step (t = 0.00390625 s)" in reason, reason
    assert "NewmarkExplicit" in reason and "Linear" in reason and "\n" not in reason
    tm = stage.site.timing
    assert len(tm.targets) == 1  # the iteration never became a target
    first = stage.site.server.mailbox.target  # the last target posted: the first trial
    assert first.seq == 1
    rec = read_run(tmp_path / "newton").record
    # every command lies on the ramp from rest to the first trial, none beyond it
    peak = float(np.abs(rec["command"]).max())
    assert peak <= abs(float(first.displacement[0])) * (1 + 1e-12)
    assert len(rec) <= 4 + 2  # one OpenSees step of 4 loop steps, then the trip


def test_newmark_explicit_and_linear_is_one_trial_per_step(tmp_path, accel):
    """The fix the message names: NewmarkExplicit + Linear sends one trial per step."""
    result, stage, _, _ = S.hybrid(
        tmp_path, S.SITE, "sdof", 1 / 256, 0.5, accel,
        extra=("--integrator", "NewmarkExplicit", "--algorithm", "Linear"), name="explicit",
    )  # fmt: skip
    assert result.status == "completed", result.trip
    s = stage.summary()
    assert s["targets"] == s["actions"]["commitState"] == 128


def test_opensees_dt_not_whole_loop_periods_is_refused(tmp_path, accel):
    """dt = 0.005 s at loop.fs = 1024 Hz is 5.12 loop periods: refused before the first trial
    moves the actuator, naming loop.fs = 1000 Hz and dt = 5/1024 s; at 1000 Hz it runs and
    equals the numerical model."""
    result, stage, _, _ = S.hybrid(tmp_path, S.SITE, "sdof", 0.005, 1.0, accel, name="dt1024")
    assert result.status == "trip" and result.trip.rule == "openfresco"
    reason = result.trip.reason
    assert "0.005 s is 5.120 loop periods at loop.fs = 1024 Hz" in reason, reason
    assert "-2.3 %" in reason and "loop.fs = 1000 Hz" in reason
    assert "dt of 0.0048828125 s" in reason
    assert len(stage.site.timing.targets) == 0
    ref = S.reference(tmp_path, "sdof", 0.005, 3.0, accel)
    result, _, floors, _ = S.hybrid(
        tmp_path, S.SITE, "sdof", 0.005, 3.0, accel, overrides=("loop.fs=1000",), name="dt1000"
    )
    assert result.status == "completed", result.trip
    assert j2_nrms(ref[:, 1], floors[:, 1]) <= 0.5


def test_dt_rule_and_element_dt_at_start_up():
    from rths_hil.openfresco.server import _dt_fault
    from rths_hil.openfresco.site import ExperimentalSite

    dt = 1 / 1024
    assert _dt_fault(4 / 1024, dt) is None
    assert _dt_fault(4 / 1024 * (1 + 0.9e-3), dt) is None  # within 0.1 %
    assert _dt_fault(4 / 1024 * (1 + 1.1e-3), dt) is not None
    assert "loop.fs = 1000 Hz" in _dt_fault(0.01, dt)  # 10.24 periods → 10 at 1000 Hz
    with pytest.raises(InputError, match=r"openfresco.element_dt 0.005 s is 5.120 loop periods"):
        ExperimentalSite({"element_dt": 0.005, "timing": "predictor-corrector"}, dt)
    ExperimentalSite({"element_dt": 0.005, "timing": "ramp-hold"}, dt)  # its own ramp time
    # the timing's own trial limit: 1 (lockstep, ramp-hold), none (predictor–corrector)
    assert ExperimentalSite({"timing": "lockstep"}, dt).max_trials == 1
    assert ExperimentalSite({"timing": "predictor-corrector"}, dt).max_trials == 0
    assert ExperimentalSite({"timing": "ramp-hold", "max_trials_per_step": 0}, dt).max_trials == 0


def test_a_second_trial_before_commit_without_time_block_stops(tmp_path):
    """A GenericTCP client without a time block: trials are counted between commitState
    requests; the second one of a step stops the site before it is executed."""
    replies = []

    def script(s):
        s.sendall(_frame(256, P.SET_TRIAL, 0.001))
        s.sendall(_frame(256, P.GET_DAQ))
        replies.append(_recv(s, 256)[:2].copy())
        s.sendall(_frame(256, P.COMMIT))
        s.sendall(_frame(256, P.SET_TRIAL, 0.002))
        s.sendall(_frame(256, P.GET_DAQ))
        replies.append(_recv(s, 256)[:2].copy())
        s.sendall(_frame(256, P.SET_TRIAL, 0.0025))  # an iteration: no commit in between
        s.sendall(_frame(256, P.GET_DAQ))
        with contextlib.suppress(AssertionError, OSError):
            _recv(s, 256)

    loop, port = _loop(
        tmp_path, "iter", "openfresco.protocol=generic-tcp", "openfresco.ramp_time=0.05s"
    )
    th = _client(port, (1, 0, 0, 0, 0, 1, 0, 0, 1, 0, 256), script)
    result = loop.run()
    th.join(5)
    assert result.status == "trip" and "before its commitState" in result.trip.reason
    assert len(replies) == 2 and len(loop.structure.site.timing.targets) == 2
    rec = read_run(tmp_path / "iter").record
    assert float(rec["command"].max()) <= 0.002 * (1 + 1e-12)  # 2.5 mm was never commanded

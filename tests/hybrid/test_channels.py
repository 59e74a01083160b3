"""Several actuators in one test: channels on an MDOF structure.

End to end in lockstep through the real drivers and twins (CAN nodes on one virtual bus, CAN +
Modbus TCP), the structure wiring against the offline MDOF integrator, a fault on one channel
stopping every channel, kill -9 of a paced two-channel run, and one-line config errors.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rths_hil.cli import main as cli
from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import COLUMNS, read_run
from tests.helpers.loop import run_loop

ROOT = Path(__file__).resolve().parents[2]
TWO = ROOT / "examples" / "two_actuators.toml"
MIXED = ROOT / "examples" / "mixed_drivers.toml"


def _run(tmp_path, path, name, overrides=(), duration=10.0, **kw):
    mode = kw.pop("mode", "lockstep")
    r = run_loop(tmp_path / name, path, *overrides, mode=mode, duration=duration, **kw)
    return r.loop, r.result, r.run


def _median_delay(rec, sfx: str) -> float:
    v = rec["fei_valid" + sfx]
    assert v.sum() > 2000
    return float(np.median(rec["fei_delay" + sfx][v]))


@pytest.mark.parametrize("path", [TWO, MIXED], ids=["can+can", "can+modbus"])
def test_two_actuators_fei_delay_per_channel_with_and_without_compensation(tmp_path, path):
    """The issue's acceptance: compensated ≈ 0 ms, uncompensated ≈ the twin's delay (±1 ms)."""
    loop, res, run = _run(tmp_path, path, "on")
    assert res.status == "completed" and res.steps == 10240 and res.missed_replies == 0
    rec = run.record
    assert abs(_median_delay(rec, "_storey1")) < 1e-3
    assert abs(_median_delay(rec, "_storey3")) < 1e-3
    # both twins stepped once per step, the CAN nodes on one bus each got their own frames
    for ch in loop.channels:
        assert ch.twin.stats.steps == res.steps and ch.driver.stats.malformed == 0
    if path == TWO:
        assert [c.driver.node for c in loop.channels] == [1, 2]
        assert loop.channels[0].driver._bus is loop.channels[1].driver._bus  # one shared bus
    else:
        assert [c.plan.driver_name for c in loop.channels] == ["can", "modbus"]
    # per-channel reply times and the skew between them are recorded
    assert np.all(rec["feedback_time_storey1"] > 0) and np.all(rec["feedback_time_storey3"] > 0)
    assert np.all(rec["skew"] >= 0)

    _, res, run = _run(tmp_path, path, "off", ["compensation.enabled=false"])
    assert res.status == "completed"
    assert abs(_median_delay(run.record, "_storey1") - 0.010) < 1e-3
    assert abs(_median_delay(run.record, "_storey3") - 0.020) < 1e-3


def test_record_columns_by_channel_and_dof(tmp_path):
    _, _, run = _run(tmp_path, TWO, "r", duration=0.5)
    names = run.record.dtype.names
    for base in ("target", "command", "measured", "force", "fei_delay", "kf_gain", "feedback_ok"):
        assert f"{base}_storey1" in names and f"{base}_storey3" in names and base not in names
    assert ("u_1", "u_2", "u_3") == names[-3:]
    # the inter-storey actuator's target is T·u with T = [0, -1, 1]
    rec = run.record
    np.testing.assert_allclose(rec["target_storey3"], rec["u_3"] - rec["u_2"], atol=1e-15)
    np.testing.assert_allclose(rec["target_storey1"], rec["u_1"], atol=0)
    meta = [c["name"] for c in run.meta["channels"]]
    assert meta == ["storey1", "storey3"]


def test_single_actuator_record_keeps_todays_columns(tmp_path):
    cfg = load_config(None, ["loop.console=0", "output.plot=false"])
    RTHSLoop(cfg, tmp_path / "r", mode="lockstep", duration=0.2).run()
    names = read_run(tmp_path / "r").record.dtype.names
    assert names[: len(COLUMNS)] == tuple(c[0] for c in COLUMNS)
    assert names[len(COLUMNS) :] == ("feedback_time", "fei_exact_step", "stability")


def test_structure_targets_equal_the_offline_mdof_integration(tmp_path):
    """The runner's wiring (ag indexing, Tᵀ·f, T·u) against rths_hil.structures.mdof run offline.

    Specimens of zero stiffness and no force noise: the structure then moves exactly as the
    offline CR integration of the same model (whose accuracy against modal superposition with
    scipy.signal is tests/structure/test_mdof.py's).
    """
    from rths_hil.hybrid.substructure import build_ground_motion, build_model
    from rths_hil.structures.mdof import simulate_mdof

    over = [
        "twin.specimen={stiffness=0.0, damping=0.0}",
        "twin.sensor={displacement_noise=0.0, force_noise=0.0, seed=0}",
        "structure.k_specimen=0",
    ]
    _, res, run = _run(tmp_path, TWO, "r", over, duration=6.0)
    assert res.status == "completed"
    cfg = load_config(TWO, over)
    ag = build_ground_motion(cfg).accel[: res.steps]
    ref = simulate_mdof(build_model(cfg), ag, cfg["loop"]["fs"])
    u = np.column_stack([run.record[f"u_{i}"] for i in (1, 2, 3)])
    np.testing.assert_allclose(u, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.abs(ref).max() > 5e-3  # a real response, not rest


def _delay_jump_plant(dt: float, k_jump: int):
    from rths_hil.sim_backends.delay import DelayGain

    class Jump:
        """A pure delay of 20 ms that grows to 60 ms over 0.25 s from step ``k_jump`` (a cross-fade:
        a step change of delay would be a step of position, which the velocity rule catches
        first), on a 1 MN/m spring."""

        def __init__(self) -> None:
            self.dt = dt
            self.a = DelayGain(0.020, 1.0, dt)
            self.b = DelayGain(0.060, 1.0, dt)
            self.k = 0

        def reset(self) -> None:
            self.a.reset()
            self.b.reset()
            self.k = 0

        def step(self, command: float):
            xa, xb = self.a.step(command), self.b.step(command)
            w = min(max((self.k - k_jump) / 256.0, 0.0), 1.0)
            x = (1.0 - w) * xa + w * xb
            self.k += 1
            return x, 1.0e6 * x

    return Jump()


# in lockstep (virtual time): only the disconnect's trip, on the wall-clock lockstep timeout, runs
# apart from the parallel tests
@pytest.mark.parametrize(
    "fault", ["stuck", pytest.param("disconnect", marks=pytest.mark.timing), "delay_jump"]
)
def test_a_fault_on_one_channel_stops_every_channel(tmp_path, fault):
    over: list[str] = []
    plant = None
    if fault == "stuck":
        over.append("actuators.storey3.twin.faults=stuck_from=3000")
    elif fault == "disconnect":
        # lockstep waits for each reply up to this wall-clock bound, which then trips
        over += ["actuators.storey3.twin.faults=disconnect_from=3000", "loop.lockstep_timeout=1.0"]
    else:
        over += ["actuators.storey3.safety.fei_consecutive=32", "safety.warmup=2.5"]
        plant = {"storey3": _delay_jump_plant(1 / 1024, 4000)}
    loop, res, run = _run(tmp_path, TWO, "r", over, duration=8.0, plant=plant)
    rule = {"stuck": "stuck", "disconnect": "watchdog", "delay_jump": "fei"}[fault]
    assert res.status == "trip" and res.exit_code == 3
    assert res.trip.rule == rule and res.trip.channel == "storey3"
    k = res.trip.step
    assert k >= 3000
    # the record is complete up to the step that tripped
    assert len(run.record) == res.steps == k + 1
    # every channel stopped within 2 steps of detection: no command after the trip moved a plant
    for ch in loop.channels:
        assert ch.driver.stats.estops == 1  # every channel's driver sent its e-stop
        if fault == "disconnect" and ch.name == "storey3":
            continue  # a node that has fallen off the bus hears nothing
        assert ch.twin.stats.estops == 1  # each twin received its e-stop
        assert ch.twin.controller.estop_latched
    healthy = loop.channels[0].twin.stats
    assert k + 1 <= healthy.steps <= k + 1 + 2
    ev = [e for e in run.events if e["kind"] == "trip"]
    assert ev[0]["channel"] == "storey3" and ev[0]["rule"] == rule
    estops = [e for e in run.events if e["kind"] == "estop"]
    assert sorted(e["channel"] for e in estops) == ["storey1", "storey3"]
    assert [e["confirmed"] for e in estops if e["channel"] == "storey1"] == [True]


@pytest.mark.timing  # paced, killed
def test_kill_9_of_a_paced_two_channel_run_leaves_a_readable_record(tmp_path):
    out = tmp_path / "killed"
    code = (
        "import sys; from rths_hil.cli import main; sys.exit(main(['run', sys.argv[1], '--paced',"
        " '--duration', '20s', '--out', sys.argv[2], '-q', '--no-plot',"
        " '--set', 'safety.max_overruns=100000', '--set', 'safety.watchdog_missed=100000',"
        " '--set', 'fei.exact_hop=0']))"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(TWO), str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the loop has run for a while
            ev = out / "events.jsonl"
            if ev.exists() and '"clock"' in ev.read_text():
                break
            time.sleep(0.05)
        time.sleep(0.5)  # a few flushes of both channels' rows
        os.kill(proc.pid, signal.SIGKILL)
        t_kill = time.time()
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    run = read_run(out)
    clock = next(e for e in run.events if e["kind"] == "clock")
    t_loop_at_kill = t_kill - clock["wall_t0"]
    rec = run.record
    assert len(rec) > 100
    assert np.all(np.diff(rec["step"]) == 1) and rec["step"][0] == 0
    # every row up to 0.25 s before the kill is on disk (loop time ≈ wall time when paced)
    assert rec["time"][-1] >= t_loop_at_kill - 0.25 - float(np.max(rec["lateness"]))
    for sfx in ("_storey1", "_storey3"):
        assert np.all(np.isfinite(rec["measured" + sfx][rec["feedback_ok" + sfx]]))


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        ("--set=actuators.storey9.dof=2", "actuators.storey9"),
        ("dup", "actuators[1].name"),
        ("--set=actuators.storey1.dof=4", "actuators[0] (storey1).dof"),
        ("--set=actuators.storey3.transform=[1, -1]", "actuators[1] (storey3).transform"),
        ("--set=actuators.storey1.compensation.alhpa=2", "actuators.storey1.compensation.alhpa"),
    ],
)
def test_actuator_config_errors_are_one_line_exit_2(tmp_path, capsys, edit, key):
    args = [str(TWO)]
    if edit == "dup":
        text = TWO.read_text().replace('name = "storey3"', 'name = "storey1"')
        p = tmp_path / "dup.toml"
        p.write_text(text)
        args = [str(p)]
    else:
        args.append(edit)
    code = cli(["run", *args, "--lockstep", "--duration=0.1s", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and key in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "o").exists()


def test_set_on_every_channel_and_on_one():
    cfg = load_config(TWO, ["compensation.enabled=false", "actuators.storey3.fei.window=2.0"])
    chans = cfg.channels()
    assert [c.config["compensation"]["enabled"] for c in chans] == [False, False]
    assert [c.config["compensation"]["alpha"] for c in chans] == [11.24, 21.48]
    assert chans[1].config["fei"]["window"] == 2.0 and chans[0].config["fei"]["window"] == "3T"
    # connection merged key by key: node from the channel, bus from the top level
    assert chans[0].config["driver"]["connection"] == {
        "interface": "virtual",
        "channel": "rths-two-actuators",
        "node": 1,
    }
    with pytest.raises(InputError, match=r"actuators.nope: no channel of that name"):
        load_config(TWO, ["actuators.nope.dof=1"])


def test_two_channels_on_one_can_node_are_refused(tmp_path):
    with pytest.raises(InputError, match="same CAN node"):
        RTHSLoop(load_config(TWO, ["actuators.storey3.driver.connection.node=1"]), tmp_path / "r")


def test_console_names_the_worst_channel(tmp_path):
    seen: list[dict] = []
    cfg = load_config(TWO, ["loop.console=0.001", "output.plot=false"])
    RTHSLoop(cfg, tmp_path / "r", mode="lockstep", duration=3.0, live=seen.append).run()
    last = seen[-1]
    # storey3's limit is 30 mm on ≈ 8 mm, storey1's 40 mm on ≈ 13 mm: storey1 is nearer
    assert last["channel"] in ("storey1", "storey3")
    name, margin = last["margin"]
    assert 0.0 < margin < 1.0 and name in ("displacement", "velocity", "force")
    assert not math.isnan(last["delay"]) or last["t"] < 2.5


@pytest.mark.timing  # paced
def test_exact_fei_is_recorded_at_its_windows_end_step(tmp_path):
    """Issue 15 §4: in a paced run the exact cross-check comes back from a worker process some
    steps after its window ended; the record and the report place it at the window's end,
    where it equals the batch moving_fei of the recorded signals."""
    from rths_hil.fei import moving_fei
    from rths_hil.report import exact_fei_points

    cfg = load_config(
        None,
        [
            "loop.console=0",
            "output.plot=false",
            "fei.window=1.0",
            "fei.exact_hop=128",
            "safety.max_overruns=100000",
            "safety.watchdog_missed=100000",
        ],
    )
    # 2.5 s: 12 exact points after the first 1 s window (one every 128 steps), each placed
    # and compared below
    res = RTHSLoop(cfg, tmp_path / "r", mode="paced", duration=2.5).run()
    assert res.steps > 2400
    rec = read_run(tmp_path / "r").record
    k_end, amp, dly = exact_fei_points(rec)
    assert k_end.size >= 10
    fs = cfg["loop"]["fs"]
    ref = moving_fei(rec["target"].astype(float), rec["measured"].astype(float), fs, 1.0, hop=1)
    ends = np.round(ref.t_end * fs).astype(int)
    idx = np.searchsorted(ends, k_end)
    assert np.all(ends[idx] == k_end)
    np.testing.assert_allclose(amp, ref.amplitude[idx], rtol=1e-6)
    np.testing.assert_allclose(dly, ref.delay[idx], atol=1e-7)
    # the values arrive after their window ended (the worker's lag), never before
    first_seen = np.array([np.flatnonzero(rec["fei_exact_step"] == k)[0] for k in k_end])
    assert np.all(first_seen >= k_end)

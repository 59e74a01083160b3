"""Start and end of a test on an actuator that is not at rest (rths_hil.hybrid.phases).

What reaches the actuator is observed at the twin's plant (every command it is stepped with,
after the CAN/Modbus frames and the controller), not taken from the bridge's own bookkeeping:

* a twin sitting at +3 mm: the first command the actuator gets is +3 mm (no jump), the commands
  follow the closed-form cosine ramp to the first target, no command step exceeds the ramp's
  velocity bound, and the loop's step 0 continues from the ramp's end within ``start.tolerance``;
  without the ramp (tolerance 1 m) the first command jumps 3 mm — the fault the ramp removes;
* offset mode: every command reaching the actuator is the record's command + 3 mm;
* a start outside the displacement limit, or with the controller reporting a fault, is refused
  with one line and exit 2;
* completed runs, SIGTERM and SIGHUP leave the controller disabled and not latched, and a served
  twin with a 250 ms heartbeat watchdog logs no e-stop afterwards; a trip still e-stops;
* real hardware (a driver without a twin) needs --confirm-hardware; lockstep against it needs
  driver.stepped.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from rths_hil.sim_backends.twin import default_plant

from rths_hil.cli import main as cli_main
from rths_hil.errors import InputError
from rths_hil.hybrid.phases import cosine_ramp, ramp_duration
from rths_hil.records.recorder import read_run
from tests.helpers.cli import one_line_exit_2
from tests.helpers.loop import run_loop
from tests.helpers.procs import (
    LATCH_LINE,
    ROOT,
    ServedTwin,
    bridge_cmd,
    run_bridge,
    toml_table,
    wait_rows,
)

# The start and end phases in lockstep, the refusals and the served twin in lockstep run with
# the parallel tests; the paced runs against a served twin run apart from them, one at a time
# (the "timing" marker, pyproject.toml; make test).

MM = 1e-3
LSB = 1e-7  # CAN/Modbus displacement resolution (m)
BASE = [
    "loop.duration=1",
    "loop.console=0",
    "output.plot=false",
    "fei.enabled=false",
    "kalman.enabled=false",
    "twin.sensor={displacement_noise = 0.0, force_noise = 0.0}",
]


class RecordingPlant:
    """A twin plant that keeps every command it is stepped with (what the actuator got)."""

    def __init__(self, plant) -> None:
        self.plant = plant
        self.dt = plant.dt
        self.commands: list[float] = []

    def reset(self) -> None:
        self.plant.reset()

    def step(self, command: float):
        self.commands.append(command)
        return self.plant.step(command)


def _run(tmp_path, over, mode="lockstep", name="run"):
    plant = RecordingPlant(default_plant(delay=0.005, dt=1 / 1024))
    r = run_loop(tmp_path / name, None, *BASE, *over, plant=plant, mode=mode)
    return r.loop, r.result, plant, r.run


def _twin_last(loop) -> float:
    """The twin's last measured displacement (what a disabled controller holds)."""
    return loop.twin.controller.displacement


def _events(run, kind):
    return [e for e in run.events if e["kind"] == kind]


# ----------------------------------------------------------------------------------------------
# start


def test_ramp_from_where_the_actuator_is_to_the_first_target(tmp_path):
    home = 3 * MM
    _, res, plant, run = _run(tmp_path, ['twin.initial_position="3mm"'])
    assert res.status == "completed" and res.handback is True
    fs = 1024.0
    # what the actuator got, in absolute coordinates (the twin runs its plant about home)
    cmd = np.array(plant.commands) + home
    (ramp,) = _events(run, "start_ramp")
    m = ramp["steps"]
    assert m == res.start_steps and ramp["start"] == [pytest.approx(home)]
    # closed form: T = max(ramp_time, π·|Δ|/(2·v)) = max(2 s, π·3 mm/(2·10 mm/s)) = 2 s
    T = ramp_duration(home, 0.01, 2.0)
    n_ramp = int(np.ceil(T * fs))
    assert ramp["duration"] == pytest.approx(n_ramp / fs)
    expect = np.concatenate([cosine_ramp(home, 0.0, n_ramp), np.zeros(m - n_ramp - 1)])
    # the commands the actuator got during the ramp are that cosine, to the bus resolution
    assert np.max(np.abs(cmd[:m] - expect)) <= LSB
    assert abs(cmd[0] - home) <= LSB  # no jump at the first command
    steps = np.abs(np.diff(cmd))
    # no step of the ramp beyond its peak velocity π·Δ/(2T) (≤ start.velocity)
    v_peak = np.pi * home / (2 * n_ramp / fs)
    assert steps[: m - 1].max() * fs <= v_peak * (1 + 1e-3) + LSB * fs
    assert steps[: m - 1].max() * fs <= 0.01
    # from the ramp's last command to the loop's step 0: within start.tolerance (0.05 mm)
    assert abs(cmd[m] - cmd[m - 1]) <= 5e-5
    # the record starts where the actuator now is: step 0 measured ≈ the first target
    assert abs(run.record["measured"][0]) < 1e-5
    assert run.record["step"][0] == 0 and len(run.record) == res.steps == 1024


def test_without_the_ramp_the_first_command_jumps(tmp_path):
    """The reference: a tolerance of 1 m switches the ramp off and step 0 commands 0."""
    _, res, plant, run = _run(tmp_path, ['twin.initial_position="3mm"', "start.tolerance=1.0"])
    cmd = np.array(plant.commands) + 3 * MM
    assert res.start_steps == 0 and not _events(run, "start_ramp")
    assert abs(cmd[0] - 0.0) <= LSB  # the actuator is told to jump 3 mm at once


def test_twin_at_rest_runs_exactly_as_without_the_phases(tmp_path):
    """A twin at 0: no ramp, no shift, the record equals one with a huge start tolerance."""
    _, res_a, plant_a, run_a = _run(tmp_path, [], name="a")
    _, _, plant_b, run_b = _run(tmp_path, ["start.tolerance=1.0"], name="b")
    assert res_a.start_steps == 0 and not _events(run_a, "start_ramp")
    for name in run_a.record.dtype.names:
        if name != "feedback_time":  # wall-clock reply times differ from run to run
            assert run_a.record[name].tobytes() == run_b.record[name].tobytes(), name
    n = res_a.steps
    assert plant_a.commands[:n] == plant_b.commands[:n]


def test_offset_mode_runs_about_the_start_position(tmp_path):
    home = 3 * MM
    _, res, plant, run = _run(tmp_path, ['twin.initial_position="3mm"', "start.mode=offset"])
    assert res.status == "completed" and res.start_steps == 0
    (pos,) = _events(run, "start_position")
    assert pos["offset"] == pytest.approx(home)
    cmd = np.array(plant.commands) + home
    n = res.steps
    # every command reaching the actuator is the record's command plus the start position
    assert np.max(np.abs(cmd[:n] - (run.record["command"] + home))) <= LSB
    assert abs(cmd[0] - home) <= LSB
    # and the structure sees the measurement about the start position: it starts at 0
    assert abs(run.record["measured"][0]) < 1e-5


def test_start_outside_the_displacement_limit_is_refused(tmp_path):
    with pytest.raises(InputError, match=r"\+60\.000 mm, outside the displacement limit ±50"):
        _run(tmp_path, ['twin.initial_position="60mm"'])
    run = read_run(tmp_path / "run")
    assert _events(run, "refused") and not _events(run, "start_ramp")


def test_cli_refusal_is_one_line_exit_2(tmp_path, capsys):
    argv = ["run", "-q", "--lockstep", "--out", str(tmp_path / "r")]
    argv += [f"--set={s}" for s in [*BASE, 'twin.initial_position="-70mm"']]
    one_line_exit_2(argv, capsys, "-70.000 mm", "displacement limit")


def test_controller_fault_at_start_is_refused(tmp_path, capsys):
    """A served twin left in a runaway fault: the next run reads FAULT and refuses to start
    (both runs in this process, the second through ``rths-hil run``'s own ``main``)."""
    twin = ServedTwin(
        "--driver", "modbus", "--heartbeat-timeout", "0", "--faults", "runaway_from=50"
    )  # fmt: skip
    try:
        base = [*BASE, "safety.velocity_limit=0"]
        first = run_bridge("modbus", twin.connection, tmp_path / "r1", *base, mode="lockstep")
        assert first.result.status == "trip", first.result  # the runaway trips the run
        second = bridge_cmd("modbus", twin.connection, tmp_path / "r2", "--lockstep")[3:]
        one_line_exit_2([*second, *[f"--set={s}" for s in base]], capsys,
                        "reports a fault (status 0x")  # fmt: skip
    finally:
        twin.stop()


# ----------------------------------------------------------------------------------------------
# end


def test_completed_run_hands_the_controller_back_disabled(tmp_path):
    loop, res, plant, run = _run(tmp_path, ['twin.initial_position="3mm"'])
    ctl = loop.twin.controller
    assert not ctl.enabled and not ctl.estop_latched and not ctl.watchdog_tripped
    (hb,) = _events(run, "handback")
    assert hb["disabled"] and not hb["latched"] and hb["status"] == 0
    (end_ramp,) = _events(run, "end_ramp")
    # default rest = hold: the actuator is held at the last command of the test, then disabled
    last = run.record["command"][-1]
    assert end_ramp["start"] == end_ramp["end"] == [pytest.approx(last)]
    # end.hold = 0 (default): disabled at once, the controller holds; the plant was stepped
    # by the start ramp and the test only
    assert len(plant.commands) == res.start_steps + res.steps
    assert hb["position"] == pytest.approx(_twin_last(loop), abs=LSB)  # it holds there
    assert not _events(run, "estop")


def test_end_hold_keeps_commanding_the_last_position(tmp_path):
    _, res, plant, run = _run(tmp_path, ["end.hold=0.1"])
    last = run.record["command"][-1]
    tail = np.array(plant.commands[res.start_steps + res.steps :])
    assert tail.size == round(0.1 * 1024)
    assert np.max(np.abs(tail - last)) <= LSB  # every end command is the hold position
    assert _events(run, "handback")[0]["disabled"]


def test_end_ramp_to_a_rest_position(tmp_path):
    over = ["end.rest=position", 'end.rest_position="0mm"', "loop.duration=2"]
    _, res, plant, run = _run(tmp_path, over)
    assert len(_events(run, "end_ramp")) == 1
    cmd = np.array(plant.commands)
    tail = cmd[res.start_steps + res.steps :]
    assert abs(tail[-1]) <= LSB  # arrived at 0
    assert np.max(np.abs(np.diff(tail))) * 1024 <= 0.01 + LSB * 1024  # start.velocity
    assert abs(tail[0] - run.record["command"][-1]) <= 0.01 / 1024 + LSB  # no jump from the test
    assert _events(run, "handback")[0]["disabled"]


def test_trip_still_estops_without_a_ramp(tmp_path):
    _, res, plant, run = _run(tmp_path, ["safety.displacement_limit=1mm", "loop.duration=5"])
    assert res.status == "trip" and res.handback is None
    assert not _events(run, "end_ramp") and not _events(run, "handback")
    (estop,) = _events(run, "estop")
    assert estop["confirmed"] is True
    # nothing was stepped after the trip (a latched controller holds)
    assert len(plant.commands) == res.steps


def test_trip_in_the_start_ramp_exits_3_with_a_summary(tmp_path, capsys):
    """A trip before loop step 0 (a NaN reply in the start ramp): exit 3, the summary printed
    (no steps, no rate), the e-stop confirmed by a poll numbered after the ramp's commands."""
    from rths_hil.cli import main

    out = tmp_path / "run"
    sets = [*BASE, 'twin.initial_position="3mm"', 'twin.faults="nan=5"']
    code = main(["run", "--lockstep", "--out", str(out), *[a for s in sets for a in ("--set", s)]])
    cap = capsys.readouterr()
    assert code == 3, cap.err
    assert "Traceback" not in cap.err + cap.out
    assert "trip after 0 steps" in cap.out and "no loop steps, missed replies 0" in cap.out
    assert "e-stop: nan" in cap.err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "trip" and summary["steps"] == 0
    assert summary["trip"]["rule"] == "nan" and summary["trip"]["step"] < 0  # in the ramp
    assert summary["steps_per_second"] is None and summary["estop_confirmed"] is True


HB = 0.25  # the served twin's heartbeat watchdog (s)
# paced against a twin process on a loaded 2-core machine: a reply may take a few ms (the
# loop waits up to 10 ms for it, then catches up), the bridge's feedback watchdog at 0.3 s (a
# twin descheduled for 20 ms is not a dead one), overruns counted, not tripped
PACED = ["loop.feedback_timeout=0.01", "safety.watchdog_timeout=0.3",
         "safety.watchdog_missed=1000000", "safety.max_overruns=100000"]  # fmt: skip


@pytest.fixture()
def served():
    twin = ServedTwin("--driver", "modbus", "--heartbeat-timeout", f"{HB * 1e3:g}ms",
                      "--initial-position", "2mm")  # fmt: skip
    yield twin
    twin.stop()


def _modbus_status(conn) -> int:
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(conn["host"], port=conn["port"])
    assert client.connect()
    try:
        return client.read_holding_registers(16, count=7, device_id=conn["device_id"]).registers[1]
    finally:
        client.close()


@pytest.mark.timing
def test_served_twin_logs_no_latch_after_a_completed_paced_run(served, tmp_path):
    out = tmp_path / "run"
    # the bridge in this process (the twin is the other one; a bridge process's own stop is
    # the next test)
    r = run_bridge("modbus", served.connection, out, *BASE, *PACED, mode="paced", duration=1.0)
    assert r.result.status == "completed", r.result.trip
    t_end = time.monotonic()
    time.sleep(3 * HB)  # well past the controller's watchdog
    assert served.first(LATCH_LINE, timeout=0.1) is None, served.lines
    status = _modbus_status(served.connection)
    assert status & 0x03 == 0, status  # neither ENABLED nor ESTOP_ACTIVE
    run = read_run(out)
    assert _events(run, "start_ramp")[0]["start"] == [pytest.approx(2 * MM)]
    assert _events(run, "handback")[0]["disabled"] is True
    assert time.monotonic() - t_end >= 3 * HB


# one signal: every stop signal is caught by the same OperatorStop
# (test_loop_paced.py::test_every_stop_signal_is_the_operator_stop_and_a_second_one_interrupts)
@pytest.mark.timing
@pytest.mark.parametrize("sig", [signal.SIGTERM])
def test_signal_stop_hands_back_without_estop(served, tmp_path, sig):
    out = tmp_path / "run"
    cmd = bridge_cmd("modbus", served.connection, out, "--paced", "--duration", "30")
    cmd += [f"--set={s}" for s in [*BASE, *PACED, "start.ramp_time=0.5"]]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT)  # fmt: skip
    wait_rows(out, 300, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    time.sleep(3 * HB)
    assert served.first(LATCH_LINE, timeout=0.1) is None, served.lines
    assert _modbus_status(served.connection) & 0x03 == 0
    run = read_run(out)
    kinds = [e["kind"] for e in run.events]
    assert "operator_stop" in kinds and "estop" not in kinds
    assert kinds.index("end_ramp") < kinds.index("handback") < kinds.index("end")
    assert _events(run, "handback")[0]["disabled"] is True


# ----------------------------------------------------------------------------------------------
# real hardware


def _hw_cmd(conn, out, *extra):
    return [
        sys.executable, "-m", "rths_hil", "run", "-q", "--out", str(out),
        "--set=twin.enabled=false", "--set=driver.name=modbus",
        f"--set=driver.connection={toml_table(conn)}", *[f"--set={s}" for s in BASE], *extra,
    ]  # fmt: skip


def test_hardware_needs_confirmation_and_lockstep_needs_stepped(tmp_path, capsys):
    """The two refusals and the run that is allowed, against the served twin, each through
    ``rths-hil run``'s own ``main`` in this process (exit 2 and one line; exit 0)."""
    twin = ServedTwin("--driver", "modbus", "--heartbeat-timeout", "0")
    try:
        conn = twin.connection
        unconfirmed = _hw_cmd(conn, tmp_path / "a", "--paced")[3:]
        one_line_exit_2(unconfirmed, capsys, "--confirm-hardware")
        assert not (tmp_path / "a").exists()
        lockstep = _hw_cmd(conn, tmp_path / "b", "--confirm-hardware", "--lockstep")[3:]
        one_line_exit_2(lockstep, capsys, "driver.stepped")
        stepped = _hw_cmd(
            conn,
            tmp_path / "c",
            "--lockstep",
            "--set=driver.stepped=true",
            "--set=loop.confirm_hardware=true",
        )[3:]
        code = cli_main(stepped)
    finally:
        twin.stop()
    assert code == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "c" / "meta.json").read_text())["mode"] == "lockstep"


def test_tune_takes_the_configs_confirmation_and_refuses_a_silent_controller(tmp_path, capsys):
    """loop.confirm_hardware = true confirms for tune; a controller that does not answer the
    arming command cannot say where its actuator is: refused before anything moves."""
    from rths_hil.cli import main as cli

    over = [
        "twin.enabled=false",
        "driver.name=can",
        'driver.connection={interface = "virtual", channel = "nobody-listens"}',
        "loop.console=0",
        "loop.confirm_hardware=true",
    ]
    out = tmp_path / "hw"
    args = ["tune", *[f"--set={s}" for s in over], "--max-iterations=1", "--trial-duration=1s"]
    code = cli([*args, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "confirmed" in err and "did not answer the arming command" in err
    assert (
        not (out / "trial-01" / "record.npy").exists()
        or read_run(out / "trial-01").record.size == 0
    )

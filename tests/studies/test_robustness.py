"""Robustness studies: perturbed twins in lockstep, on a real Dask cluster.

The cluster tests start a ``distributed.LocalCluster`` of two worker processes over TCP on
127.0.0.1 and run short trials (2 s of the NEES-711 example each) through the same code path
as ``rths-hil study robustness``.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rths_hil import studies as study
from rths_hil.cli import main
from rths_hil.config import load_config

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "nees711" / "nees711.toml"
# short trials: 2 s of the record, a 1 s FEI window so that the MWO has windows
SETS = ["fei.window=1.0", "safety.warmup=0.5"]
DURATION = 2.0


def _cfg():
    return load_config(EXAMPLE, SETS)


def test_reference_response_equals_the_loop_with_an_ideal_transfer_system(tmp_path):
    from rths_hil.sim_backends.models import Identity
    from rths_hil.sim_backends.plant import Sensor, TwinPlant
    from rths_hil.sim_backends.specimen import KelvinVoigt

    from rths_hil.hybrid import run
    from rths_hil.records.recorder import read_run

    # the serial transport carries float64 (the CAN frames quantise displacement and force)
    cfg = study.inline_twin(
        load_config(EXAMPLE, [*SETS, "driver.name=serial", "driver.connection={}"])
    )
    cfg["compensation"]["enabled"] = False
    cfg["twin"]["specimen"]["stiffness"] = 1.4e6
    dt = 1.0 / cfg["loop"]["fs"]
    spec = cfg["twin"]["specimen"]
    plant = TwinPlant(
        Identity(dt), [], KelvinVoigt(spec["stiffness"], spec["damping"], dt), Sensor()
    )
    res = run(cfg, run_dir=tmp_path / "ideal", plant=plant, mode="lockstep", duration=8.0)
    assert res.status == "completed"
    target = read_run(tmp_path / "ideal").record["target"]
    ref = study.reference_response(cfg, res.planned_steps)
    np.testing.assert_allclose(ref, target, rtol=0, atol=1e-15)
    assert np.max(np.abs(ref)) > 1e-3  # the structure moved


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of two single-threaded worker processes over TCP on 127.0.0.1: the
    executor of a client and the scheduler's address (for the CLI's --scheduler)."""
    with study.open_executor("local", 2) as ex:
        address = ex._client.scheduler.address
        assert address.startswith("tcp://127.0.0.1:")
        workers = ex._client.scheduler_info()["workers"]
        assert len(workers) == 2 and all(w.startswith("tcp://127.0.0.1:") for w in workers)
        yield ex, address


def _serial_csv(path: Path, alphas, trials: int, perts) -> bytes:
    res = study.robustness_study(
        _cfg(),
        perts,
        trials,
        seed=7,
        alphas=alphas,
        duration=DURATION,
        executor=study.SerialExecutor(),
        progress=False,
    )
    study.write_trials_csv(path, res)
    return path.read_bytes()


def test_same_seed_same_trials_serially_and_on_a_local_cluster(cluster, tmp_path, capsys):
    vary = ["twin.actuator.time_constant=20ms:32ms", "twin.specimen.stiffness=0.8e6:1.6e6:normal"]
    # two draws under two α: four trials, two rounds on the two workers
    args = ["study", "robustness", str(EXAMPLE), "--trials", "2", "--seed", "7"]
    args += ["--alpha", "15,29", "--duration", str(DURATION), "--scheduler", cluster[1]]
    args += ["--no-progress", "--out", str(tmp_path / "cluster")]
    for s in SETS:
        args += ["--set", s]
    for v in vary:
        args += ["--vary", v]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "wrote trials.csv" in out
    cluster = (tmp_path / "cluster" / "trials.csv").read_bytes()
    base = study.inline_twin(_cfg())
    perts = [study.parse_vary(v, base) for v in vary]
    serial = _serial_csv(tmp_path / "serial.csv", [15, 29], 2, perts)
    assert cluster == serial
    lines = serial.decode().splitlines()
    assert len(lines) == 1 + 4
    head = lines[0].split(",")
    rows = [dict(zip(head, line.split(","), strict=True)) for line in lines[1:]]
    # the same drawn twins under both α; α = 15 lags (d > 0), α = 29 about balances
    assert [r["twin.specimen.stiffness"] for r in rows[:2]] == [
        r["twin.specimen.stiffness"] for r in rows[2:]
    ]
    assert rows[0]["twin.specimen.stiffness"] != rows[1]["twin.specimen.stiffness"]
    for r in rows:
        tc = float(r["twin.actuator.time_constant"])
        assert 0.020 <= tc <= 0.032
        assert r["status"] == "completed"
        assert (
            float(r["fei_delay"]) > 0.005
            if r["alpha"] == "15.0"
            else abs(float(r["fei_delay"])) < 0.004
        )
        assert math.isfinite(float(r["mwo_delay_max"]))
        assert float(r["bench_J1"]) >= 0  # the script's J1 cannot lead
    for name in ("summary.csv", "summary.json", "robustness_hist.png", "robustness_alpha.png"):
        assert (tmp_path / "cluster" / name).stat().st_size > 0


def test_killed_worker_trial_is_rerun_and_the_study_completes(cluster, tmp_path):
    base = study.inline_twin(_cfg())
    perts = [study.parse_vary("twin.actuator.time_constant=20ms:32ms", base)]
    ex = cluster[0]
    client = ex._client
    result: dict = {}

    def run_study():
        result["res"] = study.robustness_study(
            base, perts, 4, seed=3, duration=DURATION, executor=ex, progress=False
        )

    th = threading.Thread(target=run_study)
    th.start()
    deadline = time.monotonic() + 120
    killed = None
    while killed is None and time.monotonic() < deadline:
        busy = {w: keys for w, keys in client.processing().items() if keys}
        if busy:
            time.sleep(0.3)  # let the trial get going
            addr, keys = next(iter(busy.items()))
            pid = client.run(os.getpid, workers=[addr])[addr]
            os.kill(pid, signal.SIGKILL)
            killed = list(keys)
        time.sleep(0.05)
    assert killed, "no worker ever ran a trial"

    def suspicious(dask_scheduler, keys=tuple(killed)):
        return max(
            (dask_scheduler.tasks[k].suspicious for k in keys if k in dask_scheduler.tasks),
            default=0,
        )

    # the scheduler notices the lost worker and reschedules its task (marked suspicious)
    seen = 0
    while not seen and th.is_alive() and time.monotonic() < deadline:
        seen = client.run_on_scheduler(suspicious)
        time.sleep(0.05)
    th.join(timeout=180)
    assert not th.is_alive()
    assert seen >= 1
    res = result["res"]
    assert [r["trial"] for r in res.rows] == [0, 1, 2, 3]
    # the killed worker's scratch directory was removed by a later trial
    assert not list(Path(tempfile.gettempdir()).glob(f"rths-trial-{pid}-*"))
    assert all(r["status"] == "completed" for r in res.rows)
    serial = study.robustness_study(
        base, perts, 4, seed=3, duration=DURATION, executor=study.SerialExecutor(), progress=False
    )
    study.write_trials_csv(tmp_path / "a.csv", res)
    study.write_trials_csv(tmp_path / "b.csv", serial)
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_study_accuracy_on_the_cluster_equals_the_serial_run(cluster, tmp_path, capsys):
    args = ["study", "accuracy", "--fn", "1.0", "--hop", "32", "--no-progress"]
    assert main([*args, "--workers", "1", "--out", str(tmp_path / "serial")]) == 0
    assert main([*args, "--scheduler", cluster[1], "--out", str(tmp_path / "dask")]) == 0
    serial = (tmp_path / "serial" / "accuracy.csv").read_bytes()
    assert serial == (tmp_path / "dask" / "accuracy.csv").read_bytes()
    assert len(serial.decode().splitlines()) == 3  # linear and Bouc-Wen


def test_tune_sweep_on_the_cluster_equals_the_serial_sweep(cluster, tmp_path, capsys):
    import csv

    args = ["tune", str(EXAMPLE), "--sweep", "20,35", "--trial-duration", "2s", "--no-plot"]
    args += ["-q", "--set", "driver.name=serial", "--set", "driver.connection={}"]
    assert main([*args, "--out", str(tmp_path / "serial")]) == 0
    assert main([*args, "--scheduler", cluster[1], "--out", str(tmp_path / "dask")]) == 0

    def table(d):
        with (tmp_path / d / "sweep.csv").open() as fh:
            return [{k: v for k, v in r.items() if k != "run_dir"} for r in csv.DictReader(fh)]

    assert table("serial") == table("dask")
    assert len(table("dask")) == 2
    assert (tmp_path / "dask" / "sweep-02" / "record.npy").is_file()


@pytest.mark.parametrize(
    "vary,message",
    [
        ("twin.actuator.foo=1:2", "unknown key 'twin.actuator.foo'"),
        ("structure.nope=1:2", "unknown key"),
        ("twin.actuator.time_constant=30ms:20ms", "low (30ms) is above high (20ms)"),
        ("twin.specimen.stiffness=-1e6:2e6", "not physical"),
        ("twin.actuator.time_constant=0:20ms", "not physical"),
        ("twin.actuator.gain=0:1", "not physical"),
        ("twin.actuator.delay=-5ms:5ms:normal", "not physical"),
        ("twin.actuator.delay=abc:5ms", "not a number"),
        ("twin.actuator.delay=1ms", "expected LOW:HIGH"),
        ("structure.mass=-5:5", "structure.mass"),
        ("structure.fn=0.5:600", "Nyquist"),
    ],
)
def test_bad_vary_is_one_line_and_exit_2(vary, message, tmp_path, capsys):
    rc = main(["study", "robustness", str(EXAMPLE), "--vary", vary, "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1
    assert message in err
    assert "Traceback" not in err
    assert not (tmp_path / "trials.csv").exists()


def test_default_perturbations_are_the_benchmarks_spreads():
    base = study.inline_twin(_cfg())
    perts = {p.key: p for p in study.default_perturbations(base)}
    tc = perts["twin.actuator.time_constant"]
    assert tc.dist == "normal"
    assert 0.5 * (tc.low + tc.high) == pytest.approx(0.0262)
    assert 0.25 * (tc.high - tc.low) == pytest.approx(0.034 * 0.0262)
    k = perts["twin.specimen.stiffness"]
    assert 0.25 * (k.high - k.low) == pytest.approx(50e3)  # F1_input_file.m: 50e3·randn
    bench = study.inline_twin(load_config(EXAMPLE, [*SETS, 'twin.actuator={model="benchmark"}']))
    b = {p.key: p for p in study.default_perturbations(bench)}
    assert 0.25 * (b["twin.actuator.a3"].high - b["twin.actuator.a3"].low) == pytest.approx(1.3)
    draws = b["twin.actuator.a3"].draw(np.random.default_rng(0), 5000)
    assert draws.min() > 0  # truncated to the physical domain
    assert np.std(draws) == pytest.approx(1.3, rel=0.08)


def test_scratch_of_a_dead_worker_is_swept_and_a_live_ones_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        d_dead = tmp_path / f"rths-trial-{int(dead.stdout)}-abc"
        d_live = tmp_path / f"rths-trial-{live.pid}-def"
        d_other = tmp_path / "rths-trial-notapid"
        for d in (d_dead, d_live, d_other):
            (d / "run").mkdir(parents=True)
        assert study.robustness._sweep_dead_scratch(str(tmp_path)) == 1
        assert not d_dead.exists() and d_live.exists() and d_other.exists()
    finally:
        live.kill()
        live.wait()


# ---- several actuators, MDOF structures ------------------------------------------------------

TWO = Path(__file__).resolve().parents[2] / "examples" / "two_actuators.toml"
TWO_SETS = ["fei.window=1.0", "actuators.storey3.fei.window=1.0", "safety.warmup=0.5"]


def test_reference_by_loop_equals_the_sdof_reference(tmp_path):
    """Two independent references agree: the loop with ideal twins, and the direct CR
    integration with the specimen (serial driver: float64 on the wire)."""
    cfg = study.inline_twin(
        load_config(EXAMPLE, [*SETS, "driver.name=serial", "driver.connection={}"])
    )
    cfg["twin"]["specimen"]["stiffness"] = 1.4e6
    n = 4 * 1024
    direct = study.reference_response(cfg, n)
    by_loop = study.reference_by_loop(cfg, n, tmp_path)[""]
    assert np.max(np.abs(direct)) > 1e-3
    np.testing.assert_allclose(by_loop, direct, rtol=0, atol=1e-12)


def test_two_actuators_study_per_channel_columns_serially_and_on_a_local_cluster(
    cluster, tmp_path, capsys
):
    """The two-actuator example (3-storey shear building, an inter-storey channel): every
    per-channel quantity is suffixed; compensation off, each channel's whole-record FEI delay
    is within 1 ms of its own drawn twin delay; the cluster gives the serial bytes. 3 s
    trials: the FEI delays are then within 40 µs of the twins' (as in 6 s trials), so 1 ms
    still tells storey 1's drawn 8-12 ms from storey 3's 20 ms."""
    vary = ["actuators.storey1.twin.actuator.delay=8ms:12ms", "twin.specimen.stiffness=0.9e6:1.1e6"]
    sets = [*TWO_SETS, "compensation.enabled=false"]
    args = ["study", "robustness", str(TWO), "--trials", "2", "--seed", "3"]
    args += ["--duration", "3", "--scheduler", cluster[1], "--no-progress"]
    args += ["--out", str(tmp_path / "cluster")]
    for s in sets:
        args += ["--set", s]
    for v in vary:
        args += ["--vary", v]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "storey1" in out and "storey3" in out
    base = study.inline_twin(load_config(TWO, sets))
    perts = [study.parse_vary(v, base) for v in vary]
    res = study.robustness_study(
        base, perts, 2, seed=3, duration=3.0, executor=study.SerialExecutor(), progress=False
    )
    study.write_trials_csv(tmp_path / "serial.csv", res)
    assert (tmp_path / "cluster" / "trials.csv").read_bytes() == (
        tmp_path / "serial.csv"
    ).read_bytes()
    assert res.suffixes == ["_storey1", "_storey3"]
    for r in res.rows:
        assert r["status"] == "completed" and r["trip_channel"] == ""
        assert "fei_delay" not in r and "J2" not in r
        d1 = r["actuators.storey1.twin.actuator.delay"]
        assert 0.008 <= d1 <= 0.012
        assert abs(r["fei_delay_storey1"] - d1) < 1e-3
        assert abs(r["fei_delay_storey3"] - 0.020) < 1e-3  # storey 3's twin: 20 ms, not varied
        assert r["alpha_storey1"] == 1.0 and r["alpha_storey3"] == 1.0
        for sfx in res.suffixes:
            assert r["J2" + sfx] > 1.0 and r["peak_reference" + sfx] > 1e-3
    # the top-level twin.* key reached both channels' specimens (the same drawn value)
    spec = study.plan_trials(base, perts, 1, seed=3, duration=3.0)[0]
    k = spec.values["twin.specimen.stiffness"]
    assert [a["twin"]["specimen"]["stiffness"] for a in spec.cfg["actuators"]] == [k, k]
    summ = {(s["metric"]) for s in res.summary()}
    assert {"fei_delay_storey1", "J2_storey3"} <= summ


@pytest.mark.parametrize(
    "vary,message",
    [
        ("actuators.nobody.twin.actuator.delay=1ms:2ms", "unknown key"),
        ("actuators.storey1.twin.actuator.delay=30ms:20ms", "is above high"),
        ("actuators.storey3.twin.actuator.gain=0:1", "not physical"),
    ],
)
def test_bad_per_channel_vary_is_one_line_and_exit_2(vary, message, tmp_path, capsys):
    rc = main(["study", "robustness", str(TWO), "--vary", vary, "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and message in err, err


def test_a_structure_the_bridge_does_not_integrate_is_refused(tmp_path, capsys):
    site = Path(__file__).resolve().parents[2] / "examples" / "opensees" / "site_two.toml"
    rc = main(["study", "robustness", str(site), "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "structure.kind" in err, err

"""The worked example of docs/protocols.md, "Adding a driver": a lab's driver and its twin in a
package of their own (``examples/lab_driver``), installed for the test (its entry points read
from its ``pyproject.toml``), run by ``rths-hil run`` in lockstep and paced; and a driver that
blocks past its receive deadline cannot hold the loop's watchdog past its limit."""

from __future__ import annotations

import importlib
import inspect
import shutil
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.records.recorder import read_run

# The registries and the lockstep run (virtual time) run with the parallel tests; the paced runs
# run apart from them, one at a time (the "timing" marker, pyproject.toml; make test).

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "lab_driver"
QUIET = ["--set", "loop.console=0", "-q"]

# A lab driver whose receive blocks 0.4 s from step STALL_AT on (a hung vendor library): the
# class does not declare honours_deadline, so the base class reads it through a reader thread.
_BLOCKING = """
import time
from mylab_udp import UDPDriver

STALL_AT = 1024
STALL = 0.4
SENT = {}
REPLY_DEADLINE = {}
ESTOPS = []


class BlockingDriver(UDPDriver):
    name = "mylab_block"
    honours_deadline = False

    def _send_raw(self, seq, displacement, enable):
        SENT[seq] = time.perf_counter()
        super()._send_raw(seq, displacement, enable)

    def receive(self, timeout):
        REPLY_DEADLINE[self._last_sent] = time.perf_counter() + timeout
        return super().receive(timeout)

    def _recv_internal(self, deadline):
        if self._last_sent >= STALL_AT and not getattr(self, "_stalled", False):
            self._stalled = True
            time.sleep(STALL)  # far past any deadline
        return super()._recv_internal(deadline)

    def estop(self):
        ESTOPS.append(time.perf_counter())
        super().estop()
"""


@pytest.fixture
def lab_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``examples/lab_driver`` as an installed distribution: its package and a dist-info
    with the entry points its pyproject.toml declares (what ``pip install`` writes)."""
    site = tmp_path / "site"
    shutil.copytree(EXAMPLE / "mylab_udp", site / "mylab_udp")
    project = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]
    groups = {g: dict(eps) for g, eps in project["entry-points"].items()}
    groups["rths_hil.drivers"]["mylab_block"] = "mylab_block:BlockingDriver"
    groups["rths_hil.twins"]["mylab_block"] = "mylab_udp:UDPTwin"
    (site / "mylab_block.py").write_text(_BLOCKING)
    info = site / f"{project['name'].replace('-', '_')}-{project['version']}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n"
    )
    (info / "entry_points.txt").write_text(
        "".join(
            f"[{g}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n"
            for g, eps in groups.items()
        )
    )
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    yield site
    for mod in ("mylab_udp", "mylab_block"):
        sys.modules.pop(mod, None)


def test_registries_find_the_lab_driver_and_its_twin(lab_package: Path) -> None:
    from rths_hil.drivers.registry import driver_class
    from rths_hil.sim_backends.registry import available_twins, twin_class

    assert driver_class("mylab").__name__ == "UDPDriver"
    assert available_twins()["mylab"] == "mylab_udp:UDPTwin"
    cls, entry = twin_class("mylab")
    assert cls.__name__ == "UDPTwin" and entry.seq_bits is None


def test_the_lab_plugins_declare_their_constructors_keys(lab_package: Path) -> None:
    """What the example declares (``CONNECTION``) is what its constructors take, with their
    defaults: the configuration is read against the same names the classes are built with."""
    from rths_hil.drivers.registry import driver_class
    from rths_hil.sim_backends.registry import twin_class

    for cls in (driver_class("mylab"), twin_class("mylab")[0]):
        params = inspect.signature(cls.__init__).parameters
        named = {n: p.default for n, p in params.items() if n not in ("self", "controller")}
        assert {n: k.default for n, k in cls.CONNECTION.items()} == named, cls.__name__


@pytest.mark.parametrize(
    "twin, setting, line",
    [
        ("true", "{prot=9001}", "driver.connection.prot: unknown key (did you mean 'port'?)"),
        ("true", "{port=70000}", "driver.connection.port: must be ≤ 65535, got 70000"),
        ("false", "{port=0}", "driver.connection.port: must be ≥ 1, got 0"),
        ("false", "{port='x'}", "driver.connection.port: "),
    ],
)
def test_a_bad_lab_connection_is_one_line_naming_the_key(
    lab_package: Path, twin: str, setting: str, line: str, capsys
) -> None:
    """The lab's keys are read by the same validator as the built-in drivers': one line naming
    ``driver.connection.KEY``, exit 2, before a twin starts or a socket opens."""
    argv = ["run", "--lockstep", "--no-plot", "-q", "--duration", "0.1", "--confirm-hardware"]
    argv += ["--set", "driver.name=mylab", "--set", f"twin.enabled={twin}"]
    code = main([*argv, "--set", f"driver.connection={setting}"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = [x for x in err.splitlines() if "error" in x]
    assert len(lines) == 1 and line in lines[0], err


def test_lab_driver_lockstep_equals_the_serial_driver(lab_package: Path, tmp_path: Path) -> None:
    """Lockstep is virtual time: the same plant behind two protocols that both carry IEEE-754
    doubles gives the same record, sample for sample."""
    runs = {}
    for name, conn in (("mylab", "{}"), ("serial", '{transport="pty"}')):
        out = tmp_path / name
        args = ["run", "--lockstep", "--duration", "3", "--out", str(out), *QUIET]
        args += ["--set", f"driver.name={name}", "--set", f"driver.connection={conn}"]
        assert main(args) == 0, name
        runs[name] = read_run(out).record
    a, b = runs["mylab"], runs["serial"]
    assert len(a) == 3 * 1024 and bool(np.all(a["feedback_ok"]))
    for col in ("command", "measured", "force"):
        np.testing.assert_array_equal(a[col], b[col], err_msg=col)
    assert np.ptp(a["measured"]) > 1e-3  # the twin moved


@pytest.mark.timing
def test_lab_driver_paced_run_completes(lab_package: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "paced"
    args = ["run", "--paced", "--duration", "1", "--out", str(out), "--set", "loop.console=0"]
    args += ["--set", "driver.name=mylab", "--set", "driver.connection={}"]
    code = main(args)
    err = capsys.readouterr().err
    assert code == 0, err
    rec = read_run(out).record
    # paced on a shared machine: a reply may miss its 0.8-period deadline now and then (the twin
    # is a thread of this process: 28 % of them once in CI); a reply filed under the wrong step
    # is not ``feedback_ok`` (its sequence number is not the step's), so a driver that filed
    # them a step late would have almost none answered
    assert len(rec) == 1024 and rec["feedback_ok"].mean() > 0.5
    link = [ln for ln in err.splitlines() if "link mylab udp" in ln]
    assert link and "UDP loopback" in link[0]


@pytest.mark.timing
def test_a_blocking_driver_cannot_hold_the_watchdog(lab_package: Path, tmp_path: Path) -> None:
    """Its receive blocks 0.4 s; the watchdog (safety.watchdog_timeout) still trips within its
    limit plus one period of the deadline of the first unanswered step (wall time,
    perf_counter)."""
    import mylab_block

    out = tmp_path / "block"
    args = ["run", "--paced", "--duration", "3", "--out", str(out), *QUIET]
    args += ["--set", "driver.name=mylab_block", "--set", "driver.connection={}"]
    # the rule under test is the watchdog: a loaded machine's overruns are counted, not tripped
    args += ["--set", "safety.max_overruns=1000000"]
    assert main(args) == 3  # a safety trip
    run = read_run(out)
    trips = [e for e in run.events if e.get("kind") == "trip"]
    assert trips and trips[0]["rule"] == "watchdog", trips
    ok = run.record["feedback_ok"]
    missed = np.flatnonzero(~ok.astype(bool))
    # the first step the blocked call leaves unanswered (a loaded machine may miss one earlier)
    first_miss = int(missed[missed >= mylab_block.STALL_AT][0])
    from rths_hil.config import default_config

    dt = 1.0 / 1024.0
    limit = default_config()["safety"]["watchdog_timeout"]  # the default test's limit
    waited = mylab_block.ESTOPS[0] - mylab_block.SENT[first_miss]
    # a stall of the bridge itself in that time is not the controller's silence: the rule does
    # not count it (its trip says how long), so the e-stop comes that much later in wall time
    stalled = float(trips[0]["values"]["stalled"])
    # the rule looks once per step, after the step's receive: the step before the trip was
    # within the limit, so the trip step's look comes at most one period later, plus what the
    # machine delayed that step by (its send's lateness, and the time from its reply deadline
    # to the e-stop: a late wake-up, the loop's own check and e-stop)
    k = int(trips[0]["step"])
    machine = float(run.record["lateness"][k]) + (
        mylab_block.ESTOPS[0] - mylab_block.REPLY_DEADLINE[k]
    )
    bound = limit + dt + stalled + machine
    assert 0.0 < waited <= bound, (waited, limit + dt, stalled, machine)
    # the blocked call held neither the step nor the e-stop: nowhere near its 0.4 s
    assert waited < mylab_block.STALL / 2
    assert machine < mylab_block.STALL / 4

"""The wheel installs one top-level package, ``rths_hil``, and works outside the repository.

Builds the wheel from this checkout, installs it with its dependencies into a fresh virtual
environment in a temporary directory (pip's cache makes this quick after the first time), and
from a working directory outside the repository — so neither ``drivers/`` nor
``sim_backends/`` of the checkout can be imported by accident — runs a short lockstep test over
each built-in driver with its twin.
"""

from __future__ import annotations

import json
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    work = tmp_path_factory.mktemp("wheel")
    dist = work / "dist"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(dist), str(ROOT)],
        check=True,
        cwd=work,
    )
    (wheel,) = dist.glob("rths_hil-*.whl")
    env_dir = work / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    python = env_dir / "bin" / "python"
    subprocess.run([python, "-m", "pip", "install", "--quiet", str(wheel)], check=True, cwd=work)
    return wheel, env_dir, work


def test_wheel_has_only_the_rths_hil_top_level(installed):
    wheel, _, _ = installed
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        (top_level,) = [n for n in names if n.endswith(".dist-info/top_level.txt")]
        assert zf.read(top_level).decode().split() == ["rths_hil"]
    tops = {n.split("/", 1)[0] for n in names if not n.split("/", 1)[0].endswith(".dist-info")}
    assert tops == {"rths_hil"}
    # the data files travel with the packages that read them
    assert "rths_hil/drivers/can/actuator.dbc" in names
    assert "rths_hil/sim_backends/eds/cia402_twin.eds" in names
    assert "rths_hil/sim_backends/eds/cia408_twin.eds" in names
    assert any(n.startswith("rths_hil/data/ground_motions/") for n in names)


@pytest.mark.parametrize("driver", ["can", "modbus", "serial", "controllers/cia402"])
def test_lockstep_run_from_the_installed_wheel(installed, driver):
    _, env_dir, work = installed
    out = work / f"runs-{driver.replace('/', '-')}"
    proc = subprocess.run(
        [
            env_dir / "bin" / "rths-hil",
            "run",
            str(ROOT / "examples" / f"{driver}.toml"),
            "--lockstep",
            "--duration",
            "2",
            "--no-plot",
            "--out",
            str(out),
        ],
        cwd=work,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 2048
    # the package came from the venv, not from the checkout
    where = subprocess.run(
        [env_dir / "bin" / "python", "-c", "import rths_hil.drivers as d; print(d.__file__)"],
        cwd=work,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert str(env_dir) in where

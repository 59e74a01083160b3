"""The wheel installs one top-level package, ``rths_hil``, and works outside the repository.

Builds the wheel from this checkout, installs it with its dependencies into a fresh virtual
environment (without pip of its own) in a temporary directory (pip's cache makes this quick
after the first time), and from a working directory outside the repository — so neither
``drivers/`` nor ``sim_backends/`` of the checkout can be imported by accident — runs a short
lockstep test over each built-in driver with its twin. The environment has the core
dependencies only: a feature of an extra that is not installed says which one in one line
(exit 2).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow

#: The environment of the commands run from the installed wheel: as a user's, where Python
#: writes the bytecode of what it imports (with PYTHONDONTWRITEBYTECODE set, as it may be where
#: the tests run, each command would compile every module it imports again, seconds each).
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


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
    # no pip of its own (ensurepip is the slow part of making a venv): this environment's pip
    # installs into it (pip --python); the wheel's dependencies are still resolved for it.
    # --no-compile: byte-compiling every installed module (most of them scipy's, never imported
    # here) took half the fixture; the commands below compile what they import, once (ENV)
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet",
         "--no-compile", str(wheel)],
        check=True,
        cwd=work,
    )  # fmt: skip
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
    assert "rths_hil/data/ground_motions/README.md" in names  # the records' terms
    # the licence travels in the wheel, and the metadata names it and the extras
    with zipfile.ZipFile(wheel) as zf:
        (lic,) = [n for n in names if n.endswith(".dist-info/licenses/LICENSE")]
        assert zf.read(lic).decode().startswith("MIT License")
        (meta,) = [n for n in names if n.endswith(".dist-info/METADATA")]
        text = zf.read(meta).decode()
    assert "License-Expression: MIT" in text
    for extra in ("hdf5", "studies", "live", "opensees", "all"):
        assert f"Provides-Extra: {extra}" in text


def test_every_package_of_the_tree_is_in_the_wheel(installed):
    """A folder with Python files (or bundled data) that is not listed in pyproject.toml would
    be left out of the wheel; setuptools' "Package would be ignored" warning is about that."""
    wheel, _, _ = installed
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
    roots = {"rths_hil": "rths_hil", "drivers": "rths_hil/drivers",
             "sim_backends": "rths_hil/sim_backends"}  # fmt: skip
    for src, dst in roots.items():
        for f in (ROOT / src).rglob("*"):
            kinds = (".py", ".dbc", ".csv", ".AT2", ".toml")
            if f.is_file() and "__pycache__" not in f.parts and f.suffix in kinds:
                rel = f.relative_to(ROOT / src).as_posix()
                assert f"{dst}/{rel}" in names, rel


@pytest.mark.parametrize(
    ("args", "extra", "module"),
    [
        (["watch", "--latest"], "live", "bokeh"),
        (["run", "--lockstep", "--duration", "0.1", "--watch"], "live", "bokeh"),
        (["export", "RUN", "--hdf5"], "hdf5", "h5py"),
        (
            ["study", "robustness", "EXAMPLE", "--trials", "2", "--out", "O"],
            "studies",
            "distributed",
        ),
    ],
)
def test_a_missing_extra_is_one_line_naming_it(installed, args, extra, module):
    _, env_dir, work = installed
    run_dir = work / "runs-extra"
    if not (run_dir / "record.npy").exists():  # a small run to export
        subprocess.run(
            [env_dir / "bin" / "rths-hil", "run", "--lockstep", "--duration", "0.2", "-q",
             "--no-plot", "--out", str(run_dir)],
            cwd=work, env=ENV, check=True, capture_output=True, timeout=300,
        )  # fmt: skip
    example = str(ROOT / "examples" / "can.toml")
    if args[0] == "run":
        args = [*args, "--out", "O"]
    subst = {"RUN": str(run_dir), "EXAMPLE": example, "O": str(work / f"o-{extra}")}
    proc = subprocess.run(
        [env_dir / "bin" / "rths-hil", *[subst.get(a, a) for a in args]],
        cwd=work, env=ENV, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert f"needs {module}, which is not installed: pip install 'rths-hil[{extra}]'" in lines[0]


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
        env=ENV,
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
        env=ENV,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert str(env_dir) in where

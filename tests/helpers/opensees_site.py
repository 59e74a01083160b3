"""Helpers for the OpenSees tests: run examples/opensees/two_storey.py against the bridge.

OpenSeesPy keeps global state and its genericClient blocks on the socket, so every OpenSees
model runs in its own subprocess (the example script) while the bridge runs in this process.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "opensees" / "two_storey.py"
SITE = ROOT / "examples" / "opensees" / "site.toml"
SITE_RT = ROOT / "examples" / "opensees" / "site_realtime.toml"
SITE_TWO = ROOT / "examples" / "opensees" / "site_two.toml"


def write_accel(path: Path, pga: float = 1.0) -> tuple[Path, float]:
    """The bundled El Centro record scaled to ``pga`` as a one-column file; (path, dt)."""
    from rths_hil import groundmotion

    gm = groundmotion.default_record().scaled(pga)
    np.savetxt(path, np.asarray(gm.accel, dtype=float))
    return path, float(gm.dt)


def opensees_args(model: str, dt: float, duration: float, accel: tuple[Path, float], *extra):
    return [
        sys.executable,
        str(EXAMPLE),
        "--model",
        model,
        "--dt",
        repr(dt),
        "--duration",
        repr(duration),
        "--accel",
        str(accel[0]),
        "--accel-dt",
        repr(accel[1]),
        *extra,
    ]


def reference(tmp: Path, model: str, dt: float, duration: float, accel, *extra) -> np.ndarray:
    """The all-numerical model (damper as zeroLength elastic + viscous)."""
    out = tmp / f"ref-{model}-{dt:g}.npy"
    reference.last = subprocess.run(
        [*opensees_args(model, dt, duration, accel, *extra), "--numerical", "--out", str(out)],
        check=True,
        capture_output=True,
        text=True,
        timeout=120,
    )
    return np.load(out)


def analysis_seconds(stdout: str) -> float:
    """The analysis time the example prints (``… N steps in T s``)."""
    for line in stdout.splitlines():
        if " steps in " in line:
            return float(line.split(" steps in ")[1].split()[0])
    raise ValueError("no timing line in the example's output")


def hybrid(
    tmp: Path,
    config: Path,
    model: str,
    dt: float,
    duration: float,
    accel,
    overrides: tuple[str, ...] = (),
    extra: tuple[str, ...] = (),
    name: str = "run",
):
    """Run the bridge (site config) with the example as its OpenSees client.

    Returns ``(result, stage, floors, proc)``: the loop's RunResult, the site stage, the
    client's floor displacements (None if it wrote none) and its finished process.
    """
    from rths_hil.config import load_config
    from rths_hil.hybrid import RTHSLoop

    cfg = load_config(config, ["openfresco.port=0", "output.plot=false", *overrides])
    loop = RTHSLoop(cfg, tmp / name)
    stage = loop.structure
    _, port = stage.listen()
    out = tmp / f"{name}.npy"
    proc = subprocess.Popen(
        [
            *opensees_args(model, dt, duration, accel, *extra),
            "--port",
            str(port),
            "--out",
            str(out),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        result = loop.run()
    finally:
        # OpenSees' TCP_Socket does not check recv's result: after the site closes the
        # connection on a fault its client spins; stop it
        if loop.result is None or loop.result.status != "completed":
            proc.kill()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    floors = np.load(out) if out.exists() else None
    return result, stage, floors, proc

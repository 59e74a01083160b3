"""A 2-storey shear frame in OpenSeesPy whose first-storey damper is tested through rths_hil.

The damper (a linear spring–dashpot specimen between the ground and floor 1) is a
``genericClient`` element served by ``rths-hil run examples/opensees/site.toml``; the frame's
columns, masses and damping stay numerical. With ``--numerical`` the damper is an ordinary
``zeroLength`` element (elastic + viscous) instead: the reference the hybrid run must match.
``--model sdof`` gives a one-storey version. ``--dampers 2`` puts a second damper in storey 2
and tests both through rths_hil: one ``genericClient`` on nodes 1, 2, 3 (three element DOFs),
two actuator channels (``rths-hil run examples/opensees/site_two.toml``), the site's default
mapping the basic system of two elements in series (actuator 1 = u₂ − u₁, actuator 2 =
u₃ − u₂). SI units throughout (m, N, kg, s).

Usage::

    rths-hil run examples/opensees/site.toml            # terminal 1: the experimental site
    python examples/opensees/two_storey.py              # terminal 2: OpenSees drives it

    python examples/opensees/two_storey.py --numerical --out ref.npy   # reference run

Each run writes the floor displacements per analysis step (``.npy``: time, u1[, u2]).

Equivalent Tcl (OpenSees 3.x) for the experimental element::

    element genericClient 3 -node 1 2 -dof 1 -dof 1 -server 8090 127.0.0.1

and with ``--dampers 2`` (both storeys' dampers, two channels)::

    element genericClient 3 -node 1 2 3 -dof 1 -dof 1 -dof 1 -server 8090 127.0.0.1
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

# The frame: two floors of 50 t each, storey stiffnesses 4 and 3 MN/m, 2 % mass-proportional
# damping on the first mode; the damper (the specimen): 1.19 MN/m and 2 kN·s/m.
MASSES = (50.0e3, 50.0e3)
STOREY_K = (4.0e6, 3.0e6)
SPECIMEN_K = 1.19e6
SPECIMEN_C = 2.0e3
# the second damper (--dampers 2), in storey 2: another specimen, so a channel mix-up shows
SPECIMEN2_K = 0.8e6
SPECIMEN2_C = 1.5e3
ZETA = 0.02


def ground_motion(args: argparse.Namespace) -> tuple[float, np.ndarray]:
    """``--accel`` (one value per line, m/s², step ``--accel-dt``) or the bridge's bundled
    El Centro 1940 record scaled to ``--pga``; cut to ``--duration``."""
    if args.accel:
        dt, a = args.accel_dt, np.loadtxt(args.accel, ndmin=1)
    else:
        from rths_hil import groundmotion

        gm = groundmotion.default_record().scaled(args.pga)
        dt, a = gm.dt, np.asarray(gm.accel, dtype=float)
    n = min(len(a), round(args.duration / dt) + 1)
    return dt, a[:n]


def build(ops, model: str, numerical: bool, host: str, port: int, specimen_k: float,
          specimen_c: float, dampers: int = 1) -> list[int]:  # fmt: skip
    """Nodes, masses, columns and the damper(s); return the floor node tags."""
    ops.wipe()
    ops.model("basic", "-ndm", 1, "-ndf", 1)
    floors = 1 if model == "sdof" else 2
    ops.node(1, 0.0)
    ops.fix(1, 1)
    for i in range(floors):
        ops.node(i + 2, 0.0)
        ops.mass(i + 2, MASSES[i])
    # storey columns: elastic zeroLength springs between consecutive floors
    for i in range(floors):
        ops.uniaxialMaterial("Elastic", 10 + i, STOREY_K[i])
        ops.element("zeroLength", 10 + i, i + 1, i + 2, "-mat", 10 + i, "-dir", 1)
    # the damper in storey 1 (and with dampers = 2 the one in storey 2)
    if numerical:
        ops.uniaxialMaterial("Elastic", 1, specimen_k)
        ops.uniaxialMaterial("Viscous", 2, specimen_c, 1.0)
        ops.element("zeroLength", 3, 1, 2, "-mat", 1, 2, "-dir", 1, 1)
        if dampers == 2:
            ops.uniaxialMaterial("Elastic", 3, SPECIMEN2_K)
            ops.uniaxialMaterial("Viscous", 4, SPECIMEN2_C, 1.0)
            ops.element("zeroLength", 4, 2, 3, "-mat", 3, 4, "-dir", 1, 1)
    elif dampers == 2:  # one element, three DOFs: the site drives two actuators
        ops.element("genericClient", 3, "-node", 1, 2, 3, "-dof", 1, "-dof", 1, "-dof", 1,
                    "-server", port, host)  # fmt: skip
    else:
        ops.element("genericClient", 3, "-node", 1, 2, "-dof", 1, "-dof", 1,
                    "-server", port, host)  # fmt: skip
    return [i + 2 for i in range(floors)]


def first_mode_omega(model: str, specimen_k: float, dampers: int = 1) -> float:
    """Circular frequency of the first mode with the dampers' stiffness (rad/s)."""
    if model == "sdof":
        return math.sqrt((STOREY_K[0] + specimen_k) / MASSES[0])
    k1 = STOREY_K[0] + specimen_k
    k2 = STOREY_K[1] + (SPECIMEN2_K if dampers == 2 else 0.0)
    K = np.array([[k1 + k2, -k2], [-k2, k2]])
    M = np.diag(MASSES)
    w2 = np.linalg.eigvals(np.linalg.solve(M, K)).real
    return float(math.sqrt(min(w2)))


def run(args: argparse.Namespace) -> np.ndarray:
    try:
        import openseespy.opensees as ops
    except ImportError:
        raise SystemExit(
            "two_storey.py needs OpenSeesPy, which is not installed: "
            "pip install 'rths-hil[opensees]'"
        ) from None

    nodes = build(ops, args.model, args.numerical, args.host, args.port, args.specimen_k,
                  args.specimen_c, args.dampers)  # fmt: skip
    gdt, ag = ground_motion(args)
    ops.timeSeries("Path", 1, "-dt", gdt, "-values", *ag.tolist())
    ops.pattern("UniformExcitation", 1, 1, "-accel", 1)
    # 2 % mass-proportional damping at the first mode (C = αM, α = 2ζω)
    omega = first_mode_omega(args.model, args.specimen_k, args.dampers)
    ops.rayleigh(2.0 * ZETA * omega, 0.0, 0.0, 0.0)
    ops.constraints("Plain")
    ops.numberer("Plain")
    ops.system("FullGeneral")
    ops.test("NormDispIncr", 1e-12, 20)
    ops.algorithm(args.algorithm)
    if args.integrator == "Newmark":
        ops.integrator("Newmark", 0.5, 0.25)
    elif args.integrator == "NewmarkExplicit":
        ops.integrator("NewmarkExplicit", 0.5)
    elif args.integrator == "AlphaOS":
        ops.integrator("AlphaOS", 1.0)
    else:
        ops.integrator(args.integrator)
    ops.analysis("Transient")
    n = round(args.duration / args.dt)
    out = np.zeros((n + 1, 1 + len(nodes)))
    t0 = time.perf_counter()
    for i in range(1, n + 1):
        if ops.analyze(1, args.dt) != 0:
            print(f"two_storey.py: analysis failed at step {i}", file=sys.stderr)
            out = out[:i]
            break
        out[i, 0] = ops.getTime()
        out[i, 1:] = [ops.nodeDisp(nd, 1) for nd in nodes]
    elapsed = time.perf_counter() - t0
    ops.wipe()  # a genericClient sends DIE (99) when it is destroyed
    print(f"two_storey.py: {len(out) - 1} steps in {elapsed:.3f} s")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", choices=("frame", "sdof"), default="frame")
    p.add_argument("--numerical", action="store_true", help="damper as a numerical element")
    p.add_argument(
        "--dampers",
        type=int,
        choices=(1, 2),
        default=1,
        help="storeys with a damper (2: both tested, two channels; frame only)",
    )
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8090)
    p.add_argument("--dt", type=float, default=1 / 256, help="analysis step (s)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds of the record")
    p.add_argument("--pga", type=float, default=1.0, help="peak ground acceleration (m/s²)")
    p.add_argument("--accel", help="ground acceleration file (m/s², one value per line)")
    p.add_argument("--accel-dt", type=float, default=0.02, help="step of --accel (s)")
    p.add_argument("--algorithm", default="Linear", help="OpenSees solution algorithm")
    p.add_argument("--integrator", default="NewmarkExplicit", help="OpenSees integrator")
    p.add_argument("--specimen-k", type=float, default=SPECIMEN_K)
    p.add_argument("--specimen-c", type=float, default=SPECIMEN_C)
    p.add_argument("--out", help="write time and floor displacements to this .npy")
    args = p.parse_args(argv)
    if args.dampers == 2 and args.model != "frame":
        p.error("--dampers 2 needs --model frame")
    out = run(args)
    if args.out:
        np.save(args.out, out)
    peak = np.abs(out[:, 1:]).max(axis=0)
    print(f"two_storey.py: {len(out) - 1} steps, peak floor displacements {peak.tolist()} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())

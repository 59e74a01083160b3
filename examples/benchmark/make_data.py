"""Write the RTHS benchmark's figures into this directory from the benchmark's MATLAB files.

The RTHS benchmark (Silva et al. 2020) is distributed as MATLAB/Simulink files; a public
repository redistributes them (https://github.com/lihongweiseu/RTHS_benchmark_SMC). This script
reads, from a clone of that repository, the numbers this example needs and writes them in
plain formats, so the example runs from a clone of rths_hil alone:

* ``reference_cases.toml`` — the four reference-structure cases (``Building cases/Case_N.mat``:
  variables ``M``, ``K``, ``C``, ``zetas``) and the specimen of the partition (``F1_input_file.m``:
  ``m_e``, ``k_e``, ``z_e``).
* ``numerical_caseN.npz`` — each case's numerical substructure (M, K, C and the influence
  vector), derived with :func:`rths_hil.structures.mdof.partition` (the specimen on DOF 1, the first
  storey): what ``structure.matrices`` of ``benchmark.toml`` reads.
* ``el_centro.csv``, ``kobe.csv``, ``morgan_hill.csv`` — the three ground motions
  (``ElCentroAccelNoScaling.mat``: ``ElCentroAccel``, ``KobeAccelNoScaling.mat``: ``KobeAccel``,
  ``MorganAccelNoScaling.mat``: ``MorganAccel``; row 1 time in s, row 2 acceleration in m/s²),
  as ``time_s,accel_ms2`` CSV, every value written exactly (shortest round-trip repr).

Only numbers are taken over; no MATLAB code. Run::

    git clone https://github.com/lihongweiseu/RTHS_benchmark_SMC
    python examples/benchmark/make_data.py RTHS_benchmark_SMC

``SOURCE`` may also be a bare git directory of that repository (its ``HEAD`` is read). The
commit read is printed and written into ``reference_cases.toml``.
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import scipy.io
import tomli_w

from rths_hil.structures import mdof

HERE = Path(__file__).resolve().parent
REPOSITORY = "https://github.com/lihongweiseu/RTHS_benchmark_SMC"
#: Specimen of the partition, F1_input_file.m ("Partitioning of RTHS"): m_e, k_e, z_e.
SPECIMEN = {"mass": 29.13, "stiffness": 1190e3, "damping_ratio": 0.0097}
#: Ground motions: output name → (file, variable).
RECORDS = {
    "el_centro": ("ElCentroAccelNoScaling.mat", "ElCentroAccel"),
    "kobe": ("KobeAccelNoScaling.mat", "KobeAccel"),
    "morgan_hill": ("MorganAccelNoScaling.mat", "MorganAccel"),
}
CASES = (1, 2, 3, 4)


class Source:
    """Files of the benchmark repository: a work tree, or a bare git directory's HEAD."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.tree = (path / "Building cases").is_dir()
        if self.tree:
            self.commit = self._git("rev-parse", "HEAD", check=False).strip() or "unknown"
        else:
            self.commit = self._git("rev-parse", "HEAD").strip()

    def _git(self, *args: str, check: bool = True) -> str:
        res = subprocess.run(
            ["git", "-C", str(self.path), *args], capture_output=True, text=True, check=False
        )
        if res.returncode != 0 and check:
            sys.exit(f"{self.path}: not a clone of {REPOSITORY} ({res.stderr.strip()})")
        return res.stdout if res.returncode == 0 else ""

    def read(self, name: str) -> bytes:
        if self.tree:
            return (self.path / name).read_bytes()
        res = subprocess.run(
            ["git", "-C", str(self.path), "show", f"HEAD:{name}"], capture_output=True, check=False
        )
        if res.returncode != 0:
            sys.exit(f"{self.path}: no {name} at HEAD")
        return res.stdout

    def mat(self, name: str) -> dict:
        return scipy.io.loadmat(io.BytesIO(self.read(name)))


def specimen_damping() -> float:
    """``c_e = 2·z_e·m_e·√(k_e/m_e)`` as F1_input_file.m computes it (N·s/m)."""
    s = SPECIMEN
    return 2.0 * s["damping_ratio"] * s["mass"] * float(np.sqrt(s["stiffness"] / s["mass"]))


def reference_model(case: dict) -> mdof.MDOFModel:
    """The reference structure of one case of ``reference_cases.toml`` (M, K, C given)."""
    return mdof.from_matrices(case["M"], case["K"], case["C"], name="reference")


def numerical_model(case: dict) -> mdof.MDOFModel:
    """The numerical substructure: the specimen taken out of DOF 1 (the first storey)."""
    return mdof.partition(
        reference_model(case),
        1,
        mass=SPECIMEN["mass"],
        damping=specimen_damping(),
        stiffness=SPECIMEN["stiffness"],
        name="numerical substructure",
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", type=Path, help=f"a clone (or bare git dir) of {REPOSITORY}")
    ap.add_argument("--out", type=Path, default=HERE, help="output directory (default: here)")
    args = ap.parse_args(argv)
    src = Source(args.source)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    doc: dict = {
        "source": {
            "repository": REPOSITORY,
            "commit": src.commit,
            "files": "Building cases/Case_1.mat … Case_4.mat (M, K, C, zetas); "
            "F1_input_file.m (m_e, k_e, z_e)",
        },
        "specimen": {**SPECIMEN, "damping": specimen_damping()},
    }
    for i in CASES:
        m = src.mat(f"Building cases/Case_{i}.mat")
        case = {
            "M": np.asarray(m["M"], dtype=float).tolist(),
            "K": np.asarray(m["K"], dtype=float).tolist(),
            "C": np.asarray(m["C"], dtype=float).tolist(),
            "zetas": np.asarray(m["zetas"], dtype=float).ravel().tolist(),
        }
        doc[f"case{i}"] = case
        num = numerical_model(case)
        np.savez(out / f"numerical_case{i}.npz", M=num.M, K=num.K, C=num.C, influence=num.influence)
        f = reference_model(case).frequencies
        print(f"case {i}: reference f = {', '.join(f'{x:.4f}' for x in f)} Hz")
    (out / "reference_cases.toml").write_text(
        "# Written by make_data.py from the RTHS benchmark's files (see README.md). SI units.\n"
        + tomli_w.dumps(doc),
        encoding="utf-8",
    )
    for name, (file, var) in RECORDS.items():
        data = np.asarray(src.mat(file)[var], dtype=float)
        lines = ["time_s,accel_ms2"]
        lines += [f"{t!r},{a!r}" for t, a in zip(data[0].tolist(), data[1].tolist(), strict=True)]
        (out / f"{name}.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
        print(f"{name}: {data.shape[1]} samples, PGA {np.max(np.abs(data[1])):.4f} m/s²")
    print(f"read {REPOSITORY} at {src.commit}; wrote {out}")


if __name__ == "__main__":
    main()

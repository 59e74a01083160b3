"""Measure the installed size of rths_hil's core and of each extra (README "Install").

Builds the wheel of this checkout, installs it into a fresh virtual environment (core), and for
each extra asks pip which distributions it would add to that environment (``--dry-run
--report``), installs exactly those into a separate folder without dependencies and measures
it. Sizes are the bytes on disk of the installed files (``du``-like, apparent size), without
pip and setuptools. Prints a Markdown table.

    python scripts/install_sizes.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXTRAS = ("hdf5", "studies", "live", "opensees")
SKIP = {"pip", "setuptools", "_distutils_hack", "distutils-precedence.pth"}


def size(path: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            p = Path(dirpath) / f
            if not p.is_symlink():
                total += p.stat().st_size
    return total


def site_size(site: Path) -> int:
    return sum(
        size(p) if p.is_dir() else p.stat().st_size
        for p in site.iterdir()
        if p.name.split("-")[0] not in SKIP and p.name not in SKIP
    )


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        dist = work / "dist"
        pip = [sys.executable, "-m", "pip"]
        subprocess.run([*pip, "wheel", "-q", "--no-deps", "-w", dist, ROOT], check=True)
        (wheel,) = dist.glob("rths_hil-*.whl")
        env = work / "venv"
        venv.EnvBuilder(with_pip=True).create(env)
        py = env / "bin" / "python"
        subprocess.run([py, "-m", "pip", "install", "-q", wheel], check=True)
        (site,) = (env / "lib").glob("python*/site-packages")
        core = site_size(site)
        rows = [("core (`pip install rths-hil`)", core, "")]
        for extra in EXTRAS:
            report = work / f"{extra}.json"
            subprocess.run(
                [py, "-m", "pip", "install", "-q", "--dry-run", "--report", report,
                 f"rths_hil[{extra}] @ {wheel.as_uri()}"],
                check=True,
            )  # fmt: skip
            items = json.loads(report.read_text())["install"]
            reqs = [
                f"{i['metadata']['name']}=={i['metadata']['version']}"
                for i in items
                if i["metadata"]["name"].replace("-", "_") != "rths_hil"
            ]
            target = work / f"t-{extra}"
            if reqs:
                subprocess.run(
                    [py, "-m", "pip", "install", "-q", "--no-deps", "--target", target, *reqs],
                    check=True,
                )
            add = size(target) if reqs else 0
            names = ", ".join(r.split("==")[0] for r in reqs)
            rows.append((f"`[{extra}]`", add, names))
    print("| install | size on disk | adds |")
    print("|---|---|---|")
    for name, b, names in rows:
        print(f"| {name} | {b / 1e6:.0f} MB | {names} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Screenshot of ``rths-hil watch`` on a real run, for ``docs/watch.md``.

Runs the default test (NEES-711 over the CAN twin, paced at 1024 Hz) with ``--watch``, opens
the page in headless Chromium and saves the page at ``--at`` seconds of loop time to
``docs/img/watch.png``. The run tolerates overruns (``safety.max_overruns``), so that a stall
of a busy machine does not end it before the picture.

Usage: ``python scripts/watch_screenshot.py [--at 20] [--out docs/img/watch.png]``.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rths_hil.watch.browser import Browser

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--at", type=float, default=20.0, help="loop time of the screenshot (s)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "img" / "watch.png"))
    ap.add_argument("--port", type=int, default=8050)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="watch-shot-"))
    run_dir = Path("runs") / "nees711"  # relative to a scratch directory: the page shows this
    run = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "rths_hil",
            "run",
            "--paced",
            "--duration",
            "30",
            "--out",
            str(run_dir),
            "-q",
            "--watch",
            "--watch-port",
            str(args.port),
            "--set",
            "output.plot=false",
            # a picture of the page, not of a busy machine: stalls of the VM must not stop it
            "--set",
            "safety.max_overruns=1000000",
        ],
        stderr=subprocess.PIPE,
        text=True,
        cwd=work,
    )
    try:
        line = run.stderr.readline()
        m = re.search(r"live view at (http://\S+)", line)
        if not m:
            raise SystemExit(f"no live view: {line.strip()}")
        with Browser(width=1200, height=1420) as b:
            b.goto(m.group(1))
            b.wait_for(
                "!!(window.Bokeh && Bokeh.documents.length && "
                "Bokeh.documents[0].get_model_by_name('window'))",
                timeout=60,
            )
            while True:
                t = b.column("window", "t") or [0.0]
                if t[-1] >= args.at or run.poll() is not None:
                    break
                time.sleep(0.05)
            time.sleep(0.3)  # the last refresh drawn
            b.screenshot(args.out)
        print(f"{args.out}: page at t = {t[-1]:.2f} s of {work / run_dir}")
    finally:
        run.terminate()  # SIGTERM: the run's operator stop (flushed, exit 130)
        run.wait(30)


if __name__ == "__main__":
    main()

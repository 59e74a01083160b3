"""Benchmark of ``rths-hil watch``: what watching costs the loop, and how live the page is.

One paced run of the default test (NEES-711 over the CAN twin, 1024 Hz) in this process. A
``rths-hil watch`` server follows its run directory from the start, and a headless Chromium
(the Debian ``chromium``) opens the page during every other segment of ``--segment`` seconds
of loop time and leaves it (``about:blank``) during the others, so the same run has steps with
and without a watcher attached. Driving the browser is a separate process (this script with
``--driver``), so nothing but the loop runs in the loop's process.

Measured:

* the loop's own work per step, from its send to the moment it was ready for the next step
  (``dt + ready[k+1] − lateness[k]``, as ``bench_loop.py``), p50 / p99 / p99.9, in the
  segments with and without the page (the first second of each segment left out: opening and
  closing the page); goal: p99 with the page within 2 % of p99 without;
* the page's refresh rate (refreshes the browser applied per second) and its lag behind the
  record: wall-clock time when the browser holds the row of loop time t minus the time that
  row was sent (``wall_t0 + t + lateness``, from the record); goals ≥ 5 Hz and ≤ 0.5 s.

Usage: ``python benchmarks/bench_watch.py [--duration 60] [--segment 10]``.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rths_hil.config import load_config
from rths_hil.loop import RTHSLoop

GOALS = (
    "- the loop's own work per step, p99, with the page open within 2 % of p99 without it "
    "(same run)\n- page refresh ≥ 5 Hz, lag behind the record ≤ 0.5 s"
)


def _wall_t0(run_dir: Path, timeout: float = 60.0) -> float:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            for line in (run_dir / "events.jsonl").read_text().splitlines():
                e = json.loads(line)
                if e.get("kind") == "clock":
                    return float(e["wall_t0"])
        except (OSError, ValueError):
            pass
        time.sleep(0.02)
    raise TimeoutError("the run never started")


def driver(run_dir: Path, url: str, duration: float, segment: float, out: Path) -> None:
    """Open and leave the page by segments of loop time; sample refresh and lag (own process)."""
    from rths_hil.watch.browser import Browser

    samples: list[tuple[float, float, int]] = []  # (wall time, page's last t, tick)
    with Browser(width=1200, height=1500) as b:
        w0 = _wall_t0(run_dir)
        n_seg = int(duration // segment)
        for i in range(n_seg):
            start = w0 + i * segment
            while time.time() < start:
                time.sleep(0.01)
            if i % 2 == 1:  # odd segments: the page is open
                b.goto(url)
                while time.time() < start + segment - 0.05:
                    try:
                        t_col = b.column("window", "t")
                        tick = b.model("tick", "start")
                    except RuntimeError:  # the page is still loading
                        t_col = tick = None
                    vals = (t_col[-1], tick) if t_col and tick is not None else None
                    if vals and vals[0] is not None:
                        samples.append((time.time(), float(vals[0]), int(vals[1])))
                    time.sleep(0.1)
            else:
                b.goto("about:blank")
    out.write_text(json.dumps(samples))


def _stats(x: np.ndarray) -> tuple[float, float, float]:
    p50, p99, p999 = np.percentile(x, [50, 99, 99.9])
    return float(p50), float(p99), float(p999)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="loop time of the run (s)")
    ap.add_argument("--segment", type=float, default=10.0, help="segment length (s)")
    ap.add_argument("--driver", nargs=4, metavar=("RUN", "URL", "DURATION", "SEGMENT"))
    ap.add_argument("--samples", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.driver:
        run, url, dur, seg = args.driver
        driver(Path(run), url, float(dur), float(seg), Path(args.samples))
        return

    tmp = Path(tempfile.mkdtemp(prefix="bench-watch-"))
    run_dir = tmp / "run"
    cfg = load_config(
        None,
        [
            f"loop.duration={args.duration}",
            "loop.console=0",
            "output.plot=false",
            # the benchmark measures time; a slow minute of the VM must not stop the run
            "safety.max_overruns=1000000",
            "safety.watchdog_missed=1000000",
        ],
    )
    watch = subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "watch", str(run_dir), "--port", "0", "--quiet"],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    line = watch.stderr.readline()
    m = re.search(r"(http://\S+)", line)
    if not m:
        raise SystemExit(f"rths-hil watch did not start: {line}")
    url = m.group(1)
    samples_path = tmp / "samples.json"
    drv = subprocess.Popen(
        [
            sys.executable,
            __file__,
            "--driver",
            str(run_dir),
            url,
            str(args.duration),
            str(args.segment),
            "--samples",
            str(samples_path),
        ]
    )
    try:
        loop = RTHSLoop(cfg, run_dir, mode="paced")
        res = loop.run()
        drv.wait(120)
    finally:
        for p in (drv, watch):
            if p.poll() is None:
                p.terminate()
                p.wait(10)

    dt = 1.0 / loop.fs
    lat, ready = res.lateness, res.ready
    work = (ready[1:] + dt - lat[:-1]) * 1e6  # µs, work of step k = 0 … n-2
    t = np.arange(work.size) * dt
    seg = (t // args.segment).astype(int)
    settled = (t - seg * args.segment) >= 1.0
    on = (seg % 2 == 1) & settled
    off = (seg % 2 == 0) & settled & (seg > 0)  # the first segment also has the warm-up
    w_on, w_off = _stats(work[on]), _stats(work[off])
    l_on, l_off = _stats(lat[:-1][on] * 1e6), _stats(lat[:-1][off] * 1e6)
    diff = 100.0 * (w_on[1] / w_off[1] - 1.0)

    # the page: refreshes applied per second and lag behind the record
    from rths_hil.recorder import read_run

    samples = json.loads(samples_path.read_text()) if samples_path.exists() else []
    rec = read_run(run_dir).record
    w0 = _wall_t0(run_dir)
    lags, rates = [], []
    by_seg: dict[int, list] = {}
    for wall, t_page, tick in samples:
        k = min(round(t_page * loop.fs), len(rec) - 1)
        lags.append(wall - (w0 + t_page + float(rec["lateness"][k])))
        by_seg.setdefault(int((wall - w0) // args.segment), []).append((wall, tick))
    for pts in by_seg.values():
        pts = [p for p in pts if p[0] - pts[0][0] >= 1.0]  # after the page has loaded
        if len(pts) > 2 and pts[-1][0] > pts[0][0]:
            rates.append((pts[-1][1] - pts[0][1]) / (pts[-1][0] - pts[0][0]))
    lags_a = np.array(lags) if lags else np.array([np.nan])

    from _results import markdown_table, write_results

    table = markdown_table(
        ["steps", "n", "work p50 µs", "work p99 µs", "work p99.9 µs", "lateness p99 µs"],
        [
            ["without the page", int(off.sum()), *(f"{v:.1f}" for v in w_off), f"{l_off[1]:.1f}"],
            ["with the page", int(on.sum()), *(f"{v:.1f}" for v in w_on), f"{l_on[1]:.1f}"],
        ],
    )
    table += (
        f"\n\nWork p99 with the page vs without: **{diff:+.2f} %** (goal ≤ 2 %).\n\n"
        + markdown_table(
            ["page", "value", "goal"],
            [
                ["refresh rate (applied by the browser)", f"{np.mean(rates):.1f} Hz", "≥ 5 Hz"],
                [
                    "lag behind the record, p50 / p95 / max",
                    f"{np.nanmedian(lags_a):.2f} / {np.nanpercentile(lags_a, 95):.2f} / "
                    f"{np.nanmax(lags_a):.2f} s",
                    "≤ 0.5 s",
                ],
            ],
        )
    )
    notes = (
        f"One paced run of {args.duration:g} s at {loop.fs:g} Hz ({res.steps} steps, "
        f"{res.overruns} overruns, status {res.status}); segments of {args.segment:g} s "
        "alternate without and with the page open in headless Chromium (the watcher's server "
        "runs throughout); the first second of each segment and the whole first segment are "
        "left out. Lag samples: the page's newest row polled 10 times a second over the "
        "DevTools protocol during the segments with the page. Both processes of the view "
        "(server, browser) share the machine's cores with the loop."
    )
    path = write_results("bench_watch", table, goals=GOALS, notes=notes)
    print(table)
    print(f"\nwritten to {path}")


if __name__ == "__main__":
    main()

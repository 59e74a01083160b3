"""Benchmark of ``rths-hil watch``: what watching costs the loop, and how live the page is.

Paced runs of the default test (NEES-711 over the CAN twin, 1024 Hz) in this process, in
``--blocks`` blocks of three runs: without a watcher; with ``rths-hil watch RUN_DIR`` serving
but no page open (the operator looks from another machine); with the page open in a headless
Chromium (the Debian ``chromium``) on this machine, waiting for the run when its clock starts
(between runs the browser shows ``about:blank``). Blocks alternate in order (ABBA: none, served,
page, page, served, none, …) so that a drift of the machine falls on every condition. Driving
the browser is a separate process (this script with ``--driver``), so nothing but the loop runs
in the loop's process.

The loop is pinned to one CPU (``loop.cpu``, ``--pin``; default the last CPU) and runs at
SCHED_FIFO priority 10; the watcher is started the way ``rths-hil run --watch`` starts it (off
the loop's CPU; it runs at nice 10), and so is the browser (an operator's browser on the same
machine, kept off the loop's CPU).

Measured:

* the loop's own work per step (``RunResult.work``: from the moment every reply has arrived to
  the end of the step, as ``bench_loop.py``), p50 / p99 / p99.9 per condition (the first second
  of each run left out); goal: p99 with a watcher within 2 % of p99 without. Reported: the
  pooled p99s, each block's ratio (watched run over the block's run without a watcher), and —
  as the machine's own noise — the ratio of the back-to-back runs without a watcher where one
  block ends and the next begins (A vs A′), each with median and range. The step's busy time
  (send to ready for the next step, including the wait for the twin's reply) is shown beside;
* the page's refresh rate (refreshes the browser applied per second) and its lag behind the
  record: wall-clock time when the browser holds the row of loop time t minus the time that
  row was sent (``wall_t0 + t + lateness``, from the record); goals ≥ 5 Hz and ≤ 0.5 s.

With ``--baseline REV`` each block also has a run watched by the watcher of git revision REV
(exported with ``git archive``), so that the page's cost per refresh before and after a change
is measured in the same invocation, as a ratio.

Usage: ``python benchmarks/bench_watch.py [--duration 15] [--blocks 6] [--pin CPU]
[--baseline REV]``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rths_hil.cli.run import _keep_off
from rths_hil.config import load_config
from rths_hil.hybrid import RTHSLoop
from rths_hil.records.recorder import read_run

GOALS = (
    "- the loop's own work per step, p99, with a watcher and its page within 2 % of p99 "
    "without\n- page refresh ≥ 5 Hz, lag behind the record ≤ 0.5 s"
)


def _wall_t0(run_dir: Path) -> float:
    for line in (run_dir / "events.jsonl").read_text().splitlines():
        e = json.loads(line)
        if e.get("kind") == "clock":
            return float(e["wall_t0"])
    raise ValueError("no clock event")


def tree_cpu(pid: int) -> float:
    """CPU time (s, user + system) of process ``pid`` and all its descendants (Linux)."""
    stats: dict[int, tuple[int, float]] = {}  # pid -> (parent, cpu seconds)
    tick = os.sysconf("SC_CLK_TCK")
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        stats[int(d)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / tick)
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        total += stats.get(p, (0, 0.0))[1]
        todo += [c for c, (parent, _) in stats.items() if parent == p]
    return total


def driver() -> None:
    """Browser process: ``open URL`` → page loaded → ``ready``, samples until ``blank``."""
    from rths_hil.watch.browser import Browser

    def say(text: str) -> None:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()

    with Browser(width=1200, height=1500) as b:
        say("started")
        for line in sys.stdin:
            cmd, _, arg = line.strip().partition(" ")
            if cmd != "open":
                break
            b.goto(arg)
            b.wait_for(
                "!!(window.Bokeh && Bokeh.documents.length && "
                "Bokeh.documents[0].get_model_by_name('state'))",
                timeout=120,
            )
            cpu0 = tree_cpu(b.proc.pid)
            say("ready")
            samples: list[tuple[float, float, float]] = []  # (wall time, page's last t, tick)
            while not select.select([sys.stdin], [], [], 0.1)[0]:
                try:
                    got = b.eval(_PROBE)
                except RuntimeError:
                    continue
                if got:
                    samples.append((time.time(), float(got[0]), float(got[1])))
            sys.stdin.readline()  # "blank"
            cpu = tree_cpu(b.proc.pid) - cpu0
            b.goto("about:blank")
            say(json.dumps({"samples": samples, "cpu": cpu}))


# the page's newest row and its refresh counter, in one small evaluation (not the whole column)
_PROBE = """(() => {
  const d = window.Bokeh && Bokeh.documents[0];
  const w = d && d.get_model_by_name('window'), k = d && d.get_model_by_name('tick');
  if (!w || !k) return null;
  const t = w.data.get ? w.data.get('t') : w.data['t'];
  return t && t.length ? [t[t.length - 1], k.start] : null;
})()"""


def _stats(x: np.ndarray) -> tuple[float, float, float]:
    p50, p99, p999 = np.percentile(x, [50, 99, 99.9])
    return float(p50), float(p99), float(p999)


def _watched(
    cfg,
    run_dir: Path,
    drv: subprocess.Popen,
    tree: Path | None = None,
    pin: int = -1,
    page: bool = True,
):
    """One run with ``rths-hil watch`` (of ``tree``, else this one), the page open or not."""
    watch = subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "watch", str(run_dir), "--port", "0", "--quiet"],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        cwd=tree,  # ``-m`` imports rths_hil from the working directory first
        preexec_fn=functools.partial(_keep_off, pin),  # as ``rths-hil run --watch``
    )
    try:
        line = watch.stderr.readline()
        m = re.search(r"(http://\S+)", line)
        if not m:
            raise SystemExit(f"rths-hil watch did not start: {line}")
        if not page:  # served, nobody looking
            return RTHSLoop(cfg, run_dir, mode="paced").run(), [], 0.0, 0.0
        drv.stdin.write(f"open {m.group(1)}\n")
        drv.stdin.flush()
        if drv.stdout.readline().strip() != "ready":
            raise SystemExit("the browser did not open the page")
        cpu0 = tree_cpu(watch.pid)
        res = RTHSLoop(cfg, run_dir, mode="paced").run()
        server_cpu = tree_cpu(watch.pid) - cpu0
        drv.stdin.write("blank\n")
        drv.stdin.flush()
        out = json.loads(drv.stdout.readline())
    finally:
        watch.terminate()
        watch.wait(10)
    return res, out["samples"], out["cpu"], server_cpu


def main() -> None:  # noqa: C901
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=15.0, help="loop time of each run (s)")
    ap.add_argument(
        "--blocks", type=int, default=6, help="blocks of one run per condition (ABBA order)"
    )
    ap.add_argument(
        "--pin",
        type=int,
        default=max(os.sched_getaffinity(0)) if len(os.sched_getaffinity(0)) > 1 else -1,
        metavar="CPU",
        help="loop.cpu of the runs (-1: not pinned); default the last CPU",
    )
    ap.add_argument(
        "--baseline",
        metavar="REV",
        help="also watch runs with the watcher of this git revision (CPU per refresh ratio)",
    )
    ap.add_argument("--driver", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.driver:
        driver()
        return

    load0 = os.getloadavg()[0]
    tmp = Path(tempfile.mkdtemp(prefix="bench-watch-"))
    base_tree = None
    if args.baseline:
        base_tree = tmp / "baseline"
        base_tree.mkdir()
        root = Path(__file__).resolve().parent.parent
        archive = subprocess.run(
            ["git", "-C", str(root), "archive", args.baseline],
            capture_output=True,
            check=False,
        )
        if archive.returncode != 0:
            raise SystemExit(f"--baseline {args.baseline}: {archive.stderr.decode().strip()}")
        subprocess.run(["tar", "-x", "-C", str(base_tree)], input=archive.stdout, check=True)
    cfg = load_config(
        None,
        [
            f"loop.duration={args.duration}",
            "loop.console=0",
            "output.plot=false",
            # the benchmark measures time; a slow minute of the VM must not stop a run
            "safety.max_overruns=1000000",
            "safety.watchdog_missed=1000000",
            f"loop.cpu={args.pin}",
        ],
    )
    drv = subprocess.Popen(
        [sys.executable, __file__, "--driver"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=functools.partial(_keep_off, args.pin),
    )
    conds = ("none", "served", "this")  # no watcher; watcher, no page; watcher + page open
    work: dict[str, list[np.ndarray]] = {c: [] for c in conds}
    busy: dict[str, list[np.ndarray]] = {c: [] for c in conds}
    late: dict[str, list[np.ndarray]] = {c: [] for c in conds}
    p99_seq: list[tuple[str, float]] = []  # (condition, work p99) per run, in run order
    # per watcher (this one, the baseline): browser s, server s, refreshes, wall s
    cpu: dict[str, list[tuple[float, float, float, float]]] = {"this": [], "baseline": []}
    lags: dict[str, list[float]] = {"this": [], "baseline": []}
    rates: dict[str, list[float]] = {"this": [], "baseline": []}
    runs = []
    try:
        if drv.stdout.readline().strip() != "started":
            raise SystemExit("the browser did not start")
        order = [*conds] + (["baseline"] if base_tree else [])
        plan = [w for p in range(args.blocks) for w in (order if p % 2 == 0 else order[::-1])]
        for i, who in enumerate(plan):
            watched = who != "none"
            run_dir = tmp / f"run{i}"
            if watched:
                tree = base_tree if who == "baseline" else None
                res, samples, b_cpu, s_cpu = _watched(
                    cfg, run_dir, drv, tree, args.pin, page=who != "served"
                )
                if samples:
                    n_ref = samples[-1][2] - samples[0][2]
                    cpu[who].append((b_cpu, s_cpu, n_ref, res.wall_time))
            else:
                res, samples = RTHSLoop(cfg, run_dir, mode="paced").run(), []
            runs.append(res)
            if who == "baseline":
                res = None  # the loop's cost is compared between no watcher and this one
            fs = runs[-1].fs
            if res is not None:
                dt = 1.0 / res.fs
                b = (res.ready[1:] + dt - res.lateness[:-1]) * 1e6  # µs, send to ready
                keep = np.arange(b.size) * dt >= 1.0
                w = np.asarray(res.work[:-1])[keep] * 1e6  # µs, the loop's own work
                work[who].append(w)
                busy[who].append(b[keep])
                late[who].append(res.lateness[:-1][keep] * 1e6)
                p99_seq.append((who, float(np.percentile(w, 99))))
            if samples:
                rec = read_run(run_dir).record
                w0 = _wall_t0(run_dir)
                s = [x for x in samples if x[1] >= 1.0]  # once the run is under way
                for wall, t_page, _ in s:
                    k = min(round(t_page * fs), len(rec) - 1)
                    lags[who].append(wall - (w0 + t_page + float(rec["lateness"][k])))
                if len(s) > 2 and s[-1][0] > s[0][0]:
                    rates[who].append((s[-1][2] - s[0][2]) / (s[-1][0] - s[0][0]))
    finally:
        if drv.poll() is None:
            drv.stdin.close()
            drv.terminate()
            drv.wait(10)
        if base_tree is not None:
            shutil.rmtree(base_tree, ignore_errors=True)

    w = {c: _stats(np.concatenate(work[c])) for c in conds}
    b = {c: _stats(np.concatenate(busy[c])) for c in conds}
    lt = {c: _stats(np.concatenate(late[c])) for c in conds}
    diff = {c: 100.0 * (w[c][1] / w["none"][1] - 1.0) for c in conds[1:]}
    # per block (ABBA over the conditions: each block has one run of each), each watched
    # run's p99 over the block's run without a watcher; and A vs A′, the back-to-back runs
    # without a watcher where one block ends and the next begins
    size = len(conds)
    ratios: dict[str, list[float]] = {c: [] for c in conds[1:]}
    for i in range(0, len(p99_seq) - size + 1, size):
        block = dict(p99_seq[i : i + size])
        for c in conds[1:]:
            ratios[c].append(block[c] / block["none"])
    noise = [
        p99_seq[i + 1][1] / p99_seq[i][1]
        for i in range(len(p99_seq) - 1)
        if p99_seq[i][0] == "none" and p99_seq[i + 1][0] == "none"
    ]

    def spread(r: list[float], what: str = "block") -> str:
        if not r:
            return "–"
        pct = [100.0 * (x - 1.0) for x in r]
        if len(r) == 1:
            return f"{pct[0]:+.1f} % (1 {what})"
        return (
            f"median {np.median(pct):+.1f} % (range {min(pct):+.1f} … {max(pct):+.1f} %, "
            f"{len(r)} {what}s)"
        )

    from _results import markdown_table, write_results

    def page(who: str) -> dict[str, float]:
        c = cpu[who]
        n = max(sum(x[2] for x in c), 1)
        wall = max(sum(x[3] for x in c), 1e-9)
        lg = np.array(lags[who]) if lags[who] else np.array([np.nan])
        return {
            "rate": float(np.mean(rates[who])) if rates[who] else float("nan"),
            "b_ref": 1e3 * sum(x[0] for x in c) / n,
            "s_ref": 1e3 * sum(x[1] for x in c) / n,
            "b_share": 100 * sum(x[0] for x in c) / wall,
            "s_share": 100 * sum(x[1] for x in c) / wall,
            "lag": (np.nanmedian(lg), np.nanpercentile(lg, 95), np.nanmax(lg)),
        }

    names = {
        "none": "without a watcher",
        "served": "watcher serving, no page open",
        "this": "watcher + page open in the browser",
    }
    table = markdown_table(
        [
            "runs",
            "steps",
            "work p50 µs",
            "work p99 µs",
            "work p99.9 µs",
            "busy p99 µs",
            "lateness p99 µs",
        ],
        [
            [
                names[c],
                sum(x.size for x in work[c]),
                *(f"{v:.1f}" for v in w[c]),
                f"{b[c][1]:.1f}",
                f"{lt[c][1]:.1f}",
            ]
            for c in conds
        ],
    )
    whos = ["this"] + (["baseline"] if base_tree else [])
    pages = {w: page(w) for w in whos}
    head = ["page", "value", "goal"]
    label = {"this": "", "baseline": f" (baseline {args.baseline})"}
    rows = []
    for w in whos:
        pg, lb = pages[w], label[w]
        rows += [
            [f"refresh rate (applied by the browser){lb}", f"{pg['rate']:.1f} Hz", "≥ 5 Hz"],
            [
                f"CPU per refresh: browser / watcher server{lb}",
                f"{pg['b_ref']:.0f} / {pg['s_ref']:.0f} ms",
                "",
            ],
            [
                f"CPU while watching: browser / watcher server (share of one core){lb}",
                f"{pg['b_share']:.0f} % / {pg['s_share']:.0f} %",
                "",
            ],
            [
                f"lag behind the record, p50 / p95 / max{lb}",
                " / ".join(f"{v:.2f}" for v in pg["lag"]) + " s",
                "≤ 0.5 s",
            ],
        ]
    table += (
        "\n\nWork p99 against the runs without a watcher (goal: within 2 %):\n\n"
        f"- watcher serving, no page open: pooled **{diff['served']:+.2f} %**; per block "
        f"{spread(ratios['served'])}\n"
        f"- watcher + page open in the browser on this machine: pooled "
        f"**{diff['this']:+.2f} %**; per block {spread(ratios['this'])}\n"
        f"- the machine's own noise, A vs A′ (two back-to-back runs without a watcher): "
        f"{spread(noise, 'pair')}\n\n" + markdown_table(head, rows)
    )
    if base_tree:
        ratio = pages["this"]["b_ref"] / pages["baseline"]["b_ref"]
        table += (
            f"\n\nBrowser CPU per refresh, this watcher / baseline {args.baseline}: "
            f"**{ratio:.2f}**."
        )
    base = (
        f", and in each block a run watched by the watcher of {args.baseline} (the baseline)"
        if base_tree
        else ""
    )
    notes = (
        f"{len(runs)} paced runs of {args.duration:g} s at {runs[0].fs:g} Hz in ABBA blocks: "
        "without a watcher, with `rths-hil watch` serving and no page open, and with its page "
        f"open in headless Chromium on the same machine{base}; loop on CPU {args.pin} "
        "(`loop.cpu`; -1 = not pinned), SCHED_FIFO, the watcher and the browser started off "
        "that CPU as `rths-hil run --watch` starts the watcher "
        f"(overruns per run: {', '.join(str(r.overruns) for r in runs)}); the "
        "first second of each run is left out. Lag samples: the page's newest row, polled 10 "
        "times a second over the DevTools protocol (one small evaluation; the polling is "
        "itself a load on the browser). CPU: user + system time of the browser's processes and "
        "of the watcher's server process while the watched runs ran, divided by the refreshes "
        "the browser applied: what a refresh costs whatever else the machine is doing. Load "
        f"average of the machine (1 min, {os.cpu_count()} cores): {load0:.1f} before, "
        f"{os.getloadavg()[0]:.1f} after."
    )
    path = write_results("bench_watch", table, goals=GOALS, notes=notes)
    print(table)
    print(f"\nwritten to {path}")


if __name__ == "__main__":
    main()

"""The bridge against controllers written independently of it: the conformance partners.

Each partner runs as its own process with its own plant in real time (12 ms delay, 8 ms lag,
gain 0.98, 1e6 N/m): the Modbus TCP servo controller (``tests/partners/modbus_servo.py``: its own
register map, one transaction at a time, 20–40 ms pauses of its network stack) and the CiA 402
drive (``tests/partners/cia402_drive.py``: a fixed PDO mapping, over python-can's ``serial``
interface on a pseudo-terminal pair). For each partner:

1. its raw round trip, measured in the same run with the protocol's own library and nothing of
   the bridge: pymodbus's client doing the step's two transactions one at a time (FC 16 the
   set-point, FC 4 the measurement block), or ``canopen`` sending the RPDO and the SYNC and
   waiting for the TPDO;
2. ``rths-hil commission`` once (the partner disabled, then the motion and plant steps): the
   identified delay, lag and gain are written to ``tuned.toml``;
3. paced runs of the default test at 512, 1024 and 2048 Hz with ``include = ["tuned.toml"]``,
   each against a fresh partner: completed or tripped (and why), missed replies and the longest
   reply gap, the whole-record FEI of measured vs target (A, d), the bridge's own reply time per
   step (send to reply, the record's ``feedback_time``) next to the raw round trip, and the
   work-caused overruns the runner attributes.

Usage: ``python benchmarks/bench_partners.py [--runs 3] [--duration 10] [--rates 512,1024,2048]``
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from tests.partners.canopen_fixtures import DrivePartner  # noqa: E402
from tests.partners.modbus_fixtures import PROFILE, ServoPartner  # noqa: E402

CLI = "import sys; from rths_hil.cli import main; sys.exit(main(sys.argv[1:]))"


# ----------------------------------------------------------------------------------------------
# the partners as the bridge sees them
def modbus_config(partner: ServoPartner) -> str:
    return (
        '[driver]\nname = "modbus"\n'
        f'profile = "{PROFILE}"\n'
        f'connection = {{ host = "127.0.0.1", port = {partner.port} }}\n'
    )


def canopen_config(partner: DrivePartner) -> str:
    return f'[driver]\nname = "canopen"\nconnection = {partner.toml_connection()}\n'


PARTNERS: dict[str, dict[str, Any]] = {
    "Modbus TCP servo (one transaction at a time)": {
        "start": lambda tmp: ServoPartner(tmp),
        "config": modbus_config,
    },
    "CiA 402 drive, fixed mapping (serial pty)": {
        "start": lambda tmp: DrivePartner(tmp, "serial"),
        "config": canopen_config,
    },
}


# ----------------------------------------------------------------------------------------------
# raw round trips with the protocol's own library
def modbus_round_trip(partner: ServoPartner, n: int) -> list[float]:
    """``n`` step-like exchanges with pymodbus's client: FC 16 (the set-point, 0.0 mm: the
    partner is disabled and holds) then FC 4 (the measurement block), one at a time."""
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient("127.0.0.1", port=partner.port, timeout=0.2, retries=0)
    if not client.connect():
        raise RuntimeError("cannot connect to the Modbus partner")
    words = list(struct.unpack(">HH", struct.pack(">f", 0.0)))
    times = []
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            try:
                w = client.write_registers(1024, words)
                r = client.read_input_registers(2048, count=5)
            except Exception:  # a request the partner dropped (one of its pauses)
                client.close()
                client.connect()
                continue
            if not (w.isError() or r.isError()):
                times.append(time.perf_counter() - t0)
    finally:
        client.close()
    return times


def canopen_round_trip(partner: DrivePartner, n: int) -> list[float]:
    """``n`` step-like exchanges with the ``canopen`` library: NMT operational, then per step
    the RPDO (control word 0x0006: shutdown, no motion; target 0) and the SYNC, timed to the
    drive's TPDO1."""
    import canopen

    from tests.partners.canopen_fixtures import BUS_OPTIONS

    net = canopen.Network()
    net.connect(
        interface=partner.interface,
        channel=partner.cable.bridge_path,
        **BUS_OPTIONS[partner.interface],
    )
    got = threading.Event()
    nid = partner.node_id
    net.subscribe(0x180 + nid, lambda *_: got.set())
    times = []
    try:
        net.send_message(0x000, bytes((0x01, nid)))  # NMT start
        time.sleep(0.2)
        rpdo = struct.pack("<Hi", 0x0006, 0)
        for _ in range(n):
            got.clear()
            t0 = time.perf_counter()
            net.send_message(0x200 + nid, rpdo)
            net.send_message(0x80, b"")
            if got.wait(0.1):
                times.append(time.perf_counter() - t0)
        net.send_message(0x000, bytes((0x80, nid)))  # back to pre-operational
        time.sleep(0.05)
    finally:
        net.disconnect()
    return times


ROUND_TRIP = {
    "Modbus TCP servo (one transaction at a time)": modbus_round_trip,
    "CiA 402 drive, fixed mapping (serial pty)": canopen_round_trip,
}


# ----------------------------------------------------------------------------------------------
def _cli(*args: str, timeout: float, answers: int = 0) -> subprocess.CompletedProcess:
    """``rths-hil ARGS`` in its own process; ``answers``: an operator at a terminal who types
    'yes' that many times (commissioning hardware asks before each motion)."""
    if not answers:
        return subprocess.run(
            [sys.executable, "-c", CLI, *args], capture_output=True, text=True, cwd=ROOT,
            timeout=timeout,
        )  # fmt: skip
    import pty

    master, slave = pty.openpty()
    try:
        os.write(master, b"yes\n" * answers)  # the terminal's line discipline keeps them
        return subprocess.run(
            [sys.executable, "-c", CLI, *args], stdin=slave, capture_output=True, text=True,
            cwd=ROOT, timeout=timeout,
        )  # fmt: skip
    finally:
        os.close(slave)
        os.close(master)


def commission(label: str, tmp: Path) -> tuple[Path | None, str]:
    """Commission a fresh partner at 512 Hz; the tuned fragment (or None) and a one-line note."""
    spec = PARTNERS[label]
    tmp.mkdir(parents=True, exist_ok=True)
    partner = spec["start"](tmp)
    try:
        cfg = tmp / "commission.toml"
        cfg.write_text(spec["config"](partner) + "[loop]\nfs = 512\n[twin]\nenabled = false\n")
        out = tmp / "commission"
        p = _cli("commission", str(cfg), "--confirm-hardware", "--out", str(out), timeout=300,
                 answers=20)  # fmt: skip
    finally:
        partner.stop()
    tuned = sorted(out.rglob("tuned.toml"))
    lines = (p.stdout + p.stderr).strip().splitlines()
    verdict = lines[-1].split(";")[0].replace("rths-hil commission: ", "") if lines else ""
    verdict = verdict or f"exit {p.returncode}"
    failed = [ln.split(": ", 2)[-1] for ln in lines if ": failed" in ln]
    if failed:
        verdict += " (" + "; ".join(failed) + ")"
    identified = ""
    if tuned:  # the fragment's own summary line: "# actuator: delay …, lag …, gain … (fit …)"
        for ln in tuned[-1].read_text().splitlines():
            if ln.startswith("# ") and "delay" in ln and "gain" in ln:
                identified = ln[2:].split(";")[0]
    return (tuned[-1] if tuned else None), f"{verdict} | {identified or '–'}"


def paced_run(label: str, tuned: Path | None, fs: int, duration: float, tmp: Path) -> dict:
    """One paced run of the default test against a fresh partner: its figures."""
    spec = PARTNERS[label]
    tmp.mkdir(parents=True, exist_ok=True)
    partner = spec["start"](tmp)
    try:
        cfg = tmp / f"run-{fs}.toml"
        include = f'include = ["{tuned}"]\n' if tuned is not None else ""
        cfg.write_text(include + spec["config"](partner) + "[twin]\nenabled = false\n")
        out = tmp / f"run-{fs}"
        p = _cli("run", str(cfg), "--paced", "--duration", f"{duration:g}", "--set",
                 f"loop.fs={fs}", "--confirm-hardware", "--no-plot", "-q", "--out", str(out),
                 timeout=duration * 4 + 120)  # fmt: skip
        final = partner.stop()
    finally:
        partner.stop()
    path = out / "summary.json"
    if not path.is_file():
        tail = (p.stdout + p.stderr).strip().splitlines()
        return {"status": f"no summary (exit {p.returncode})", "why": tail[-1] if tail else ""}
    s = json.loads(path.read_text())
    from rths_hil.records.recorder import read_run

    rec = read_run(out).record
    link = ""  # the link check at arming: the share of the period a step's requests take
    for line in (out / "events.jsonl").read_text().splitlines():
        e = json.loads(line)
        if e.get("kind") == "link":
            m = re.search(r"(\d+) % of the", e.get("warning", ""))
            link = f"warned ({m.group(1)} %)" if m else "warned"
    ft = np.asarray(rec["feedback_time"], dtype=float)
    ft = ft[np.isfinite(ft)]
    trip = s.get("trip") or {}
    fei = s.get("fei_target") or {}
    gaps = s.get("reply_gaps") or {}
    return {
        "status": s["status"],
        "exit": p.returncode,
        "why": trip.get("reason", "") if isinstance(trip, dict) else str(trip),
        "steps": s["steps"],
        "planned": s.get("planned_steps") or s["steps"],
        "missed": s.get("missed_replies", 0),
        "longest_gap": gaps.get("longest", 0.0),
        "A": fei.get("amplitude", float("nan")) if fei.get("valid") else float("nan"),
        "d": fei.get("delay", float("nan")) if fei.get("valid") else float("nan"),
        "reply_p50": float(np.percentile(ft, 50)) if ft.size else float("nan"),
        "reply_p99": float(np.percentile(ft, 99)) if ft.size else float("nan"),
        "work": (s.get("overrun_causes") or {}).get("work", 0),
        "link": link or "–",
        # the replies the partner's own network-stack pauses cost (Modbus partner): no bridge
        # can have them; a pause of T s costs about T·fs + 1 replies
        "paused": final.get("pause_time", 0.0) * fs + final.get("pauses", 0),
        "handed_back": (
            f"status 0x{final['status']:02X}" if "status" in final else str(final.get("state"))
        ),
    }


def _ms(x: float) -> str:
    return "–" if x != x else f"{x * 1e3:.2f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="paced runs per partner and rate")
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run")
    ap.add_argument("--rates", default="512,1024,2048", help="loop rates (Hz)")
    ap.add_argument("--round-trips", type=int, default=1000, help="raw exchanges per partner")
    args = ap.parse_args(argv)
    rates = [int(r) for r in args.rates.split(",")]
    base = Path(tempfile.mkdtemp(prefix="bench-partners-"))
    rows, rtt_rows, tuned_rows = [], [], []
    for i, label in enumerate(PARTNERS):
        tmp = base / f"p{i}"
        tmp.mkdir()
        partner = PARTNERS[label]["start"](tmp)
        try:
            rt = ROUND_TRIP[label](partner, args.round_trips)
        finally:
            partner.stop()
        rt_p50 = statistics.median(rt) if rt else float("nan")
        rt_p99 = float(np.percentile(rt, 99)) if rt else float("nan")
        rtt_rows.append([label, len(rt), args.round_trips, _ms(rt_p50), _ms(rt_p99),
                         _ms(max(rt) if rt else float("nan"))])  # fmt: skip
        print(f"{label}: raw round trip p50 {_ms(rt_p50)} ms, p99 {_ms(rt_p99)} ms", flush=True)
        tuned, note = commission(label, tmp / "c")
        tuned_text = tuned.read_text() if tuned is not None else ""
        verdict, identified = note.split(" | ", 1)
        tuned_rows.append([label, verdict.replace("|", "/"), identified.replace("|", "/")])
        print(f"{label}: commission: {note}", flush=True)
        for fs in rates:
            results = []
            for r in range(args.runs):
                res = paced_run(label, tuned, fs, args.duration, tmp / f"{fs}-{r}")
                results.append(res)
                print(f"{label} {fs} Hz run {r}: {res}", flush=True)
            done = sum(1 for x in results if x["status"] == "completed")
            steps = sum(x.get("steps", 0) for x in results)
            missed = sum(x.get("missed", 0) for x in results)
            paused = sum(min(x.get("paused", 0.0), x.get("missed", 0)) for x in results)
            a = [x["A"] for x in results if x.get("A", float("nan")) == x.get("A")]
            d = [x["d"] for x in results if x.get("d", float("nan")) == x.get("d")]
            whys = sorted({x["why"] for x in results if x.get("why")})
            rows.append([
                label, fs, f"{done}/{len(results)}",
                f"{100 * missed / steps:.2f} %" if steps else "–",
                f"{100 * (missed - paused) / steps:.2f} %" if steps else "–",
                _ms(max((x.get("longest_gap", 0.0) for x in results), default=float("nan"))),
                f"{statistics.median(a):.4f}" if a else "–",
                _ms(statistics.median(d)) if d else "–",
                _ms(statistics.median([x.get("reply_p50", float("nan")) for x in results])),
                _ms(max((x.get("reply_p99", float("nan")) for x in results), default=float("nan"))),
                _ms(rt_p50),
                ", ".join(sorted({str(x.get("link", "–")) for x in results})),
                sum(x.get("work", 0) for x in results),
                ", ".join(sorted({str(x.get("handed_back")) for x in results})),
                "; ".join(w[:90].replace("|", "/") for w in whys) or "–",
            ])  # fmt: skip
        if tuned_text:
            print(f"{label}: tuned.toml:\n{tuned_text}", flush=True)
    from _results import markdown_table, write_results

    table = "### Raw round trip (the protocol's own library, nothing of the bridge)\n\n"
    table += markdown_table(
        ["partner", "answered", "sent", "p50 (ms)", "p99 (ms)", "max (ms)"], rtt_rows
    )
    table += "\n\n### Commissioning (512 Hz; the plant of 12 ms, 8 ms, 0.98)\n\n" + markdown_table(
        ["partner", "verdict", "identified (tuned.toml)"], tuned_rows
    )
    table += "\n\n### Paced runs of the default test with the fragment included\n\n"
    table += markdown_table(
        ["partner", "fs (Hz)", "completed", "missed replies", "missed beyond the partner's "
         "pauses", "longest gap (ms)", "FEI A",
         "FEI d (ms)", "bridge reply p50 (ms)", "bridge reply p99 (ms)", "raw round trip p50 "
         "(ms)", "link check at arming", "work-caused overruns", "partner at the end", "trips"],
        rows,
    )  # fmt: skip
    write_results(
        "bench_partners",
        table,
        title="The bridge against conformance partners (controllers written apart from it)",
        goals="Modbus partner: paced 20 s runs at 512 Hz complete with ≤ 0.5 % missed replies; "
        "at 1024 Hz runs complete with the missed replies as degradation (≤ 5 %). The first "
        "test after commissioning tracks within |A − 1| ≤ 1 %, |d| ≤ 1 ms.",
        command=f"python benchmarks/bench_partners.py --runs {args.runs} --duration "
        f"{args.duration:g} --rates {args.rates}",
        notes="Each paced run is `rths-hil run --paced` in its own process against a fresh "
        "partner process (the partner's plant at rest), the configuration the partner's "
        "connection plus `include = [tuned.toml]` from one `rths-hil commission` of that "
        "partner. `bridge reply` is the record's `feedback_time`: from the step's send to its "
        "reply, as the loop sees it; the raw round trip is the same exchange done by the "
        "protocol's library alone, in the same run. FEI of measured vs target over the whole "
        "record (median of the runs). The Modbus partner pauses its network stack 20–40 ms "
        "0.5 times a second (Poisson): a pause of T s costs about T·fs + 1 replies to any "
        "client, 1.5 % of them at its default rate; `missed beyond the partner's pauses` takes "
        "those (summed from the partner's own account of its pauses) out. `link check at "
        "arming`: whether `run` warned that a step's one-at-a-time requests fill more than "
        "75 % of the period (at the round trip the driver timed when it opened), and by how "
        "much. "
        "Load average at the end: "
        f"{os.getloadavg()[0]:.1f} (1 min) on {os.cpu_count()} cores.",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

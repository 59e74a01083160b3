"""Two Modbus channels in lockstep: one TCP connection (units 1 and 2) against two connections.

``examples/modbus_units.toml`` (two actuators on a 3-storey building, units 1 and 2 of one twin
server on 127.0.0.1) run in lockstep, alternately as written (one server, one connection; the
two FC 23 requests of a step pipelined) and with ``driver.connection.port = 0`` (each channel's
twin on a port of its own, one connection each). Same process, same run, interleaved repeats;
the table gives the median steps/s of each and their ratio.

Run: ``.venv/bin/python benchmarks/bench_modbus_units.py [--seconds 5] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import write_results  # noqa: E402

from rths_hil.config import load_config  # noqa: E402
from rths_hil.hybrid import RTHSLoop  # noqa: E402

EXAMPLE = ROOT / "examples" / "modbus_units.toml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_once(shared: bool, seconds: float, out: Path) -> float:
    """Steps/s of one lockstep run."""
    port = _free_port() if shared else 0
    over = ["loop.console=0", "output.plot=false", f"driver.connection.port={port}"]
    loop = RTHSLoop(load_config(EXAMPLE, over), out, mode="lockstep", duration=seconds)
    res = loop.run()
    if res.status != "completed" or res.missed_replies:
        raise SystemExit(f"run did not complete: {res.status}, {res.missed_replies} missed")
    if shared:
        a, b = loop.channels
        assert a.twin.server is b.twin.server and a.twin.server.accepted == 1
    else:
        assert loop.channels[0].twin.server is not loop.channels[1].twin.server
    return res.steps_per_second


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rates: dict[bool, list[float]] = {True: [], False: []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for shared in (True, False):
                sps = run_once(shared, args.seconds, Path(tmp) / f"{r}-{shared}")
                rates[shared].append(sps)
                print(
                    f"repeat {r}: {'one connection' if shared else 'two connections'} "
                    f"{sps:,.0f} steps/s",
                    flush=True,
                )
    one, two = statistics.median(rates[True]), statistics.median(rates[False])
    table = (
        "| two Modbus TCP channels, lockstep | steps/s (median) | runs |\n"
        "|---|---|---|\n"
        f"| one connection, units 1 and 2 (pipelined) | {one:,.0f} | "
        f"{', '.join(f'{x:,.0f}' for x in rates[True])} |\n"
        f"| two connections (a server each) | {two:,.0f} | "
        f"{', '.join(f'{x:,.0f}' for x in rates[False])} |\n"
        f"| ratio one / two | {one / two:.2f} | |\n"
    )
    print(table)
    write_results(
        "bench_modbus_units",
        table,
        title="Two Modbus channels: one TCP connection against two",
        command=f"benchmarks/bench_modbus_units.py --seconds {args.seconds:g} "
        f"--repeats {args.repeats}",
        notes=f"examples/modbus_units.toml, {args.seconds:g} simulated s per run at 1024 Hz, "
        "twins in-process (one thread per unit), same process and run, runs interleaved; "
        f"load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end.",
    )


if __name__ == "__main__":
    main()

"""Round-trip latency of each driver against its twin, beside the raw transport, in one run.

For every transport three round trips are timed, interleaved block by block so that they share
the machine's load:

``raw``
    the bare transport: precomputed bytes of the same size as one command go to a thread that
    answers with precomputed bytes of the same size as one feedback (no encode/decode on either
    side, no plant);
``raw→twin``
    precomputed command frames (built before timing) sent to the real twin, the answer read by
    length/delimiter but not decoded: the transport plus the twin, without the driver;
``driver``
    ``driver.send(k, x)`` + ``driver.receive(timeout)`` against the same twin.

Driver overhead = driver vs raw→twin (what our encode/decode/bookkeeping adds); stack overhead =
driver vs raw (driver and twin). Goals: driver overhead ≤ 30 %; p99 ≤ 300 µs for Modbus
TCP and ≤ 150 µs for CAN virtual and serial. The garbage collector is disabled inside the timed
blocks, as the real-time loop does. Usage::

    .venv/bin/python benchmarks/bench_drivers.py [--steps 4000] [--rounds 8] [--json out.json]
    .venv/bin/python benchmarks/bench_drivers.py --profile-only   # the profile table only
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import select
import socket
import sys
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import can
from rths_hil.drivers.can.codec import load as load_dbc
from rths_hil.drivers.modbus.driver import _TCP_REQ, READ_ADDRESS, READ_COUNT, WRITE_ADDRESS
from rths_hil.drivers.registry import create_driver
from rths_hil.drivers.serial.framing import COMMAND, T_COMMAND, encode_frame
from rths_hil.sim_backends.twin import default_plant, start_twin

Step = Callable[[int], None]
GOALS_P99 = {"can-virtual": 150e-6, "modbus-tcp": 300e-6, "serial-pty": 150e-6}
TIMEOUT = 0.5


class Echo(threading.Thread):
    """A thread answering each request on ``fd`` with fixed bytes (raw transport peer)."""

    def __init__(self, fd: int, reply: bytes, request_size: int | None, delimiter: bool) -> None:
        super().__init__(daemon=True)
        self.fd, self.reply, self.size, self.delim = fd, reply, request_size, delimiter
        self.stop = False

    def run(self) -> None:
        buf = b""
        while not self.stop:
            if not select.select((self.fd,), (), (), 0.05)[0]:
                continue
            try:
                buf += os.read(self.fd, 4096)
            except OSError:
                return
            while True:
                if self.delim:
                    if b"\x00" not in buf:
                        break
                    buf = buf.split(b"\x00", 1)[1]
                else:
                    if len(buf) < self.size:
                        break
                    buf = buf[self.size :]
                os.write(self.fd, self.reply)


def read_exact(fd: int, n: int) -> None:
    got = 0
    while got < n:
        select.select((fd,), (), (), TIMEOUT)
        got += len(os.read(fd, n - got))


def read_frame(fd: int) -> None:
    while True:
        select.select((fd,), (), (), TIMEOUT)
        if os.read(fd, 4096).endswith(b"\x00"):
            return


# -- CAN ----------------------------------------------------------------------------------------
def can_modes(n: int) -> dict[str, tuple[Step, Callable[[], None]]]:
    codecs = load_dbc()
    cmd_id, fb_id = codecs.command.frame_id, codecs.feedback.frame_id
    # raw: 8-byte frame in, 8-byte frame out
    a = can.Bus(interface="virtual", channel="bench-raw")
    b = can.Bus(interface="virtual", channel="bench-raw")
    reply = can.Message(arbitration_id=fb_id, data=bytes(8), is_extended_id=False)
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            if b.recv(0.05) is not None:
                b.send(reply)

    th = threading.Thread(target=echo, daemon=True)
    th.start()
    request = can.Message(arbitration_id=cmd_id, data=bytes(8), is_extended_id=False)

    def raw(_k: int) -> None:
        a.send(request)
        a.recv(TIMEOUT)

    def raw_close() -> None:
        stop.set()
        th.join()
        a.shutdown()
        b.shutdown()

    twin = start_twin("can", default_plant())
    c = can.Bus(interface="virtual", channel=twin.connection["channel"])
    frames = [
        can.Message(
            arbitration_id=cmd_id,
            data=codecs.command.pack(k & 0xFFFF, round(0.001 * np.sin(k / 50) / 1e-7), 1),
            is_extended_id=False,
        )
        for k in range(n)
    ]

    def raw_twin(k: int) -> None:
        c.send(frames[k])
        c.recv(TIMEOUT)

    def raw_twin_close() -> None:
        c.shutdown()
        twin.stop()

    twin2 = start_twin("can", default_plant())  # its own bus: no cross-talk with raw→twin
    drv = create_driver("can", **twin2.connection)
    drv.open()
    return {
        "raw": (raw, raw_close),
        "raw→twin": (raw_twin, raw_twin_close),
        "driver": (_driver_step(drv), lambda: (drv.close(), twin2.stop())),
    }


def _driver_step(drv) -> Step:
    send, receive = drv.send, drv.receive
    sin = math.sin

    def step(k: int) -> None:
        send(k, 0.001 * sin(k / 50))
        if receive(TIMEOUT) is None:
            raise RuntimeError(f"timeout at step {k}: {drv.stats}")

    return step


# -- Modbus TCP / RTU ---------------------------------------------------------------------------
def _modbus_requests(n: int, rtu: bool) -> list[bytes]:
    from pymodbus.framer import FramerRTU, FramerSocket
    from pymodbus.pdu import DecodePDU
    from pymodbus.pdu.register_message import ReadWriteMultipleRegistersRequest

    framer = (FramerRTU if rtu else FramerSocket)(DecodePDU(False))
    out = []
    for k in range(n):
        raw = round(0.001 * np.sin(k / 50) / 1e-7) & 0xFFFFFFFF
        req = ReadWriteMultipleRegistersRequest(
            read_address=READ_ADDRESS,
            read_count=READ_COUNT,
            write_address=WRITE_ADDRESS,
            write_registers=[k & 0xFFFF, 1, raw >> 16, raw & 0xFFFF],
            dev_id=1,
            transaction_id=k & 0xFFFF,
        )
        out.append(framer.buildFrame(req))
    return out


def modbus_tcp_modes(n: int) -> dict[str, tuple[Step, Callable[[], None]]]:
    req_size, resp_size = _TCP_REQ.size, 23
    lst = socket.create_server(("127.0.0.1", 0))
    cli = socket.create_connection(lst.getsockname()[:2])
    srv, _ = lst.accept()
    for s in (cli, srv):
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    echo = Echo(srv.fileno(), bytes(resp_size), req_size, delimiter=False)
    echo.start()
    payload = bytes(req_size)
    cfd = cli.fileno()

    def raw(_k: int) -> None:
        os.write(cfd, payload)
        read_exact(cfd, resp_size)

    def raw_close() -> None:
        echo.stop = True
        echo.join()
        for s in (cli, srv, lst):
            s.close()

    twin = start_twin("modbus", default_plant())
    conn = twin.connection
    t = socket.create_connection((conn["host"], conn["port"]))
    t.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    tfd = t.fileno()
    frames = _modbus_requests(n, rtu=False)

    def raw_twin(k: int) -> None:
        os.write(tfd, frames[k])
        read_exact(tfd, resp_size)

    def raw_twin_close() -> None:
        t.close()
        twin.stop()

    twin2 = start_twin("modbus", default_plant())
    drv = create_driver("modbus", **twin2.connection)
    drv.open()
    return {
        "raw": (raw, raw_close),
        "raw→twin": (raw_twin, raw_twin_close),
        "driver": (_driver_step(drv), lambda: (drv.close(), twin2.stop())),
    }


def _pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    return master, slave, os.ttyname(slave)


def modbus_rtu_modes(n: int) -> dict[str, tuple[Step, Callable[[], None]]]:
    req_size, resp_size = 21, 19  # FC 23 RTU request / response with CRC
    master, slave, path = _pty()
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    echo = Echo(master, bytes(resp_size), req_size, delimiter=False)
    echo.start()
    payload = bytes(req_size)

    def raw(_k: int) -> None:
        os.write(fd, payload)
        read_exact(fd, resp_size)

    def raw_close() -> None:
        echo.stop = True
        echo.join()
        for f in (fd, master, slave):
            os.close(f)

    twin = start_twin("modbus", default_plant(), transport="rtu")
    tfd = os.open(twin.connection["device"], os.O_RDWR | os.O_NOCTTY)
    frames = _modbus_requests(n, rtu=True)

    def raw_twin(k: int) -> None:
        os.write(tfd, frames[k])
        read_exact(tfd, resp_size)

    def raw_twin_close() -> None:
        os.close(tfd)
        twin.stop()

    twin2 = start_twin("modbus", default_plant(), transport="rtu")
    drv = create_driver("modbus", **twin2.connection)
    drv.open()
    return {
        "raw": (raw, raw_close),
        "raw→twin": (raw_twin, raw_twin_close),
        "driver": (_driver_step(drv), lambda: (drv.close(), twin2.stop())),
    }


# -- serial -------------------------------------------------------------------------------------
def serial_modes(n: int) -> dict[str, tuple[Step, Callable[[], None]]]:
    from rths_hil.drivers.serial.framing import FEEDBACK, T_FEEDBACK

    command = encode_frame(COMMAND.pack(T_COMMAND, 1, 1, 0.001))
    reply = encode_frame(FEEDBACK.pack(T_FEEDBACK, 1, 1, 0.001, 1.0))
    master, slave, path = _pty()
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    echo = Echo(master, reply, None, delimiter=True)
    echo.start()

    def raw(_k: int) -> None:
        os.write(fd, command)
        read_frame(fd)

    def raw_close() -> None:
        echo.stop = True
        echo.join()
        for f in (fd, master, slave):
            os.close(f)

    twin = start_twin("serial", default_plant())
    tfd = os.open(twin.connection["url"], os.O_RDWR | os.O_NOCTTY)
    tty.setraw(tfd)
    frames = [encode_frame(COMMAND.pack(T_COMMAND, k, 1, 0.001 * np.sin(k / 50))) for k in range(n)]

    def raw_twin(k: int) -> None:
        os.write(tfd, frames[k])
        read_frame(tfd)

    def raw_twin_close() -> None:
        os.close(tfd)
        twin.stop()

    twin2 = start_twin("serial", default_plant())
    drv = create_driver("serial", **twin2.connection)
    drv.open()
    return {
        "raw": (raw, raw_close),
        "raw→twin": (raw_twin, raw_twin_close),
        "driver": (_driver_step(drv), lambda: (drv.close(), twin2.stop())),
    }


# -- CANopen (CiA 402 twin, virtual bus) -------------------------------------------------------
def canopen_modes(n: int) -> dict[str, tuple[Step, Callable[[], None]]]:
    """Per step RPDO1 (6 bytes) + SYNC in, TPDO1 (6) + TPDO2 (4) out."""
    a = can.Bus(interface="virtual", channel="bench-canopen-raw")
    b = can.Bus(interface="virtual", channel="bench-canopen-raw")
    out = [
        can.Message(arbitration_id=0x181, data=bytes(6), is_extended_id=False),
        can.Message(arbitration_id=0x281, data=bytes(4), is_extended_id=False),
    ]
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            msg = b.recv(0.05)
            if msg is not None and msg.arbitration_id == 0x80:
                for m in out:
                    b.send(m)

    th = threading.Thread(target=echo, daemon=True)
    th.start()
    rpdo = can.Message(arbitration_id=0x201, data=bytes(6), is_extended_id=False)
    sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)

    def raw(_k: int) -> None:
        a.send(rpdo)
        a.send(sync)
        a.recv(TIMEOUT)
        a.recv(TIMEOUT)

    def raw_close() -> None:
        stop.set()
        th.join()
        a.shutdown()
        b.shutdown()

    # raw→twin: a driver configures the twin (SDO, NMT) and enables it, then steps stop going
    # through it: precomputed RPDO1 + SYNC frames, the two TPDOs read but not decoded
    twin = start_twin("canopen", default_plant())
    cfg = create_driver("canopen", **twin.connection)
    cfg.open()
    cfg.arm(1.0)
    for k in range(5):
        cfg.send(k, 0.0)
        cfg.receive(TIMEOUT)
    c = can.Bus(interface="virtual", channel=twin.connection["channel"])
    frames = [
        can.Message(
            arbitration_id=0x201,
            data=(0x0F).to_bytes(2, "little")
            + round(0.001 * math.sin(k / 50) * 1e7).to_bytes(4, "little", signed=True),
            is_extended_id=False,
        )
        for k in range(n)
    ]

    def raw_twin(k: int) -> None:
        c.send(frames[k])
        c.send(sync)
        got = 0
        while got < 2:
            msg = c.recv(TIMEOUT)
            if msg is None:
                raise RuntimeError(f"raw→twin: no TPDO at step {k}")
            got += msg.arbitration_id in (0x181, 0x281)

    def raw_twin_close() -> None:
        c.shutdown()
        cfg.close()
        twin.stop()

    twin2 = start_twin("canopen", default_plant())
    drv = create_driver("canopen", **twin2.connection)
    drv.open()
    drv.arm(1.0)
    return {
        "raw": (raw, raw_close),
        "raw→twin": (raw_twin, raw_twin_close),
        "driver": (_driver_step(drv), lambda: (drv.close(), twin2.stop())),
    }


TRANSPORTS = {
    "can-virtual": can_modes,
    "canopen-virtual": canopen_modes,
    "modbus-tcp": modbus_tcp_modes,
    "serial-pty": serial_modes,
    "modbus-rtu": modbus_rtu_modes,
}


def measure(name: str, steps: int, rounds: int) -> dict[str, dict[str, float]]:
    """Interleave the three modes in ``rounds`` blocks; return µs statistics per mode."""
    modes = TRANSPORTS[name](steps + 100)  # precomputed frames: warm-up + timed steps
    block = steps // rounds
    samples: dict[str, list[float]] = {m: [] for m in modes}
    counters = dict.fromkeys(modes, 0)
    clock = time.perf_counter
    try:
        for m, (step, _) in modes.items():  # warm-up
            for _ in range(50):
                step(counters[m])
                counters[m] += 1
        for _ in range(rounds):
            for m, (step, _) in modes.items():
                out = samples[m]
                k = counters[m]
                gc.collect()
                gc.disable()
                try:
                    for i in range(k, k + block):
                        t0 = clock()
                        step(i)
                        out.append(clock() - t0)
                finally:
                    gc.enable()
                counters[m] = k + block
    finally:
        for _, close in modes.values():
            close()
    stats = {}
    for m, xs in samples.items():
        a = np.asarray(xs) * 1e6
        stats[m] = {
            "median_us": float(np.median(a)),
            "p99_us": float(np.percentile(a, 99)),
            "max_us": float(a.max()),
            "n": len(a),
        }
    return stats


CONTROLLERS = Path(__file__).resolve().parents[1] / "examples" / "controllers"
#: The profile drivers beside the built-in drivers: label → (driver, twin/driver settings).
PROFILE_MODES: dict[str, tuple[str, dict]] = {
    "can (built-in)": ("can", {}),
    "can profile (own DBC)": ("can", {"profile": str(CONTROLLERS / "can_dbc.toml")}),
    "modbus (built-in)": ("modbus", {"port": 0}),
    "modbus profile (own map)": (
        "modbus",
        {"port": 0, "profile": str(CONTROLLERS / "modbus_map.toml")},
    ),
    # the same map with [modbus] pipeline = false: FC 16 and FC 4 one at a time
    "modbus profile, one at a time": ("modbus", {"port": 0, "profile": "<one-at-a-time>"}),
    "canopen CiA 402": ("canopen", {"device_profile": "cia402"}),
    "canopen CiA 408": ("canopen", {"device_profile": "cia408"}),
}
PROFILE_GOAL = 1.5


def profile_work(steps: int, rounds: int) -> dict[str, dict[str, float]]:
    """Loop work per step of each driver in :data:`PROFILE_MODES`, interleaved in one run.

    Loop work = CPU time of the calling thread (``time.thread_time``) in ``send`` + ``receive``
    per step: the encoding, decoding, bookkeeping and transport calls the loop's thread pays,
    not the wait for the reply nor the twin (its own thread, the same plant everywhere). The
    modes run in ``rounds`` interleaved blocks; a mode's ratio to the CAN driver is the median
    of its per-round ratios (each against the CAN block of the same round, so that a change of
    the machine's load between rounds cancels).
    """
    live = {}
    tmp = tempfile.TemporaryDirectory()
    one_at_a_time = Path(tmp.name) / "modbus_map_one_at_a_time.toml"
    one_at_a_time.write_text(
        (CONTROLLERS / "modbus_map.toml")
        .read_text()
        .replace("unit = 1\n", "unit = 1\npipeline = false\n")
    )
    try:
        for label, (name, conn) in PROFILE_MODES.items():
            conn = dict(conn)
            if conn.get("profile") == "<one-at-a-time>":
                conn["profile"] = str(one_at_a_time)
            twin = start_twin(name, default_plant(), **conn)
            drv = create_driver(name, **twin.connection)
            drv.open()
            drv.arm(1.0)
            live[label] = (twin, drv, [0], [], [])
        block = steps // rounds
        for _ in range(rounds):
            for _twin, drv, k, cpu, wall in live.values():
                gc.collect()
                gc.disable()
                try:
                    c0, w0 = time.thread_time(), time.perf_counter()
                    for i in range(k[0], k[0] + block):
                        drv.send(i, 0.001 * math.sin(i / 50.0), True)
                        if drv.receive(TIMEOUT) is None:
                            raise RuntimeError(f"{drv.name}: no reply to step {i}")
                    cpu.append((time.thread_time() - c0) / block)
                    wall.append((time.perf_counter() - w0) / block)
                finally:
                    gc.enable()
                k[0] += block
    finally:
        for twin, drv, *_ in live.values():
            drv.close()
            twin.stop()
        tmp.cleanup()
    ref = np.asarray(live["can (built-in)"][3])
    out = {}
    for label, (_, _, _, cpu, wall) in live.items():
        c = float(np.median(cpu))
        ratios = np.asarray(cpu) / ref
        out[label] = {"work_us": c * 1e6, "round_trip_us": float(np.median(wall)) * 1e6,
                      "vs_can": float(np.median(ratios)),
                      "vs_can_range": (float(ratios.min()), float(ratios.max()))}  # fmt: skip
    return out


PROFILE_HEADER = [
    "driver",
    "loop work µs/step",
    "vs CAN built-in",
    "per round",
    "round trip µs (median)",
    "goal",
]
PROFILE_HEADING = "### Profile drivers: loop work per step (examples/controllers)"


def profile_rows(prof: dict[str, dict[str, float]]) -> list[list[object]]:
    """The profile table's rows (printed as they are made)."""
    rows: list[list[object]] = []
    for label, r in prof.items():
        verdict = ""
        if "profile" in label or label.startswith("canopen"):
            verdict = f"≤ {PROFILE_GOAL:g}×: {'met' if r['vs_can'] <= PROFILE_GOAL else 'NOT met'}"
        lo, hi = r["vs_can_range"]
        print(f"{label:26s} work {r['work_us']:7.1f} µs/step ({r['vs_can']:.2f}× CAN, rounds "
              f"{lo:.2f}–{hi:.2f}), round trip {r['round_trip_us']:7.1f} µs {verdict}")  # fmt: skip
        rows.append(
            [label, f"{r['work_us']:.1f}", f"{r['vs_can']:.2f}×", f"{lo:.2f}–{hi:.2f}",
             f"{r['round_trip_us']:.1f}", verdict]
        )  # fmt: skip
    return rows


def update_profile_table(rows: list[list[object]], note: str) -> None:
    """``--profile-only``: replace the profile table of ``results/bench_drivers.md`` (from its
    heading to the next section) and keep the rest of the file: the round-trip table, the
    machine and the notes of the last full run; ``note`` (how this table was made) follows
    the table. Without that file, print only."""
    from _results import RESULTS_DIR, markdown_table

    path = RESULTS_DIR / "bench_drivers.md"
    text = path.read_text() if path.exists() else ""
    start = text.find(PROFILE_HEADING)
    end = text.find("\n## ", start)
    if start < 0 or end < 0:
        print(f"{path}: no profile table to update; run the whole benchmark to write it")
        return
    table = markdown_table(PROFILE_HEADER, rows)
    path.write_text(f"{text[:start]}{PROFILE_HEADING}\n\n{table}\n\n{note}\n{text[end:]}")
    print(f"updated the profile table of {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=4000, help="round trips per mode")
    ap.add_argument("--rounds", type=int, default=8, help="interleaved blocks")
    ap.add_argument("--only", choices=sorted(TRANSPORTS), action="append")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--profile-steps", type=int, default=4000, help="steps per profile-driver mode")
    ap.add_argument(
        "--profile-rounds", type=int, default=16, help="interleaved blocks of the profile table"
    )
    ap.add_argument(
        "--profile-only",
        action="store_true",
        help="only the profile table (loop work per step): prints it and replaces it in "
        "results/bench_drivers.md, keeping the rest of the file",
    )
    args = ap.parse_args(argv)
    if args.profile_only:
        rows = profile_rows(profile_work(args.profile_steps, args.profile_rounds))
        update_profile_table(
            rows,
            "This table alone: `python benchmarks/bench_drivers.py --profile-only --profile-steps "
            f"{args.profile_steps} --profile-rounds {args.profile_rounds}` (load average "
            f"{os.getloadavg()[0]:.1f}, 1 min, on {os.cpu_count()} cores).",
        )
        return 0
    results = {}
    rows: list[list[object]] = []
    print(f"{'transport':15s} {'mode':9s} {'median µs':>10s} {'p99 µs':>8s} {'max µs':>8s}")
    for name in args.only or list(TRANSPORTS):
        st = measure(name, args.steps, args.rounds)
        results[name] = st
        for m, s in st.items():
            print(f"{name:15s} {m:9s} {s['median_us']:10.1f} {s['p99_us']:8.1f} {s['max_us']:8.0f}")
        drv, twin, raw = st["driver"], st["raw→twin"], st["raw"]
        over_twin = drv["median_us"] / twin["median_us"] - 1
        over_raw = drv["median_us"] / raw["median_us"] - 1
        goal = GOALS_P99.get(name)
        verdict = ""
        if goal is not None:
            ok = drv["p99_us"] <= goal * 1e6 and over_twin <= 0.30
            verdict = (
                f"  goal p99 ≤ {goal * 1e6:.0f} µs, overhead ≤ 30 %: {'met' if ok else 'NOT met'}"
            )
        print(
            f"{'':12s} driver overhead (median) vs raw→twin {over_twin:+.0%}, "
            f"vs raw transport {over_raw:+.0%}{verdict}"
        )
        st["overhead_vs_raw_twin"] = over_twin  # type: ignore[assignment]
        st["overhead_vs_raw"] = over_raw  # type: ignore[assignment]
        goal_text = "–" if goal is None else f"≤ {goal * 1e6:.0f} µs: {'met' if ok else 'NOT met'}"
        for m in ("raw", "raw→twin", "driver"):
            s = st[m]
            rows.append(
                [
                    name,
                    m,
                    f"{s['median_us']:.1f}",
                    f"{s['p99_us']:.1f}",
                    f"{s['max_us']:.0f}",
                    f"{over_twin:+.0%}" if m == "driver" else "",
                    goal_text if m == "driver" else "",
                ]
            )
    prof = profile_work(args.profile_steps, args.profile_rounds)
    results["profiles"] = prof
    prof_rows = profile_rows(prof)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    from _results import markdown_table, write_results

    header = [
        "transport",
        "mode",
        "median µs",
        "p99 µs",
        "max µs",
        "driver vs raw→twin",
        "p99 goal",
    ]
    prof_table = markdown_table(PROFILE_HEADER, prof_rows)
    write_results(
        "bench_drivers",
        markdown_table(header, rows)
        + "\n\n### Profile drivers: loop work per step (examples/controllers)\n\n"
        + prof_table,
        title="Round trips of each driver against its twin",
        goals="Driver overhead (median, driver vs raw→twin) ≤ 30 %; driver p99 ≤ 300 µs for "
        "Modbus TCP and ≤ 150 µs for CAN virtual and serial. Profile drivers: loop work per "
        f"step ≤ {PROFILE_GOAL:g}× the built-in CAN driver's in the same run.",
        command=f"python benchmarks/bench_drivers.py --steps {args.steps} --rounds {args.rounds} "
        f"--profile-steps {args.profile_steps} --profile-rounds {args.profile_rounds}",
        notes="`raw`: the bare transport with payloads of the same sizes; `raw→twin`: "
        "precomputed frames to the real twin without the driver; `driver`: `driver.send` + "
        "`driver.receive` against the same twin. Modes are interleaved block by block so that "
        "they share the machine's load; the garbage collector is off in the timed blocks. "
        "Profile table: loop work = CPU time of the calling thread (`time.thread_time`) in "
        "`send` + `receive` per step against threaded twins (the twin's own work excluded), "
        "interleaved in blocks; `vs CAN built-in` = median over the blocks of the ratio to the "
        "CAN driver's block of the same round (`per round`: their range); round trip = wall "
        "time per step. Load average while measuring: "
        f"{os.getloadavg()[0]:.1f} (1 min) on {os.cpu_count()} cores.",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

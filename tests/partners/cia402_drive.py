"""A CiA 402 servo drive (cyclic synchronous position) as its own process: a conformance partner.

Written from CiA 301 / CiA 402 and from how a real drive with a *fixed* PDO mapping behaves, not
from the project's driver or twins (it imports nothing of the project). Its "manual" is its EDS,
``vendor_cia402.eds`` beside this file:

* RPDO1 (0x200 + node) = controlword 0x6040 + target position 0x607A; TPDO1 (0x180 + node) =
  statusword 0x6041 + position actual 0x6064 + torque actual 0x6077; no TPDO2. The mapping
  objects 0x1600 / 0x1A00 are read-only: a write is refused with SDO abort 0x06010002, as a
  drive whose firmware fixes the mapping does. The communication parameters (COB-ID, valid bit,
  transmission type) are writable.
* Position unit 1 µm (``--counts-per-m``, 1e6); torque actual 0x6077 in per mille of the motor
  rated torque 0x6076 (for this linear drive the rated *force*, in mN).
* RPDOs of a synchronous transmission type (0–240) are applied level-wise at every SYNC (the
  last received value, whether or not a new one came); TPDO1 of type 1–240 is sent every n-th
  SYNC with the values sampled at that SYNC. PDOs only in NMT OPERATIONAL. Writing 0x6040 by SDO
  acts at once.
* The CiA 402 state machine as the standard has it, one transition per evaluation (so 0x0F from
  READY TO SWITCH ON only reaches SWITCHED ON); quick stop (0x605A option 5–8 stays in QUICK
  STOP ACTIVE, 1–4 goes on to SWITCH ON DISABLED); fault reset on the rising edge of bit 7.
* Heartbeat producer 0x1017 (the library's NMT slave), heartbeat consumer 0x1016:01 (monitoring
  starts at the first heartbeat of the producer): when it runs out the drive enters FAULT,
  sends EMCY 0x8130 and records it in the pre-defined error field 0x1003 (newest at sub 1;
  writing 0 to 0x1003:00 clears it).
* Its own plant in real time, stepped every millisecond by its own thread: 12 ms transport
  delay, 8 ms first-order lag, gain 0.98 on the motion from where it was enabled, on a specimen
  of 1e6 N/m; the torque actual is the specimen force in per mille of 0x6076. Outside OPERATION
  ENABLED (and when commands stop) the axis holds where it is.
* ``--answer-delay`` holds each TPDO back that long (in order): a link whose answers trail the
  SYNCs, as a loaded adapter's do.

Run::

    python tests/partners/cia402_drive.py --interface serial --channel /dev/pts/7 --node-id 5 \
        --state-file state.json

It prints ``READY <json>`` on stdout once it listens, and on SIGTERM / SIGINT writes its state
(statusword, state, position, error field, EMCY codes sent, enable edges with the motion in the
50 ms after each, counters) to ``--state-file`` and as a ``STATE <json>`` line.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import threading
import time
from collections import deque
from typing import Any

import canopen
from canopen.sdo import SdoAbortedError

EDS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "vendor_cia402.eds")

# CiA 402 statusword of each state (bits 0-3, 5, 6: the codes of CiA 402 Table 30), with bit 4
# voltage enabled in the powered states and bit 9 remote always
SW = {
    "NOT READY TO SWITCH ON": 0x0000,
    "SWITCH ON DISABLED": 0x0040,
    "READY TO SWITCH ON": 0x0021,
    "SWITCHED ON": 0x0033,
    "OPERATION ENABLED": 0x0037,
    "QUICK STOP ACTIVE": 0x0017,
    "FAULT REACTION ACTIVE": 0x001F,
    "FAULT": 0x0008,
}
REMOTE = 0x0200
CSP_FOLLOWS = 0x1000  # statusword bit 12 in CSP: the drive follows the command value
ABORT_READ_ONLY = 0x06010002
ABORT_VALUE_RANGE = 0x06090030
EMCY_HEARTBEAT = 0x8130
ERR_REG_COMMUNICATION = 0x10
ERR_REG_GENERIC = 0x01


def command(cw: int) -> str:
    """The CiA 402 device control command coded by controlword ``cw`` (bits 0-3, 7)."""
    if cw & 0x02 == 0:
        return "disable voltage"
    if cw & 0x04 == 0:
        return "quick stop"
    if cw & 0x01 == 0:
        return "shutdown"
    if cw & 0x08 == 0:
        return "switch on"  # also "disable operation" from OPERATION ENABLED
    return "enable operation"  # "switch on + enable operation"


class Plant:
    """The axis in real time: delay, first-order lag and gain on the motion from the position
    where it was enabled; a linear specimen. Positions in m, forces in N."""

    def __init__(self, delay: float, tau: float, gain: float, stiffness: float, x0: float):
        self.delay, self.tau, self.gain, self.k = delay, tau, gain, stiffness
        self.x = x0
        self.t = time.monotonic()
        self.enabled = False
        self.base = x0  # where it was enabled
        self.u: float | None = None  # the delayed demand acting now (None: none yet, hold)
        self.demand: deque[tuple[float, float]] = deque()  # (time, commanded position)

    def enable(self, on: bool, now: float) -> None:
        self.advance(now)
        if on and not self.enabled:
            self.base = self.x
        self.demand.clear()  # enabled: a fresh demand; disabled: hold where it is
        self.u = None
        self.enabled = on

    def command(self, target: float, now: float) -> None:
        if self.enabled:
            self.demand.append((now, target))

    def advance(self, now: float) -> None:
        """Integrate up to ``now`` in steps of at most 1 ms (exact first-order lag)."""
        d = self.demand
        while self.t < now:
            dt = min(0.001, now - self.t)
            self.t += dt
            if not self.enabled:
                continue
            while d and d[0][0] <= self.t - self.delay:
                self.u = d.popleft()[1]
            if self.u is None:
                continue
            goal = self.base + self.gain * (self.u - self.base)
            self.x += (1.0 - math.exp(-dt / self.tau)) * (goal - self.x)

    def force(self) -> float:
        return self.k * self.x


class Drive:
    """The CiA 402 drive on a :class:`canopen.LocalNode`."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.lock = threading.RLock()
        self.network = canopen.Network()
        self.node = canopen.LocalNode(args.node_id, args.eds)
        self.state = "NOT READY TO SWITCH ON"
        self.cw = 0
        self.target = 0
        self.mode = int(self.node.object_dictionary[0x6060].default or 0)
        self.errors: list[int] = []  # 0x1003, newest first
        self.error_register = 0
        self.emcy_sent: list[int] = []
        self.plant = Plant(args.delay, args.tau, args.gain, args.stiffness, args.position)
        self.syncs = 0
        self.rpdos = 0
        self.tpdos = 0
        self.rpdo_data: bytes | None = None
        self.rpdo_cob: int | None = None
        self.lagged: deque[tuple[float, int, bytes]] = deque()  # TPDOs held (--answer-delay)
        self.hb_consumer: tuple[int, float] | None = None  # (producer node, time s)
        self.hb_seen: float | None = None
        self.edges: list[dict[str, Any]] = []
        #: (from, to, what caused it: "rpdo", "sdo" or "drive")
        self.transitions: list[tuple[str, str, str]] = []
        self.via = "drive"
        self.stop = threading.Event()

    # -- object dictionary ------------------------------------------------------------------
    def on_read(self, index: int, subindex: int, od: Any) -> Any:
        with self.lock:
            if index == 0x6041:
                return self.statusword()
            if index == 0x6064:
                self.plant.advance(time.monotonic())
                return self.counts()
            if index == 0x6077:
                self.plant.advance(time.monotonic())
                return self.torque()
            if index == 0x6061:
                return self.mode
            if index == 0x6040:
                return self.cw
            if index == 0x607A:
                return self.target
            if index == 0x1001:
                return self.error_register
            if index == 0x1003:
                if subindex == 0:
                    return len(self.errors)
                return self.errors[subindex - 1] if subindex <= len(self.errors) else 0
        return None

    def on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        value = od.decode_raw(data)
        with self.lock:
            if index == 0x6040:
                self.via = "sdo"
                self.cw_in(value, time.monotonic())
            elif index == 0x607A:
                self.target = value
            elif index == 0x6060:
                if value not in (1, 8):  # profile position, cyclic synchronous position
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
                self.mode = value
                self.update_plant(time.monotonic())
            elif index == 0x1003 and subindex == 0:
                if value != 0:
                    raise SdoAbortedError(ABORT_VALUE_RANGE)  # CiA 301: only 0 (clear)
                self.errors.clear()
                self.error_register = 0
            elif index == 0x1016 and subindex == 1:
                node, ms = (value >> 16) & 0x7F, value & 0xFFFF
                self.hb_consumer = (node, ms / 1000.0) if node and ms else None
                self.hb_seen = None  # monitoring starts at the first heartbeat
            elif index in (0x1400, 0x1800) and subindex == 2:
                if not (value <= 240 or value >= 254):
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
            elif index in (0x1600, 0x1A00):  # pragma: no cover - the EDS has them read-only
                raise SdoAbortedError(ABORT_READ_ONLY)

    def pdo_param(self, index: int, sub: int) -> int:
        return int(self.node.sdo[index][sub].raw)

    # -- CiA 402 ----------------------------------------------------------------------------
    def statusword(self) -> int:
        sw = SW[self.state] | REMOTE
        if self.state == "OPERATION ENABLED" and self.mode == 8:
            sw |= CSP_FOLLOWS
        return sw

    def counts(self) -> int:
        c = round(self.plant.x * self.args.counts_per_m)
        return max(-(2**31), min(2**31 - 1, c))

    def torque(self) -> int:
        rated_n = int(self.node.sdo[0x6076].raw) / 1000.0
        t = round(1000.0 * self.plant.force() / rated_n) if rated_n else 0
        return max(-32768, min(32767, t))

    def go(self, new: str, now: float) -> None:
        old = self.state
        if new == old:
            return
        self.transitions.append((old, new, self.via))
        self.state = new
        self.update_plant(now)

    def update_plant(self, now: float) -> None:
        """The plant follows the target only in OPERATION ENABLED with CSP (mode 8)."""
        enabled = self.state == "OPERATION ENABLED" and self.mode == 8
        if enabled and not self.plant.enabled:
            self.plant.enable(True, now)
            self.edges.append({"t": now, "x": self.plant.x, "max_dev_50ms": 0.0})
        elif not enabled and self.plant.enabled:
            self.plant.enable(False, now)

    def cw_in(self, cw: int, now: float) -> None:  # noqa: C901 - the standard's table
        """One evaluation of the controlword (CiA 402 Figure 'state machine', transitions 2-16)."""
        old_cw, self.cw = self.cw, cw
        s = self.state
        cmd = command(cw)
        if s in ("FAULT",):
            if cw & 0x80 and not old_cw & 0x80:  # 15: fault reset, rising edge of bit 7
                self.go("SWITCH ON DISABLED", now)
            return
        if s == "FAULT REACTION ACTIVE" or s == "NOT READY TO SWITCH ON":
            return
        if s == "SWITCH ON DISABLED":
            if cmd == "shutdown":
                self.go("READY TO SWITCH ON", now)  # 2
        elif s == "READY TO SWITCH ON":
            if cmd in ("switch on", "enable operation"):
                self.go("SWITCHED ON", now)  # 3 (one transition per evaluation)
            elif cmd in ("disable voltage", "quick stop"):
                self.go("SWITCH ON DISABLED", now)  # 7
        elif s == "SWITCHED ON":
            if cmd == "enable operation":
                self.go("OPERATION ENABLED", now)  # 4
            elif cmd == "shutdown":
                self.go("READY TO SWITCH ON", now)  # 6
            elif cmd in ("disable voltage", "quick stop"):
                self.go("SWITCH ON DISABLED", now)  # 10
        elif s == "OPERATION ENABLED":
            if cmd == "switch on":
                self.go("SWITCHED ON", now)  # 5 disable operation
            elif cmd == "shutdown":
                self.go("READY TO SWITCH ON", now)  # 8
            elif cmd == "disable voltage":
                self.go("SWITCH ON DISABLED", now)  # 9
            elif cmd == "quick stop":
                self.go("QUICK STOP ACTIVE", now)  # 11
                if int(self.node.sdo[0x605A].raw) in (1, 2, 3, 4):
                    self.go("SWITCH ON DISABLED", now)  # 12 once stopped (stops at once here)
        elif s == "QUICK STOP ACTIVE":
            if cmd == "disable voltage":
                self.go("SWITCH ON DISABLED", now)  # 12
            elif cmd == "enable operation" and int(self.node.sdo[0x605A].raw) in (5, 6, 7, 8):
                self.go("OPERATION ENABLED", now)  # 16

    def fault(self, code: int, register: int, now: float) -> None:
        """Enter FAULT (through FAULT REACTION ACTIVE: the axis holds), record and send EMCY."""
        if self.state in ("FAULT", "FAULT REACTION ACTIVE"):
            return
        self.via = "drive"
        self.go("FAULT REACTION ACTIVE", now)
        self.go("FAULT", now)
        self.errors.insert(0, code)
        del self.errors[8:]
        self.error_register |= register | ERR_REG_GENERIC
        self.emcy_sent.append(code)
        self.node.emcy.send(code, self.error_register)

    # -- bus --------------------------------------------------------------------------------
    def on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        now = time.monotonic()
        with self.lock:
            if self.node.nmt.state != "OPERATIONAL":
                return
            self.syncs += 1
            rp = self.node.rpdo[1]
            if rp.enabled and self.rpdo_data is not None and (rp.trans_type or 0) <= 240:
                self.apply_rpdo(self.rpdo_data, now)  # level-wise: the last one, every SYNC
            self.plant.advance(now)
            tp = self.node.tpdo[1]
            n = tp.trans_type or 0
            if tp.enabled and 1 <= n <= 240 and self.syncs % n == 0:
                self.send_tpdo(tp)

    def apply_rpdo(self, data: bytes, now: float) -> None:
        rp = self.node.rpdo[1]
        rp.data = bytearray(data)
        values = {(v.index, v.subindex): v.raw for v in rp.map}
        if (0x607A, 0) in values:
            self.target = values[(0x607A, 0)]
        if (0x6040, 0) in values:
            self.via = "rpdo"
            self.cw_in(values[(0x6040, 0)], now)
        if self.state == "OPERATION ENABLED":
            self.plant.command(self.target / self.args.counts_per_m, now)

    def on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.lock:
            rp = self.node.rpdo[1]
            if self.node.nmt.state != "OPERATIONAL" or not rp.enabled:
                return
            if len(data) < rp.length // 8:
                return  # too short: not processed (CiA 301 would send EMCY 0x8210)
            self.rpdos += 1
            self.rpdo_data = bytes(data)
            if (rp.trans_type or 0) >= 254:  # asynchronous: acts at once
                self.apply_rpdo(self.rpdo_data, time.monotonic())

    def send_tpdo(self, tp: Any) -> None:
        for var in tp.map:
            key = (var.index, var.subindex)
            var.raw = {
                (0x6041, 0): self.statusword(),
                (0x6064, 0): self.counts(),
                (0x6077, 0): self.torque(),
            }.get(key, 0)
        if self.args.answer_delay > 0:  # a link whose answers trail (a loaded adapter)
            self.lagged.append((time.monotonic() + self.args.answer_delay, tp.cob_id,
                                bytes(tp.data)))  # fmt: skip
            return
        self.network.send_message(tp.cob_id, bytes(tp.data))
        self.tpdos += 1

    def on_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self.lock:
            if self.hb_consumer and can_id - 0x700 == self.hb_consumer[0]:
                self.hb_seen = time.monotonic()

    def on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        """After the library's NMT slave changed state: re-read the PDO parameters at start."""
        with self.lock:
            if self.node.nmt.state == "OPERATIONAL":
                self.read_pdos()
            self.rpdo_data = None

    def read_pdos(self) -> None:
        cob = self.pdo_param(0x1400, 1) & 0x7FF
        if cob != self.rpdo_cob:
            if self.rpdo_cob is not None:
                self.network.unsubscribe(self.rpdo_cob, self.on_rpdo)
            self.network.subscribe(cob, self.on_rpdo)
            self.rpdo_cob = cob
        for pdo in (self.node.rpdo[1], self.node.tpdo[1]):
            cob = self.pdo_param(pdo.com_record.od.index, 1)
            pdo.read(from_od=True)  # the fixed mapping (the EDS's read-only entries)
            pdo.cob_id = cob & 0x1FFFFFFF
            pdo.enabled = not cob & 0x80000000
            pdo.trans_type = self.pdo_param(pdo.com_record.od.index, 2)
            pdo._update_data_size()

    # -- run --------------------------------------------------------------------------------
    def tick(self) -> None:
        """The drive's own 1 kHz cycle: the plant, the heartbeat consumer, the edge monitor."""
        period = 0.001
        nxt = time.monotonic()
        while not self.stop.is_set():
            nxt += period
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                nxt = time.monotonic()
            now = time.monotonic()
            with self.lock:
                lag = self.lagged
                while lag and lag[0][0] <= now:
                    _, cob, data = lag.popleft()
                    self.network.send_message(cob, data)
                self.plant.advance(now)
                for e in self.edges:
                    if now - e["t"] <= 0.05:
                        e["max_dev_50ms"] = max(e["max_dev_50ms"], abs(self.plant.x - e["x"]))
                hb = self.hb_consumer
                if hb and self.hb_seen is not None and now - self.hb_seen > hb[1]:
                    self.hb_seen = None  # one event; monitoring again at the next heartbeat
                    self.fault(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, now)

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            self.plant.advance(time.monotonic())
            return {
                "node_id": self.args.node_id,
                "state": self.state,
                "statusword": self.statusword(),
                "controlword": self.cw,
                "mode": self.mode,
                "position_m": self.plant.x,
                "position_counts": self.counts(),
                "torque_permille": self.torque(),
                "force_n": self.plant.force(),
                "errors": list(self.errors),
                "emcy": list(self.emcy_sent),
                "enable_edges": self.edges,
                "transitions": self.transitions,
                "syncs": self.syncs,
                "rpdos": self.rpdos,
                "tpdos": self.tpdos,
                "nmt": self.node.nmt.state,
            }

    def run(self) -> None:
        a = self.args
        kwargs: dict[str, Any] = {}
        if a.interface in ("slcan", "serial"):
            # the port's read timeout: python-can's readers poll the line this often when it is
            # quiet (slcan's default 1 ms would wake this process 1000 times a second)
            kwargs["timeout"] = 0.005
        if a.interface == "slcan":
            kwargs["sleep_after_open"] = 0.0  # a pseudo-terminal: no adapter to wait for
        if a.bitrate:
            kwargs["bitrate"] = a.bitrate
        self.network.connect(interface=a.interface, channel=a.channel, **kwargs)
        node = self.node
        node.add_read_callback(self.on_read)
        node.add_write_callback(self.on_write)
        self.network.add_node(node)
        self.network.subscribe(0x80, self.on_sync)
        self.network.subscribe(0, self.on_nmt)
        for producer in range(1, 128):
            if producer != a.node_id:
                self.network.subscribe(0x700 + producer, self.on_heartbeat)
        self.read_pdos()
        threading.Thread(target=self.tick, name="drive-cycle", daemon=True).start()
        with self.lock:
            node.nmt.send_command(0x00)  # boot-up → PRE-OPERATIONAL (library's NMT slave)
            self.state = "SWITCH ON DISABLED"  # transition 1 after its self-test
        print("READY " + json.dumps({"channel": a.channel, "node_id": a.node_id}), flush=True)
        self.stop.wait()
        state = self.snapshot()
        line = json.dumps(state)
        if a.state_file:
            with open(a.state_file, "w") as f:
                f.write(line)
        print("STATE " + line, flush=True)
        node.nmt.stop_heartbeat()
        self.network.disconnect()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--interface", choices=("serial", "slcan", "socketcan"), required=True)
    ap.add_argument("--channel", required=True)
    ap.add_argument("--bitrate", type=int, default=None)
    ap.add_argument("--node-id", type=int, default=5)
    ap.add_argument("--eds", default=EDS)
    ap.add_argument("--state-file", default=None)
    ap.add_argument("--position", type=float, default=0.0, help="initial axis position, m")
    ap.add_argument("--counts-per-m", type=float, default=1e6, help="position unit (1 µm)")
    ap.add_argument("--delay", type=float, default=0.012)
    ap.add_argument("--tau", type=float, default=0.008)
    ap.add_argument("--gain", type=float, default=0.98)
    ap.add_argument("--stiffness", type=float, default=1e6, help="specimen, N/m")
    ap.add_argument(
        "--answer-delay", type=float, default=0.0,
        help="send each TPDO this many seconds late, in order (a link that lags)",
    )  # fmt: skip
    ap.add_argument("--log", default="WARNING")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log, stream=sys.stderr)
    drive = Drive(args)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: drive.stop.set())
    drive.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())

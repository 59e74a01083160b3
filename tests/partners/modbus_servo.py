"""A Modbus TCP servo controller written as a vendor would, for conformance tests.

It is a test partner, not product: it knows nothing of the bridge (it imports nothing from
it) and is written from the Modbus specification (through pymodbus's own server) and from how
small embedded axis controllers behave. A profile for it is written from its manual below and
``docs/profiles.md`` alone (``tests/partners/modbus_servo.toml``).

Manual: "MB-1 servo axis", Modbus TCP, any unit id, 0-based PDU addresses
==========================================================================

Holding registers (FC 3 read, FC 6 / FC 16 write)

=========  ===========  ======================================================================
address    name         meaning
=========  ===========  ======================================================================
1024–1025  SETPOINT     position set-point, IEEE-754 float32, millimetres, high word first;
                        applied when written (FC 16 of both registers; a partial write is
                        refused with exception 03). Followed only while enabled; power-up 0.0.
1030       HEARTBEAT    any uint16; each CHANGE of its value restarts the watchdog (200 ms,
                        a parameter: ``--watchdog``)
=========  ===========  ======================================================================

Input registers (FC 4)

=========  ===========  ======================================================================
2048–2049  POSITION     measured position, float32, millimetres, high word first
2050–2051  FORCE        measured force, float32, kilonewtons, high word first
2052       STATUS       bit 0 READY (0x01), bit 1 ENABLED (0x02), bit 3 FAULT (0x08),
                        bit 5 WATCHDOG (0x20), bit 7 ESTOP (0x80)
=========  ===========  ======================================================================

Coils (FC 1 read, FC 5 write)

=====  ===========  ==========================================================================
16     ENABLE       1 = follow SETPOINT, 0 = hold where it is; ignored while latched
17     ESTOP        1 = latch an emergency stop (hold, disabled); reads back the latch
18     ACKNOWLEDGE  1 = clear a latch (e-stop, watchdog, fault); only while disabled, else
                    exception 04
=====  ===========  ==========================================================================

Behaviour

- Latches: ESTOP coil → status 0x80; watchdog (no HEARTBEAT change for 200 ms while enabled)
  → 0xA0 (WATCHDOG + ESTOP); position beyond the stroke → 0x08 (FAULT). A latch disables and
  holds; READY is off while latched.
- One transaction at a time per connection: a request that arrives while the previous one on
  the same connection is in progress is dropped (no answer), as is the rest of a segment that
  carried several requests. Connections are served concurrently (a second one can watch).
  Firmware option ``--serve queue``: requests that arrive while one is in progress, or several
  in one segment, are queued and served in their order, each answered when it has been served.
- Now and then (``--pause-rate`` per second, Poisson) the network stack pauses 20–40 ms before
  it handles a request; ``--service-time`` adds a fixed processing time to every transaction
  (a slow controller stack).
- The axis in real time: a 12 ms transport delay, an 8 ms first-order lag, gain 0.98 on the
  motion commanded since the enable edge, a 1e6 N/m specimen. Disabled or latched it holds
  where it is; enabled it holds the last set-point when commands stop.

``--state-json FILE`` writes the controller's state and its history (latches, enable edges,
e-stop writes, dropped and served requests; times in s from its start, and ``monotonic``: the
host's CLOCK_MONOTONIC, shared by every process) when it stops (SIGTERM, SIGINT).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import random
import signal
import struct
import sys
import time
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

SETPOINT, HEARTBEAT = 1024, 1030
POSITION, FORCE, STATUS = 2048, 2050, 2052
COIL_ENABLE, COIL_ESTOP, COIL_ACK = 16, 17, 18
READY, ENABLED, FAULT, WATCHDOG, ESTOP = 0x01, 0x02, 0x08, 0x20, 0x80

DELAY, TAU, GAIN, STIFFNESS = 0.012, 0.008, 0.98, 1.0e6
WATCHDOG_TIME = 0.200


def f32_regs(value: float) -> list[int]:
    """A float32 as two registers, high word first."""
    hi, lo = struct.unpack(">HH", struct.pack(">f", value))
    return [hi, lo]


def regs_f32(regs: list[int]) -> float:
    """Two registers, high word first, as a float32."""
    return struct.unpack(">f", struct.pack(">HH", regs[0], regs[1]))[0]


class Axis:
    """The controller's state machine and its plant, advanced exactly in real time."""

    def __init__(
        self, position: float, stroke: float, pause_rate: float, seed: int, watchdog: float
    ) -> None:
        self.t0 = time.monotonic()
        self.t = self.t0
        self.y = position  # m
        self.y_edge = position  # where the last enable edge found the axis
        self.u = position  # the lag's (delayed) input, m
        self.queue: list[tuple[float, float]] = []  # (effective time, input) in the delay line
        self.setpoint = 0.0  # m, the register
        self.enabled = False
        self.latch = 0  # status bits of a latch (0: none)
        self.stroke = stroke
        self.watchdog = watchdog
        self.hb: int | None = None
        self.wd_deadline = math.inf
        self.rng = random.Random(seed)
        self.pause_rate = pause_rate
        self.service_time = 0.0  # s, each transaction's own processing time (--service-time)
        self.next_pause = self._draw_pause(self.t0)
        self.history: dict[str, Any] = {
            "latches": [],
            "enable_edges": [],
            "disable_edges": [],
            "estop_writes": [],
            "ack_writes": [],
            "refused_ack": 0,
            "setpoint_writes": 0,
            "heartbeat_changes": 0,
            "served": 0,
            "dropped": 0,
            "pauses": 0,
            "pause_time": 0.0,  # s, summed
        }

    # -- time --------------------------------------------------------------------------------
    def _draw_pause(self, now: float) -> float:
        if self.pause_rate <= 0:
            return math.inf
        return now + self.rng.expovariate(self.pause_rate)

    def pause_due(self) -> float:
        """Seconds the network stack pauses before this request (0: none)."""
        now = time.monotonic()
        if now < self.next_pause:
            return 0.0
        self.next_pause = self._draw_pause(now)
        self.history["pauses"] += 1
        pause = self.rng.uniform(0.020, 0.040)
        self.history["pause_time"] += pause
        return pause

    def _lag(self, t: float) -> None:
        dt = t - self.t
        if dt > 0 and self.enabled:
            target = self.y_edge + GAIN * (self.u - self.y_edge)
            self.y += (target - self.y) * (1.0 - math.exp(-dt / TAU))
        self.t = max(self.t, t)

    def advance(self, now: float | None = None) -> None:
        """Bring the plant and the watchdog to ``now`` (exactly, event by event)."""
        now = time.monotonic() if now is None else now
        while True:
            t_next = self.queue[0][0] if self.queue else math.inf
            t_wd = self.wd_deadline if self.enabled else math.inf
            t_ev = min(t_next, t_wd)
            if t_ev > now:
                break
            self._lag(t_ev)
            if t_wd <= t_next:
                self._latch(WATCHDOG | ESTOP, "watchdog", t_ev)
            else:
                self.u = self.queue.pop(0)[1]
            if self.enabled and abs(self.y) > self.stroke:
                self._latch(FAULT, "stroke", t_ev)
        self._lag(now)
        if self.enabled and abs(self.y) > self.stroke:
            self._latch(FAULT, "stroke", now)

    def _latch(self, bits: int, cause: str, t: float) -> None:
        self.enabled = False
        self.queue.clear()
        self.latch |= bits
        self.history["latches"].append(
            {"t": t - self.t0, "monotonic": t, "cause": cause, "status": self.status()}
        )

    # -- registers ---------------------------------------------------------------------------
    def status(self) -> int:
        s = self.latch
        if not self.latch:
            s |= READY
        if self.enabled:
            s |= ENABLED
        return s

    def write_setpoint(self, value_m: float) -> None:
        now = time.monotonic()
        self.advance(now)
        self.setpoint = value_m
        self.history["setpoint_writes"] += 1
        if self.enabled:
            self.queue.append((now + DELAY, value_m))

    def write_heartbeat(self, value: int) -> None:
        now = time.monotonic()
        self.advance(now)
        if value != self.hb:
            self.hb = value
            self.history["heartbeat_changes"] += 1
            if self.enabled:
                self.wd_deadline = now + self.watchdog

    def write_enable(self, on: bool) -> None:
        now = time.monotonic()
        self.advance(now)
        if on and not self.enabled and not self.latch:
            self.enabled = True
            self.y_edge = self.u = self.y  # the delay line holds until the set-point arrives
            self.queue = [(now + DELAY, self.setpoint)]
            self.wd_deadline = now + self.watchdog
            self.history["enable_edges"].append(
                {
                    "t": now - self.t0,
                    "monotonic": now,
                    "position": self.y,
                    "setpoint": self.setpoint,
                }
            )
        elif not on and self.enabled:
            self.enabled = False
            self.queue.clear()
            self.history["disable_edges"].append({"t": now - self.t0, "position": self.y})

    def write_estop(self, on: bool) -> None:
        now = time.monotonic()
        self.advance(now)
        self.history["estop_writes"].append({"t": now - self.t0, "value": on})
        if on:
            self._latch(ESTOP, "estop", now)

    def acknowledge(self) -> bool:
        now = time.monotonic()
        self.advance(now)
        if self.enabled:
            self.history["refused_ack"] += 1
            return False
        self.history["ack_writes"].append({"t": now - self.t0, "status": self.status()})
        self.latch = 0
        self.hb = None
        return True

    def state(self) -> dict[str, Any]:
        self.advance()
        return {
            "status": self.status(),
            "position": self.y,
            "force": STIFFNESS * self.y,
            "setpoint": self.setpoint,
            "enabled": self.enabled,
            **self.history,
        }


class OneAtATime(ServerRequestHandler):
    """pymodbus's request handler, serving one transaction at a time per connection."""

    axis: Axis

    def __init__(self, owner: Any, *args: Any) -> None:
        super().__init__(owner, *args)
        self.axis = owner.axis
        self.busy = False

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        if self.busy:  # a request while one is in progress: dropped
            self.axis.history["dropped"] += 1
            return len(data)
        used = super().callback_data(data, addr)
        if self.last_pdu is not None:
            self.busy = True
            if used < len(data):  # the rest of the segment: dropped
                self.axis.history["dropped"] += 1
                return len(data)
        return used

    async def handle_request(self) -> None:
        try:
            pause = self.axis.pause_due() + self.axis.service_time
            if pause:
                await asyncio.sleep(pause)
            await super().handle_request()
            self.axis.history["served"] += 1
        finally:
            self.busy = False


class Queued(ServerRequestHandler):
    """pymodbus's request handler with a request queue: every request of a segment is decoded
    by pymodbus's framer and served in order, one at a time (``--serve queue``)."""

    axis: Axis

    def __init__(self, owner: Any, *args: Any) -> None:
        super().__init__(owner, *args)
        self.axis = owner.axis
        self.queue: asyncio.Queue[tuple[Any, Any]] = asyncio.Queue()
        self.worker: asyncio.Task[None] | None = None

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        used = 0
        while used < len(data):
            n, pdu = self.framer.handleFrame(data[used:], 0, 0)
            if not n:
                break
            used += n
            if pdu is not None:
                self.queue.put_nowait((pdu, addr))
        if self.worker is None:
            self.worker = asyncio.get_running_loop().create_task(self.serve())
        return used

    async def serve(self) -> None:
        while True:
            pdu, addr = await self.queue.get()
            pause = self.axis.pause_due() + self.axis.service_time
            if pause:
                await asyncio.sleep(pause)
            try:
                response = await pdu.datastore_update(self.server.context, pdu.dev_id)
            except Exception:  # (the controller answers, it does not crash)
                response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
            response.transaction_id, response.dev_id = pdu.transaction_id, pdu.dev_id
            self.server_send(response, addr)
            self.axis.history["served"] += 1

    def callback_disconnected(self, exc: Exception | None) -> None:
        if self.worker is not None:
            self.worker.cancel()
        super().callback_disconnected(exc)


class ServoServer(ModbusTcpServer):
    """pymodbus's TCP server with :class:`OneAtATime` (or :class:`Queued`) handlers."""

    def __init__(
        self, axis: Axis, device: SimDevice, address: tuple[str, int], queued: bool = False
    ) -> None:
        super().__init__(device, address=address)
        self.axis = axis
        self.handler = Queued if queued else OneAtATime

    def callback_new_connection(self) -> ServerRequestHandler:
        return self.handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


def _coils(axis: Axis, fc: int, address: int, regs: list[int], values: list | None) -> Any:
    """Coils 16–18 (bits 0–2 of the block's first register)."""
    if values is not None:
        if fc != 5:
            return ExcCodes.ILLEGAL_FUNCTION
        on = bool(values[0])
        if address == COIL_ENABLE:
            axis.write_enable(on)
        elif address == COIL_ESTOP:
            axis.write_estop(on)
        elif address == COIL_ACK:
            if on and not axis.acknowledge():
                return ExcCodes.DEVICE_FAILURE
        else:
            return ExcCodes.ILLEGAL_ADDRESS
    axis.advance()
    estop = bool(axis.latch & ESTOP)
    if values is not None:  # what pymodbus stores after this action: the device's state
        values[0] = {COIL_ENABLE: axis.enabled, COIL_ESTOP: estop}.get(address, False)
    regs[0] = (1 if axis.enabled else 0) | (2 if estop else 0)
    return None


def _holding(axis: Axis, address: int, values: list | None) -> Any:
    """SETPOINT (both registers, applied on write) and HEARTBEAT."""
    if values is None:
        return None
    if address <= SETPOINT + 1 and address + len(values) > SETPOINT:
        if address != SETPOINT or len(values) < 2:
            return ExcCodes.ILLEGAL_VALUE
        axis.write_setpoint(regs_f32(list(values[:2])) * 1e-3)
    if address <= HEARTBEAT < address + len(values):
        axis.write_heartbeat(int(values[HEARTBEAT - address]))
    return None


def make_device(axis: Axis) -> SimDevice:
    """The register map above as a pymodbus SimDevice whose action runs the controller."""

    async def action(
        fc: int, start: int, address: int, count: int, regs: list[int], values: list | None
    ) -> ExcCodes | None:
        if fc in (1, 5, 15):
            return _coils(axis, fc, address, regs, values)
        if fc in (3, 6, 16, 23):
            return _holding(axis, address, values)
        if fc == 4:
            axis.advance()
            regs[POSITION - start : POSITION - start + 2] = f32_regs(axis.y * 1e3)
            regs[FORCE - start : FORCE - start + 2] = f32_regs(STIFFNESS * axis.y * 1e-3)
            regs[STATUS - start] = axis.status()
            return None
        return ExcCodes.ILLEGAL_FUNCTION

    return SimDevice(
        id=0,  # any unit id
        simdata=(
            [SimData(COIL_ENABLE, count=3, values=False, datatype=DataType.BITS)],
            [SimData(0, count=1, values=False, datatype=DataType.BITS)],
            [
                SimData(SETPOINT, count=2, values=0, datatype=DataType.REGISTERS),
                SimData(HEARTBEAT, count=1, values=0, datatype=DataType.REGISTERS),
            ],
            [SimData(POSITION, count=5, values=0, datatype=DataType.REGISTERS, readonly=True)],
        ),
        action=action,
    )


async def serve(args: argparse.Namespace) -> int:
    axis = Axis(args.position, args.stroke, args.pause_rate, args.seed, args.watchdog)
    axis.service_time = args.service_time
    server = ServoServer(
        axis, make_device(axis), ("127.0.0.1", args.port), queued=args.serve == "queue"
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await server.serve_forever(background=True)
    print(f"modbus_servo listening on 127.0.0.1:{args.port}", flush=True)
    await stop.wait()
    await server.shutdown()
    if args.state_json:
        with open(args.state_json, "w", encoding="utf-8") as fh:
            json.dump(axis.state(), fh, indent=1)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--port", type=int, required=True, help="TCP port on 127.0.0.1")
    p.add_argument("--position", type=float, default=0.0, help="axis position at power-up (m)")
    p.add_argument("--stroke", type=float, default=0.1, help="stroke limit (m): FAULT beyond")
    p.add_argument(
        "--pause-rate", type=float, default=0.5, help="network stack pauses per second (0: none)"
    )
    p.add_argument("--seed", type=int, default=1, help="seed of the pause times")
    p.add_argument(
        "--service-time",
        type=float,
        default=0.0,
        help="time the controller takes to serve each transaction (s), as a slow stack does",
    )
    p.add_argument(
        "--watchdog", type=float, default=WATCHDOG_TIME, help="heartbeat watchdog time (s)"
    )
    p.add_argument(
        "--serve",
        choices=("one", "queue"),
        default="one",
        help="requests arriving while one is served: dropped (one) or queued (queue)",
    )
    p.add_argument("--state-json", help="write the state and history here when stopped")
    args = p.parse_args(argv)
    return asyncio.run(serve(args))


if __name__ == "__main__":
    sys.exit(main())

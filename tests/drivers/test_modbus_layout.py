"""The Modbus profile's precompiled layouts (drivers/modbus/layout.py) against pymodbus itself.

Property-style: for every register type, word order and byte order, with scale and offset, for
random values, the bytes the precompiled layouts write equal pymodbus's generic encoding
(``convert_to_registers`` + its request classes and framers, Modbus TCP and RTU, FC 16 and
FC 23), and what they read equals pymodbus's generic decoding (its response classes +
``convert_from_registers``), malformed responses classified as pymodbus's response classes
would have them. A layout that disagrees with pymodbus refuses the profile with one line; the
driver over mixed orders against its twin reads what the twin's registers hold.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import ReadCoilsResponse, ReadDiscreteInputsResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    WriteMultipleRegistersRequest,
)
from rths_hil.drivers.modbus.layout import BlockLayout, PointLayout, RequestTemplate
from rths_hil.drivers.modbus.profile_format import REG_TYPES, ModbusPoint, ReadBlock
from rths_hil.drivers.registry import create_driver
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.errors import InputError

TYPES = list(REG_TYPES)
ORDERS = list(itertools.product(("big", "little"), ("big", "little")))  # (word, byte)
INT_RANGE = {"int16": (-(2**15), 2**15 - 1), "uint16": (0, 2**16 - 1),
             "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1)}  # fmt: skip
RESPONSES = {"holding": ReadHoldingRegistersResponse, "input": ReadInputRegistersResponse,
             "coil": ReadCoilsResponse, "discrete": ReadDiscreteInputsResponse}  # fmt: skip


def point(role, typ, address=100, wo="big", bo="big", scale=1.0, offset=0.0, factor=1.0,
          table="holding") -> ModbusPoint:  # fmt: skip
    count = 1 if typ == "bool" else REG_TYPES[typ]
    return ModbusPoint(role, table, address, typ, count, wo, bo, scale, offset, factor)


def random_raw(rng: np.random.Generator, typ: str, n: int) -> list[float | int]:
    """Random raw values of a type: the integer range, or floats over many decades."""
    if typ in INT_RANGE:
        lo, hi = INT_RANGE[typ]
        return [int(v) for v in rng.integers(lo, hi, size=n, endpoint=True)]
    mag = 10.0 ** rng.uniform(-30 if typ == "float32" else -200, 30, size=n)
    vals = mag * rng.choice([-1.0, 1.0], size=n)
    if typ == "float32":  # values a float32 holds (pymodbus's pack would round them anyway)
        vals = vals.astype(np.float32).astype(np.float64)
    return [float(v) for v in vals]


def same(a: float, b: float) -> bool:
    return a == b or (a != a and b != b)  # NaN from random register bits reads as NaN


# ------------------------------------------------------------------------------------------
# requests: the template's bytes equal pymodbus's generic encoding
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("transport", ["tcp", "rtu"])
@pytest.mark.parametrize("fc", [16, 23])
@pytest.mark.parametrize("typ", TYPES)
def test_request_bytes_equal_pymodbus_encoding(typ, fc, transport) -> None:
    rng = np.random.default_rng(hash((typ, fc, transport)) & 0xFFFF)
    framer_cls = FramerRTU if transport == "rtu" else FramerSocket
    for (wo, bo), (scale, offset, factor) in itertools.product(
        ORDERS, [(1.0, 0.0, 1.0), (0.01, 0.0, 1e-3), (2.5e-4, -3.0, 1e3)]
    ):
        sp = point("setpoint", typ, 100, wo, bo, scale, offset, factor)
        n = sp.count

        def pdu(n: int = n):
            if fc == 23:
                return ReadWriteMultipleRegistersRequest(
                    read_address=200, read_count=7, write_address=100, write_registers=[0] * n
                )
            return WriteMultipleRegistersRequest(address=100, registers=[0] * n)

        tpl_pdu = pdu()
        tpl_pdu.dev_id = 7
        tpl = RequestTemplate(framer_cls(DecodePDU(False)), tpl_pdu, PointLayout(sp))
        ref_framer, ref_pdu = framer_cls(DecodePDU(False)), pdu()
        ref_pdu.dev_id = 7
        for raw in random_raw(rng, typ, 60):
            si = (raw * scale + offset) * factor  # the SI value whose raw value is ``raw``
            try:
                regs = sp.to_registers(si)  # pymodbus's convert_to_registers + byte order
            except InputError:  # rounded out of the integer range at its very edge
                with pytest.raises(InputError):
                    sp.raw_value(si)
                continue
            tid = int(rng.integers(0, 0x10000))
            if fc == 23:
                ref_pdu.write_registers = regs
            else:
                ref_pdu.registers = regs
            ref_pdu.transaction_id = tid
            want = ref_framer.buildFrame(ref_pdu)
            got = tpl.build(sp.raw_value(si), tid)
            assert got == want, (typ, wo, bo, raw)


def test_mixed_orders_are_a_permutation_and_plain_orders_one_struct() -> None:
    """big/big is ``>f``, little/little ``<f`` (the value's bytes reversed), the mixed orders
    ``>f`` and a permutation: CDAB for word order little, BADC for byte order little."""
    assert PointLayout(point("x", "float32")).fmt == ">f"
    little = PointLayout(point("x", "float32", wo="little", bo="little"))
    assert little.fmt == "<f" and little.perm is None
    cdab = PointLayout(point("x", "float32", wo="little", bo="big"))
    badc = PointLayout(point("x", "float32", wo="big", bo="little"))
    assert cdab.perm == (2, 3, 0, 1) and badc.perm == (1, 0, 3, 2)
    import struct

    abcd = struct.pack(">f", 1.5)
    assert cdab.pack(1.5) == abcd[2:] + abcd[:2]
    assert badc.pack(1.5) == bytes([abcd[1], abcd[0], abcd[3], abcd[2]])
    assert PointLayout(point("x", "int16", bo="little")).fmt == "<h"


# ------------------------------------------------------------------------------------------
# responses: the block decoder reads what pymodbus's generic decoding reads
# ------------------------------------------------------------------------------------------
def reference_decode(block: ReadBlock, pdu: bytes) -> dict[str, float] | str:
    """pymodbus's generic path: its response class, then ``convert_from_registers`` per point
    (ModbusPoint.from_registers / raw_from_registers); ``bad_frame`` when the class raises,
    ``bad_length`` for fewer items than the block."""
    resp = RESPONSES[block.table]()
    try:
        resp.decode(pdu[1:])
    except Exception:
        return "bad_frame"
    data = resp.bits if block.table in ("coil", "discrete") else resp.registers
    if len(data) < block.count:
        return "bad_length"
    out: dict[str, float] = {}
    for p in block.points:
        part = data[p.address - block.address : p.end - block.address]
        out[p.role] = p.raw_from_registers(part) if p.role == "status" else p.from_registers(part)
    return out


@pytest.mark.parametrize("typ", TYPES)
def test_block_decoding_equals_pymodbus_decoding(typ) -> None:
    rng = np.random.default_rng(TYPES.index(typ))
    for (wo, bo), (wo2, bo2) in itertools.product(ORDERS, ORDERS):
        pts = (
            point("position", typ, 200, wo, bo, 0.01, 0.5, 1e-3, "input"),
            point(
                "force",
                "float64" if typ != "float64" else "int32",
                210,
                wo2,
                bo2,
                2.0,
                -1.0,
                1e3,
                "input",
            ),
            point("status", "uint16" if typ == "float32" else typ, 230, wo, bo2, table="input"),
        )
        block = ReadBlock("input", 200, 230 + pts[2].count - 200, pts)
        lay = BlockLayout(block)
        for _ in range(40):
            regs = [int(r) for r in rng.integers(0, 0x10000, size=block.count)]
            for p in pts:  # half the time values through pymodbus, else random bits
                if rng.random() < 0.5:
                    (raw,) = random_raw(rng, p.type, 1)
                    k = p.address - block.address
                    regs[k : k + p.count] = p._swap(
                        ModbusClientMixin.convert_to_registers(
                            raw, p.dtype, word_order=p.word_order
                        )
                    )
            pdu = bytes([4]) + ReadInputRegistersResponse(registers=regs).encode()
            want = reference_decode(block, pdu)
            got: dict[str, float] = {}
            try:
                why = lay.decode(pdu, got)
            except ValueError:  # int(NaN) of a float status: pymodbus's int() raises it too
                assert typ.startswith("float")
                with pytest.raises(ValueError):
                    reference_decode(block, pdu)
                continue
            assert why is None and isinstance(want, dict)
            for role in want:
                assert same(got[role], want[role]), (role, typ, wo, bo, wo2, bo2)


def test_malformed_responses_are_classified_as_pymodbus_would() -> None:
    """Truncated frames and wrong byte counts: ``bad_frame`` where pymodbus's response class
    raises, ``bad_length`` where it returns fewer registers than the block, else the values."""
    pts = (point("position", "float32", 200, table="holding"),
           point("force", "float32", 202, table="holding"),
           point("status", "uint16", 210, table="holding"))  # fmt: skip
    block = ReadBlock("holding", 200, 11, pts)
    lay = BlockLayout(block)
    good = bytes([3]) + ReadHoldingRegistersResponse(registers=list(range(1, 12))).encode()
    rng = np.random.default_rng(5)
    seen = set()
    for _ in range(400):
        pdu = bytearray(good[: int(rng.integers(1, len(good) + 3))])
        if len(pdu) > 1 and rng.random() < 0.6:
            pdu[1] = int(rng.integers(0, 30))  # the byte count
        pdu = bytes(pdu) + bytes(int(rng.integers(0, 3)))
        want = reference_decode(block, pdu)
        got: dict[str, float] = {}
        why = lay.decode(pdu, got)
        if isinstance(want, str):
            assert why == want, pdu.hex()
        else:
            assert why is None and got == want, pdu.hex()
        seen.add(want if isinstance(want, str) else "ok")
    assert seen == {"bad_frame", "bad_length", "ok"}


@pytest.mark.parametrize("table", ["coil", "discrete"])
def test_bit_blocks_equal_pymodbus_decoding(table) -> None:
    pts = (point("position", "bool", 3, table=table, scale=0.25, offset=0.1),
           point("force", "bool", 12, table=table, scale=-3.0),
           point("status", "bool", 17, table=table))  # fmt: skip
    block = ReadBlock(table, 3, 15, pts)
    lay = BlockLayout(block)
    rng = np.random.default_rng(9)
    fc = {"coil": 1, "discrete": 2}[table]
    for _ in range(100):
        bits = [bool(b) for b in rng.integers(0, 2, size=block.count)]
        pdu = bytes([fc]) + RESPONSES[table](bits=bits).encode()
        pdu = pdu[: int(rng.integers(1, len(pdu) + 1))]
        want = reference_decode(block, pdu)
        got: dict[str, float] = {}
        why = lay.decode(pdu, got)
        assert (why == want) if isinstance(want, str) else (why is None and got == want)


# ------------------------------------------------------------------------------------------
# the check at open, and the driver end to end
# ------------------------------------------------------------------------------------------
def test_a_layout_that_disagrees_with_pymodbus_is_refused_in_one_line(monkeypatch) -> None:
    """A pymodbus whose conversion differs from the derived layout (here one that ignores the
    word order, as a changed library might) refuses the point with one line."""
    real = ModbusClientMixin.convert_to_registers.__func__

    def no_word_order(cls, value, data_type, word_order="big", string_encoding="utf-8"):
        return real(cls, value, data_type, "big", string_encoding)

    PointLayout(point("setpoint", "float32", wo="little"))  # agrees with the real pymodbus
    monkeypatch.setattr(ModbusClientMixin, "convert_to_registers", classmethod(no_word_order))
    with pytest.raises(InputError) as e:
        PointLayout(point("setpoint", "float32", wo="little"), "lab.toml")
    msg = str(e.value)
    assert "\n" not in msg and "lab.toml" in msg and "roles.setpoint" in msg
    assert "disagrees with pymodbus" in msg
    PointLayout(point("setpoint", "float32", wo="big"))  # unaffected: word order big


MIXED = """protocol = "modbus"
[modbus]
unit = 3
[roles.setpoint]
table = "holding"
address = 10
type = "int32"
word_order = "little"
scale = 1e-3
units = "mm"
[roles.position]
table = "input"
address = 20
type = "float64"
word_order = "little"
byte_order = "little"
units = "mm"
[roles.force]
table = "input"
address = 24
type = "float32"
byte_order = "little"
scale = 0.5
offset = -2.0
units = "kN"
[roles.status]
table = "input"
address = 30
type = "uint32"
word_order = "little"
[status]
enabled = 0x10000
estop = 0x2
[actions.enable]
table = "coil"
address = 0
[actions.disable]
table = "coil"
address = 0
value = 0
[actions.estop]
table = "coil"
address = 1
"""


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_driver_with_mixed_orders_reads_what_its_twin_holds(tmp_path, transport) -> None:
    """Every order at once (int32 CDAB with scale, float64 all reversed, float32 BADC with
    scale and offset, a uint32 status word CDAB): each feedback equals pymodbus's decoding of
    the registers the twin holds for that step."""
    prof = tmp_path / "mixed.toml"
    prof.write_text(MIXED)
    extra = {"transport": "rtu"} if transport == "rtu" else {"port": 0}
    twin = start_twin("modbus", default_plant(), profile=str(prof), **extra)
    try:
        pts = twin.profile.points
        with create_driver("modbus", **twin.connection) as drv:
            assert drv.arm(1.0) is not None
            moved = 0.0
            for k in range(30):
                drv.send(k, 0.002 * math.sin(k / 5), True)
                fb = drv.receive(1.0)
                assert fb is not None and fb.seq == k
                t = twin.tables["input"]
                regs = {
                    r: [t[a] for a in range(pts[r].address, pts[r].end)]
                    for r in ("position", "force", "status")
                }
                assert fb.displacement == pts["position"].from_registers(regs["position"])
                assert fb.force == pts["force"].from_registers(regs["force"])
                word = pts["status"].raw_from_registers(regs["status"])
                assert fb.status & 0x01 == (1 if word & 0x10000 else 0)  # ENABLED
                moved = max(moved, abs(fb.displacement))
            assert moved > 1e-4 and drv.stats.malformed == 0
    finally:
        twin.stop()


# ------------------------------------------------------------------------------------------
# the pipelined step's whole reply (StepReply, the fast path)
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("two_blocks", [False, True])
def test_step_reply_reads_pymodbus_frames_and_refuses_any_other_byte(two_blocks) -> None:
    """The reply of a step (FC 16 echo, then one FC 4 read, or FC 3 + FC 4 reads) built by
    pymodbus's response classes and framer with random values: ``match`` gives what the
    generic decoding gives; a change of any byte outside the registers (a transaction id, a
    header, the echo), another step's id or a short buffer gives ``None``."""
    from pymodbus.pdu.register_message import WriteMultipleRegistersResponse
    from rths_hil.drivers.modbus.layout import StepReply

    rng = np.random.default_rng(11 + two_blocks)
    pos = point("position", "float32", 200, table="input", scale=0.5, offset=1.0, factor=1e-3)
    force = point("force", "int32", 202, table="input", scale=0.01, factor=1e3)
    status = point("status", "uint16", 50 if two_blocks else 210,
                   table="holding" if two_blocks else "input")  # fmt: skip
    if two_blocks:
        blocks = [ReadBlock("input", 200, 4, (pos, force)), ReadBlock("holding", 50, 1, (status,))]
    else:
        blocks = [ReadBlock("input", 200, 11, (pos, force, status))]
    lays = [BlockLayout(b) for b in blocks]
    framer = FramerSocket(DecodePDU(False))
    echo = WriteMultipleRegistersResponse(address=100, count=2)
    txs = [(echo, None)] + [(RESPONSES[b.table](registers=[0] * b.count), lay)
                            for b, lay in zip(blocks, lays, strict=True)]  # fmt: skip
    reply = StepReply(framer, 5, txs)
    if not two_blocks:
        assert reply.fmt == ">H10sH7sfi12xH"  # 204–209 unmapped: 12 bytes
    for _ in range(50):
        tid = int(rng.integers(0, 0x1000)) << 4
        frames, want = [], {}
        for i in range(len(txs)):
            if i == 0:
                resp = WriteMultipleRegistersResponse(address=100, count=2)
            else:
                b = blocks[i - 1]
                regs = [int(r) for r in rng.integers(0, 0x10000, size=b.count)]
                for p in b.points:
                    (raw,) = random_raw(rng, p.type, 1)
                    k = p.address - b.address
                    regs[k : k + p.count] = ModbusClientMixin.convert_to_registers(raw, p.dtype)
                resp = RESPONSES[b.table](registers=regs)
                pdu_bytes = bytes([resp.function_code]) + resp.encode()
                want.update(reference_decode(b, pdu_bytes))
            resp.dev_id, resp.transaction_id = 5, tid + i
            frames.append(framer.buildFrame(resp))
        buf = b"".join(frames)
        assert reply.match(buf + b"\x00\x07", tid) == (
            want["position"], want["force"], want["status"])  # fmt: skip
        assert reply.match(buf, tid + 16) is None and reply.match(buf[:-1], tid) is None
        data = {range(at + 2, at + 2 + 2 * lay.block.count) for lay, at in
                zip(lays, [len(frames[0]) + 7, len(frames[0]) + len(frames[1]) + 7][: len(lays)],
                    strict=True)}  # fmt: skip
        in_data = {i for r in data for i in r}
        for i in range(len(buf)):
            if i in in_data:
                continue
            bad = bytearray(buf)
            bad[i] ^= 1 << int(rng.integers(0, 8))
            assert reply.match(bytes(bad), tid) is None, i


def test_driver_fast_path_leaves_other_replies_to_the_general_parser() -> None:
    """The example map pipelined over TCP takes its step replies in one pass; a reply that is
    not the expected one (here an exception to the read, built by pymodbus, ahead of the real
    reply) is parsed and counted as before, and the real reply behind it still delivered."""
    from pathlib import Path

    from pymodbus.pdu import ExceptionResponse
    from pymodbus.pdu.register_message import WriteMultipleRegistersResponse

    prof = Path(__file__).resolve().parents[2] / "examples" / "controllers" / "modbus_map.toml"
    twin = start_twin("modbus", default_plant(), profile=str(prof), port=0)
    try:
        with create_driver("modbus", **twin.connection) as drv:
            assert drv._reply is not None and drv._reply.fmt == ">H10sH7sff12xH"
            assert drv.arm(1.0) is not None
            for k in range(5):
                drv.send(k, 0.001, True)
                assert drv.receive(1.0) is not None
            framer = FramerSocket(DecodePDU(False))
            base = (5 & 0xFFF) << 4
            echo = WriteMultipleRegistersResponse(address=100, count=2)
            exc = ExceptionResponse(4, 2)
            for pdu, tid in ((echo, base), (exc, base + 1)):
                pdu.dev_id, pdu.transaction_id = 1, tid
            drv.send(5, 0.001, True)
            drv._buf = framer.buildFrame(echo) + framer.buildFrame(exc)
            fb = drv.receive(1.0)
            assert fb is not None and fb.seq == 5
            assert drv.stats.malformed_reasons == {"modbus_exception": 1}
    finally:
        twin.stop()

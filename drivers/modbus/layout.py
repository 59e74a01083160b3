"""Precompiled wire layouts of a Modbus profile: pymodbus's generic work done once, at open.

pymodbus stays the authority for the frames and the value conversions; what it does generically
for every request (PDU objects, ``convert_to_registers`` / ``convert_from_registers``, the
framer) is done once when a driver or twin opens, and turned into plain :mod:`struct` layouts
that the step then applies to a ``bytearray`` template:

* :class:`PointLayout` — the bytes of one register point on the wire as one ``struct`` format.
  pymodbus packs a value big-endian (``struct.pack(">" + c)``, ``c`` from its ``DATATYPE``),
  cuts it into registers, reverses them for ``word_order = "little"``, and the profile swaps
  the two bytes of each register for ``byte_order = "little"`` (:meth:`.ModbusPoint._swap`);
  each register goes on the wire high byte first (MODBUS Application Protocol V1.1b3 §4.2).
  So wire byte ``i`` of an ``n``-register value is byte ``perm[i]`` of the big-endian packing,

      perm[2k + j] = 2·(k if word_order big else n − 1 − k) + (j if byte_order big else 1 − j),

  ``k`` the register, ``j`` the byte in it. ``perm`` the identity is the format ``">" + c``,
  ``perm`` reversed is ``"<" + c``; a mixed order (``CDAB``, ``BADC``) is ``">" + c`` and
  the permutation.
* :class:`BlockLayout` — a read block's response: the header checks pymodbus's response
  classes make (byte count, length), then one ``struct.unpack_from`` for the block's
  big-endian points (e.g. ``">ff12xH"`` for the example map's FC 4 block: position, force,
  six unmapped registers, status) and per point for the others; coils and discrete inputs are
  a byte offset and a bit mask each.
* :class:`RequestTemplate` — one request frame built by pymodbus's PDU class and framer, and
  where its value bytes sit (found by building it twice); per step the value, the transaction
  id (Modbus TCP) and the CRC (RTU, by pymodbus's ``FramerRTU.compute_CRC``) are patched in;
  pipelined Modbus TCP appends the step's read requests to the same template.
* :class:`StepReply` — pipelined Modbus TCP: a step's whole reply (the responses of its
  transactions as pymodbus's response classes and framer build them) as one ``struct``,
  checked byte for byte outside the registers and read in one pass.

Every layout is checked against pymodbus when it is made: test values through the layout give
the bytes pymodbus gives (``convert_to_registers``, ``buildFrame``) and decode to the values it
decodes (``convert_from_registers``, the response classes); a disagreement refuses the profile
with one line (:class:`~rths_hil.errors.InputError`).
"""

from __future__ import annotations

import math
import operator
import struct
from collections.abc import Sequence
from typing import Any

from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.framer import FramerRTU
from pymodbus.pdu.bit_message import ReadCoilsResponse, ReadDiscreteInputsResponse
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
)

from rths_hil.errors import InputError

from .profile_format import ModbusPoint, ReadBlock

__all__ = ["TID", "BlockLayout", "PointLayout", "RequestTemplate", "StepReply", "rtu_crc"]

#: The MBAP transaction identifier: bytes 0–1 of a Modbus TCP frame, big-endian.
TID = struct.Struct(">H")
#: An RTU frame's last two bytes: pymodbus appends ``compute_CRC(frame).to_bytes(2, "big")``.
_CRC = struct.Struct(">H")
_compute_crc = FramerRTU.compute_CRC

#: Raw test values per type: the layouts are checked against pymodbus with these.
PROBES: dict[str, tuple[float, ...]] = {
    "int16": (0, 1, -1, -32768, 32767, 0x1234, -0x2345),
    "uint16": (0, 1, 65535, 0x1234, 0xA55A),
    "int32": (0, -1, -(2**31), 2**31 - 1, 0x12345678, -123456789),
    "uint32": (0, 1, 2**32 - 1, 0x12345678, 0xA1B2C3D4),
    "float32": (0.0, -1.5, 3.1415927410125732, 1e-20, -6.5e7, 2.5e-3),
    "float64": (0.0, -1.5, math.pi, 1e-300, 6.02214076e23, -2.5e-3),
}
#: Response classes of the register and bit reads (the reference decoders of the check).
_RESPONSES: dict[str, Any] = {
    "holding": ReadHoldingRegistersResponse,
    "input": ReadInputRegistersResponse,
    "coil": ReadCoilsResponse,
    "discrete": ReadDiscreteInputsResponse,
}


def _refuse(point: ModbusPoint, source: str, what: str) -> InputError:
    return InputError(
        f"modbus: profile {source}: roles.{point.role}: the precompiled {point.type} layout "
        f"(word_order {point.word_order}, byte_order {point.byte_order}) disagrees with "
        f"pymodbus: {what}"
    )


def _wire(regs: list[int]) -> bytes:
    """Registers as they go on the wire: each one high byte first."""
    return b"".join(r.to_bytes(2, "big") for r in regs)


class PointLayout:
    """The wire bytes of one register point as a ``struct`` format (module docstring).

    Parameters
    ----------
    point : ModbusPoint
        A register point (not ``bool``).
    source : str
        The profile's path, for the refusal.
    """

    __slots__ = ("_get", "_put", "fmt", "n", "perm", "point", "struct")

    def __init__(self, point: ModbusPoint, source: str = "") -> None:
        c, regs = point.dtype.value  # pymodbus's struct character and registers per value
        big_w, big_b = point.word_order == "big", point.byte_order == "big"
        perm = tuple(
            2 * (k if big_w else regs - 1 - k) + (j if big_b else 1 - j)
            for k in range(regs)
            for j in (0, 1)
        )  # wire byte i = byte perm[i] of struct.pack(">" + c)
        self.point = point
        self.n = 2 * regs
        if perm == tuple(range(self.n)):
            self.fmt, self.perm = ">" + c, None
        elif perm == tuple(reversed(range(self.n))):
            self.fmt, self.perm = "<" + c, None
        else:
            self.fmt, self.perm = ">" + c, perm
        self.struct = struct.Struct(self.fmt)
        self._get = operator.itemgetter(*perm)  # packed bytes → wire bytes
        inverse = [0] * self.n
        for i, k in enumerate(perm):
            inverse[k] = i  # packed byte k is wire byte i
        self._put = operator.itemgetter(*inverse)  # wire bytes → packed bytes
        self._check(source)

    @property
    def native(self) -> bool:
        """Whether the point is plain big-endian (``">" + c``): Modbus's own order."""
        return self.perm is None and self.fmt[0] == ">"

    def pack(self, raw: float | int) -> bytes:
        """The wire bytes of the raw value."""
        b = self.struct.pack(raw)
        return b if self.perm is None else bytes(self._get(b))

    def pack_into(self, buf: bytearray, offset: int, raw: float | int) -> None:
        """Write the raw value's wire bytes into ``buf`` at ``offset``."""
        if self.perm is None:
            self.struct.pack_into(buf, offset, raw)
        else:
            buf[offset : offset + self.n] = bytes(self._get(self.struct.pack(raw)))

    def unpack_from(self, data: bytes, offset: int) -> float | int:
        """The raw value of the wire bytes at ``offset``."""
        if self.perm is None:
            return self.struct.unpack_from(data, offset)[0]
        return self.struct.unpack(bytes(self._put(data[offset : offset + self.n])))[0]

    def _check(self, source: str) -> None:
        """Refuse unless every probe value gives pymodbus's bytes and decodes to its value."""
        p = self.point
        conv_to = ModbusClientMixin.convert_to_registers
        conv_from = ModbusClientMixin.convert_from_registers
        wo: Any = p.word_order
        for raw in PROBES[p.type]:
            regs = p._swap(conv_to(raw, p.dtype, word_order=wo))
            ref = _wire(regs)
            got = self.pack(raw)
            if got != ref:
                raise _refuse(p, source, f"{raw!r} packs as {got.hex()}, pymodbus {ref.hex()}")
            back = conv_from(p._swap(regs), p.dtype, word_order=wo)
            mine = self.unpack_from(ref, 0)
            if mine != back:
                raise _refuse(p, source, f"{ref.hex()} reads as {mine!r}, pymodbus {back!r}")


class BlockLayout:
    """Decoder of one read block's response PDU (function code first), see the module
    docstring; :meth:`decode` fills ``role → SI value`` (``status``: the raw status word).

    Parameters
    ----------
    block : ReadBlock
        The block (its table and points).
    source : str
        The profile's path, for the refusal.
    """

    def __init__(self, block: ReadBlock, source: str = "") -> None:
        self.block = block
        self.bits = block.table in ("coil", "discrete")
        pts = sorted(block.points, key=lambda q: q.address)
        #: (role, byte index in the PDU, bit mask, scale, offset, factor) of each bit point
        self.bit_points: list[tuple[str, int, int, float, float, float]] = []
        #: (role, scale, offset, factor) of the points in the block's big-endian struct
        self.native_points: list[tuple[str, float, float, float]] = []
        #: (role, layout, byte offset in the PDU, scale, offset, factor) of the others
        self.other_points: list[tuple[str, PointLayout, int, float, float, float]] = []
        fmt, at = ">", 0  # the block's struct, from byte 2 of the PDU (after fc, byte count)
        for p in pts:
            k = p.address - block.address  # the point's place in the block (items)
            scaling = (p.scale, p.offset, p.factor)
            if self.bits:  # bit k: byte 2 + k // 8 of the PDU, LSB first (§6.1)
                self.bit_points.append((p.role, 2 + k // 8, 1 << (k % 8), *scaling))
                continue
            lay = PointLayout(p, source)
            if lay.native:
                gap = 2 * k - at  # unmapped registers between the points: pad bytes
                fmt += (f"{gap}x" if gap else "") + lay.fmt[1:]
                at = 2 * k + lay.n
                self.native_points.append((p.role, *scaling))
            else:
                self.other_points.append((p.role, lay, 2 + 2 * k, *scaling))
        if 2 * block.count > at:  # to the block's end (bytes after the last struct point)
            fmt += f"{2 * block.count - at}x"
        self.struct = struct.Struct(fmt)  # e.g. ">ff12xH": float32, float32, 6 gaps, uint16
        self.fmt = fmt
        self._check(source)

    def decode(self, pdu: bytes, out: dict[str, float]) -> str | None:
        """Decode a read response PDU into ``out``; ``None``, or the reason it is refused:
        ``bad_frame`` (pymodbus's response class would not decode it) or ``bad_length``
        (fewer items than the block)."""
        if self.bits:
            if 8 * (len(pdu) - 2) < self.block.count:  # pymodbus unpacks every byte after
                return "bad_length"  # the byte count: 8 bits each
            for role, i, mask, scale, offset, factor in self.bit_points:
                bit = 1 if pdu[i] & mask else 0
                out[role] = bit if role == "status" else (bit * scale + offset) * factor
            return None
        if len(pdu) < 2:  # no byte count (pymodbus raises)
            return "bad_frame"
        n = pdu[1]  # the byte count
        if n >= len(pdu) - 1:  # more bytes announced than came (pymodbus raises)
            return "bad_frame"
        if n // 2 < self.block.count:  # registers = byte count // 2
            return "bad_length"
        self.values_from(pdu, 0, out)
        return None

    def values_from(self, buf: bytes, at: int, out: dict[str, float]) -> None:
        """The register block's values from the response PDU at ``buf[at:]`` (its function
        code at ``at``), its byte count and length already checked."""
        raws = self.struct.unpack_from(buf, at + 2)
        for (role, scale, offset, factor), raw in zip(self.native_points, raws, strict=True):
            # value in units = raw · scale + offset; SI = that · factor (ModbusPoint.si); the
            # status word is the raw integer (ValueError for a NaN in a float status point)
            out[role] = int(raw) if role == "status" else (raw * scale + offset) * factor
        for role, lay, off, scale, offset, factor in self.other_points:
            raw = lay.unpack_from(buf, at + off)
            out[role] = int(raw) if role == "status" else (raw * scale + offset) * factor

    def _check(self, source: str) -> None:
        """Decode a response pymodbus built for probe values; refuse on a disagreement."""
        b = self.block
        fc = _RESPONSES[b.table].function_code
        for i in range(max(len(PROBES[p.type]) for p in b.points) if not self.bits else 2):
            items: list[int] = [0] * b.count
            for p in b.points:
                k = p.address - b.address
                if self.bits:
                    items[k] = (i + k) % 2
                else:
                    probes = PROBES[p.type]
                    items[k : k + p.count] = p._swap(
                        ModbusClientMixin.convert_to_registers(
                            probes[i % len(probes)],
                            p.dtype,
                            word_order=p.word_order,  # type: ignore[arg-type]
                        )
                    )
            if self.bits:
                resp = _RESPONSES[b.table](bits=[bool(x) for x in items])
            else:
                resp = _RESPONSES[b.table](registers=items)
            pdu = bytes([fc]) + resp.encode()
            mine: dict[str, float] = {}
            self.decode(pdu, mine)
            ref = _RESPONSES[b.table]()
            ref.decode(pdu[1:])
            data = ref.bits if self.bits else ref.registers
            for p in b.points:
                k = p.address - b.address
                part = data[k : k + p.count]
                want = p.raw_from_registers(part) if p.role == "status" else p.from_registers(part)
                if mine[p.role] != want:
                    raise _refuse(
                        p, source, f"{pdu.hex()} reads as {mine[p.role]!r}, pymodbus {want!r}"
                    )


class RequestTemplate:
    """A request frame built once by pymodbus, patched per step (module docstring).

    Parameters
    ----------
    framer : pymodbus framer
        ``FramerSocket`` (Modbus TCP) or ``FramerRTU``.
    pdu : pymodbus request
        The request (``dev_id`` set); its ``registers`` (FC 16) or ``write_registers``
        (FC 23) carry the value of ``layout``.
    layout : PointLayout
        The value's layout.
    source : str
        The profile's path, for the refusal.
    follow : list of bytes, optional
        Modbus TCP: frames sent after it in the same write (the step's reads, built by
        pymodbus), their transaction ids ``tid + 1``, ``tid + 2``, … patched per step.
    """

    def __init__(
        self,
        framer: Any,
        pdu: Any,
        layout: PointLayout,
        source: str = "",
        follow: Sequence[bytes] = (),
    ) -> None:
        self.framer, self.pdu, self.layout = framer, pdu, layout
        self.rtu = isinstance(framer, FramerRTU)
        self.field = "write_registers" if hasattr(pdu, "write_registers") else "registers"
        regs = layout.n // 2
        a = self._build([0] * regs, 0)
        b = self._build([0xFFFF] * regs, 0)
        end = len(a) - 2 if self.rtu else len(a)  # (the RTU CRC changes too)
        diff = [i for i in range(end) if a[i] != b[i]]
        if len(diff) != layout.n or diff[-1] - diff[0] != layout.n - 1:
            raise _refuse(layout.point, source, "the value's bytes not found in its request")
        #: byte offset of the value in the frame
        self.offset = diff[0]
        self.function_code = pdu.function_code
        self._check(source)
        #: the frame(s): the request, then ``follow``; the MBAP transaction id of each at
        self.frame = bytearray(a + b"".join(follow))
        self.tids = [len(a) + sum(len(f) for f in follow[:i]) for i in range(len(follow))]

    def _build(self, regs: list[int], tid: int) -> bytes:
        setattr(self.pdu, self.field, regs)
        self.pdu.transaction_id = tid
        return bytes(self.framer.buildFrame(self.pdu))

    def build(self, raw: float | int, tid: int) -> bytes:
        """The frame with the raw value and (TCP) the transaction id ``tid``."""
        f = self.frame
        self.layout.pack_into(f, self.offset, raw)
        if self.rtu:  # CRC-16 of address … data (pymodbus's), high byte first as it appends it
            _CRC.pack_into(f, len(f) - 2, _compute_crc(f[:-2]))
        else:
            TID.pack_into(f, 0, tid)  # MBAP transaction identifier
            for i, at in enumerate(self.tids, start=1):
                TID.pack_into(f, at, tid + i)  # the following frames': tid + 1, tid + 2, …
        return bytes(f)

    def _check(self, source: str) -> None:
        self.frame = bytearray(self._build([0] * (self.layout.n // 2), 0))
        self.tids = []
        p = self.layout.point
        for k, raw in enumerate(PROBES[p.type]):
            tid = (0x1234 + 4099 * k) & 0xFFFF
            si = p.si(raw)
            try:
                regs = p.to_registers(si)
                value = p.raw_value(si)
            except InputError:
                continue  # (a probe at the edge of an integer range may round out of it)
            mine = self.build(value, tid)
            ref = self._build(regs, tid)
            if mine != ref:
                raise _refuse(p, source, f"the request is {mine.hex()}, pymodbus {ref.hex()}")


class StepReply:
    """A pipelined Modbus TCP step's whole reply as one ``struct`` (the fast path).

    The reply of a step is the responses of its transactions, in order, each as pymodbus's
    response class and framer build it: a write's echo (all predictable but the transaction
    id), a read's MBAP header, function code and byte count, then the block's registers. One
    format covers it all, e.g. ``">H10sH7sff12xH"`` for the example map: FC 16 echo (id, 10
    bytes), FC 4 response (id, 7 bytes), position and force (float32), 6 unmapped registers,
    the status word (uint16). :meth:`match` unpacks it once and checks every transaction id and
    every predictable byte; a reply that differs anywhere is left to the general parser (which
    counts what is wrong with it). Made only when the read points are all in Modbus's own order
    (:attr:`PointLayout.native`); other maps take the general path.

    Parameters
    ----------
    framer : FramerSocket
        pymodbus's Modbus TCP framer.
    unit : int
        The unit id.
    transactions : list
        The step's transactions in order: ``(pymodbus response PDU, BlockLayout or None)``;
        a read's response built with zero registers, a write's echo with ``None``.
    """

    def __init__(self, framer: Any, unit: int, transactions: list[tuple[Any, Any]]) -> None:
        fmt, fields = ">", 0  # the struct, and how many values it unpacks to so far
        tids: list[int] = []  # the fields of the transaction ids
        heads: list[int] = []  # the fields of the predictable bytes
        consts: list[bytes] = []  # … and what they must be
        raw_at: dict[str, int] = {}  # role → the field of its raw value
        self.scaling: dict[str, tuple[float, float, float]] = {}  # role → scale, offset, factor
        for pdu, block in transactions:
            pdu.dev_id, pdu.transaction_id = unit, 0
            frame = bytes(framer.buildFrame(pdu))
            head = len(frame) if block is None else 9  # MBAP (7) + function code + byte count
            fmt += f"H{head - 2}s"  # transaction id, then the predictable bytes
            tids.append(fields)
            heads.append(fields + 1)
            consts.append(frame[2:head])
            fields += 2
            if block is None:
                continue
            if block.bits or block.other_points:
                raise ValueError("StepReply: only register blocks in Modbus's own order")
            fmt += block.fmt[1:]  # the block's registers, e.g. "ff12xH"
            for i, (role, *scaling) in enumerate(block.native_points):
                raw_at[role] = fields + i
                self.scaling[role] = tuple(scaling)  # type: ignore[assignment]
            fields += len(block.native_points)
        self.struct = struct.Struct(fmt)
        self.fmt = fmt
        self.size = self.struct.size
        self.n = len(tids)
        self.consts = tuple(consts)
        self._tids = _getter(tids)
        self._heads = _getter(heads)
        self._raws = operator.itemgetter(raw_at["position"], raw_at["force"], raw_at["status"])
        ps, po, pf = self.scaling["position"]
        fs, fo, ff = self.scaling["force"]
        self._scaling = (ps, po, pf, fs, fo, ff)

    def match(self, buf: bytes, tid: int) -> tuple[float, float, int] | None:
        """(position, force in SI, the status word) if ``buf`` starts with the reply of the
        step whose first transaction id is ``tid`` (then ``tid + 1``, …), else ``None``."""
        if len(buf) < self.size:
            return None
        vals = self.struct.unpack_from(buf)
        if self._tids(vals) != tuple(range(tid, tid + self.n)) or self._heads(vals) != self.consts:
            return None
        pos, force, word = self._raws(vals)
        ps, po, pf, fs, fo, ff = self._scaling
        # value in units = raw · scale + offset; SI = that · factor (ModbusPoint.si)
        return (pos * ps + po) * pf, (force * fs + fo) * ff, int(word)


def _getter(fields: list[int]) -> Any:
    """``itemgetter`` that always returns a tuple (also of one field)."""
    if len(fields) == 1:
        (k,) = fields
        return lambda vals: (vals[k],)
    return operator.itemgetter(*fields)


def rtu_crc(frame: bytes | bytearray) -> bytes:
    """pymodbus's CRC of an RTU frame's address … data, as it appends it."""
    return _CRC.pack(_compute_crc(frame))

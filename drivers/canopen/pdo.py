"""PDO layout: :class:`Layout` packs and unpacks a PDO's mapped objects with one precompiled
struct, checked against the ``canopen`` library's encoding and decoding of its PDO maps
(:meth:`Layout.check`; the library stays the authority on the mapping).
"""

from __future__ import annotations

import logging
import random
import struct
from dataclasses import dataclass
from typing import Any, cast

from canopen.objectdictionary import ODVariable

from rths_hil.errors import InputError

log = logging.getLogger(__package__)


@dataclass(frozen=True)
class Layout:
    """Byte layout of one PDO: ``struct`` format and the bits it takes (checked ≤ 64)."""

    fmt: struct.Struct
    bits: int

    @classmethod
    def of(cls, variables: list[ODVariable], name: str) -> Layout:
        """The little-endian layout of ``variables`` in order (CiA 301 PDO mapping)."""
        bits = sum(len(v) for v in variables)
        if bits > 64:
            objs = " + ".join(
                f"0x{v.index:04X}:{v.subindex:02X} ({len(v)} bits)" for v in variables
            )
            raise InputError(f"canopen: {name} does not fit in 8 bytes: {objs} = {bits} bits")
        fmt = "<"
        for v in variables:
            st = v.STRUCT_TYPES.get(v.data_type) if v.data_type is not None else None
            if st is None or 8 * st.size != len(v):
                raise InputError(
                    f"canopen: {name}: object 0x{v.index:04X}:{v.subindex:02X} is not a "
                    "whole-byte integer"
                )
            fmt += st.format.lstrip("<")
        return cls(struct.Struct(fmt), bits)

    def check(self, pdo_map: Any, name: str, rng: random.Random, rounds: int = 8) -> None:
        """Refuse (one line) unless this layout packs and unpacks exactly as the library does.

        ``pdo_map`` is the library's PDO map (``canopen.pdo.PdoMap``) of the objects this
        layout was built from. For ``rounds`` sets of values (each object's extremes, 0, 1 and
        random values of its type) the bytes of :attr:`fmt` must equal the map's data after
        ``PdoVariable.raw = value`` for each mapped object (``ODVariable.encode_raw`` at the
        library's offsets), and for as many random payloads :attr:`fmt` must unpack the values
        ``PdoVariable.raw`` decodes. The map's data is restored afterwards. This is what lets
        the step pack and unpack a PDO with one precompiled ``struct`` call while the library
        stays the authority on the mapping and the encoding.
        """
        variables = list(pdo_map.map)
        size = self.fmt.size
        if sum(v.length for v in variables) != 8 * size:
            raise InputError(f"canopen: {name}: the library maps {len(variables)} objects that "
                             f"are not the {size} bytes the driver packs")  # fmt: skip
        samples = [_sample_values(v.od, rng, rounds) for v in variables]
        saved = pdo_map.data
        try:
            for j in range(rounds):
                values = [col[j] for col in samples]
                pdo_map.data = bytearray(size)
                for var, value in zip(variables, values, strict=True):
                    var.raw = value
                try:
                    ours = self.fmt.pack(*values)
                except struct.error as exc:
                    raise InputError(
                        f"canopen: {name}: the driver cannot pack {values} ({exc}), the canopen "
                        f"library's encoding is {bytes(pdo_map.data).hex()}"
                    ) from None
                if bytes(pdo_map.data) != ours:
                    raise InputError(
                        f"canopen: {name}: the driver's packing of {values} is {ours.hex()}, "
                        f"the canopen library's is {bytes(pdo_map.data).hex()}"
                    )
                payload = bytes(rng.getrandbits(8) for _ in range(size))
                pdo_map.data = bytearray(payload)
                lib = [var.raw for var in variables]
                mine = list(self.fmt.unpack(payload))
                if any(a != b and (a == a or b == b) for a, b in zip(lib, mine, strict=True)):
                    raise InputError(
                        f"canopen: {name}: the driver unpacks {payload.hex()} as {mine}, the "
                        f"canopen library as {lib}"
                    )
        finally:
            pdo_map.data = saved


def _sample_values(var: ODVariable, rng: random.Random, n: int) -> list[Any]:
    """``n`` values of ``var``'s type: its extremes, 0, 1, then random ones (floats for REAL)."""
    st = var.STRUCT_TYPES[cast(int, var.data_type)]
    code = st.format[-1]
    if code in "fd":
        base = [0.0, 1.5, -2.25]
        draw = lambda: st.unpack(st.pack(rng.uniform(-1e9, 1e9)))[0]  # noqa: E731
    elif code == "?":
        base = [False, True]
        draw = lambda: rng.random() < 0.5  # noqa: E731
    else:
        bits = 8 * st.size
        lo, hi = ((-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if code.islower()
                  else (0, (1 << bits) - 1))  # fmt: skip
        base = [lo, hi, 0, 1]
        draw = lambda: rng.randint(lo, hi)  # noqa: E731
    out = base[:n]
    while len(out) < n:
        out.append(draw())
    return out

"""The precompiled PDO packing of the CANopen driver and twin against the ``canopen`` library.

Each step packs the RPDO and unpacks the TPDOs with one ``struct`` per PDO
(:class:`rths_hil.drivers.canopen.Layout`); the library's own encoding (``ODVariable.encode_raw``
/ ``decode_raw``, and ``PdoVariable.raw`` on its PDO maps) is the independent reference here.
"""

from __future__ import annotations

import random
import struct
from pathlib import Path

import canopen
import pytest
from canopen import objectdictionary as odt
from canopen.objectdictionary import ODVariable
from rths_hil.drivers.canopen import Layout, load_od

from rths_hil.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
EDS402 = ROOT / "examples" / "controllers" / "cia402_drive.eds"
EDS408 = ROOT / "examples" / "controllers" / "cia408_axis.eds"

#: (data type, bits, signed)
TYPES = [
    (odt.INTEGER8, 8, True),
    (odt.INTEGER16, 16, True),
    (odt.INTEGER32, 32, True),
    (odt.INTEGER64, 64, True),
    (odt.UNSIGNED8, 8, False),
    (odt.UNSIGNED16, 16, False),
    (odt.UNSIGNED32, 32, False),
    (odt.UNSIGNED64, 64, False),
]


def _var(i: int, data_type: int) -> ODVariable:
    v = ODVariable(f"obj{i}", 0x2000 + i, 0)
    v.data_type = data_type
    return v


def _random_pdo(rng: random.Random) -> list[tuple[ODVariable, int, bool]]:
    """Up to 64 bits of random integer objects, in random order."""
    out, bits = [], 0
    while True:
        dt, n, signed = rng.choice(TYPES)
        if bits + n > 64:
            return out
        out.append((_var(len(out), dt), n, signed))
        bits += n


def test_layout_packs_and_unpacks_as_the_library_encodes_each_object():
    """For 300 random PDOs of signed and unsigned objects of 8–64 bits, the layout's bytes for
    random values (extremes included) equal the concatenation of the library's ``encode_raw``
    of each object, and random payloads unpack to the library's ``decode_raw`` of each slice."""
    rng = random.Random(402)
    for _ in range(300):
        pdo = _random_pdo(rng)
        if not pdo:
            continue
        layout = Layout.of([v for v, _, _ in pdo], "PDO")
        assert layout.bits == sum(n for _, n, _ in pdo)
        assert layout.fmt.size * 8 == layout.bits
        for _ in range(5):
            values = []
            for _v, n, signed in pdo:
                lo, hi = (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if signed else (0, 2**n - 1)
                values.append(rng.choice([lo, hi, 0, rng.randint(lo, hi)]))
            lib = b"".join(v.encode_raw(x) for (v, _, _), x in zip(pdo, values, strict=True))
            assert layout.fmt.pack(*values) == lib
            payload = bytes(rng.getrandbits(8) for _ in range(layout.fmt.size))
            offs, lib_vals = 0, []
            for v, n, _ in pdo:
                lib_vals.append(v.decode_raw(payload[offs : offs + n // 8]))
                offs += n // 8
            assert list(layout.fmt.unpack(payload)) == lib_vals


def test_layout_refuses_what_it_cannot_precompile():
    """More than 8 bytes, or an object that is not whole bytes, is refused in one line."""
    with pytest.raises(InputError, match=r"RPDO1 does not fit in 8 bytes: .* = 80 bits"):
        Layout.of([_var(0, odt.INTEGER64), _var(1, odt.INTEGER16)], "RPDO1")
    v = _var(0, odt.VISIBLE_STRING)
    with pytest.raises((InputError, KeyError, TypeError)):
        Layout.of([v], "TPDO1")


@pytest.mark.parametrize(
    ("eds", "objects"),
    [
        (EDS402, [(0x6040, 0), (0x607A, 0)]),  # RPDO1 of CiA 402: control word + target
        (EDS402, [(0x6041, 0), (0x6064, 0)]),  # TPDO1: status word + position actual
        (EDS408, [(0x6040, 0), (0x6600, 1)]),  # RPDO1 of CiA 408: control word + set-point
        (EDS408, [(0x6041, 0), (0x6601, 1)]),
    ],
)
def test_layout_check_agrees_with_the_library_pdo_map(eds, objects):
    """On the library's own PDO map of the examples' objects, ``Layout.check`` passes, leaves
    the map's data as it was, and the layout's bytes equal the map's after ``PdoVariable.raw``
    is set (an independent run of the library's encoding here)."""
    od = load_od(eds, 5)
    node = canopen.RemoteNode(5, od)
    pdo = node.rpdo[1]
    pdo.clear()
    for idx, sub in objects:
        pdo.add_variable(idx, sub)
    variables = [v.od for v in pdo.map]
    layout = Layout.of(variables, "PDO")
    before = bytearray(b"\x11" * layout.fmt.size)
    pdo.data = before
    layout.check(pdo, "PDO", random.Random(1))
    assert pdo.data is before and bytes(pdo.data) == b"\x11" * layout.fmt.size
    rng = random.Random(7)
    for _ in range(50):
        values = []
        for v in variables:
            st = v.STRUCT_TYPES[v.data_type]
            n = 8 * st.size
            lo, hi = (
                (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if st.format[-1].islower() else (0, 2**n - 1)
            )
            values.append(rng.randint(lo, hi))
        pdo.data = bytearray(layout.fmt.size)
        for var, x in zip(pdo.map, values, strict=True):
            var.raw = x
        assert layout.fmt.pack(*values) == bytes(pdo.data)
        assert list(layout.fmt.unpack(bytes(pdo.data))) == [var.raw for var in pdo.map]


def test_layout_check_refuses_a_layout_that_differs_from_the_map():
    """A layout of the same size in another order than the library's map (set-point before
    control word) is caught by the start-up check, naming both encodings."""
    od = load_od(EDS402, 5)
    node = canopen.RemoteNode(5, od)
    pdo = node.rpdo[1]
    pdo.clear()
    pdo.add_variable(0x6040)
    pdo.add_variable(0x607A)
    swapped = Layout(struct.Struct("<iH"), 48)
    with pytest.raises(InputError, match=r"RPDO1: the driver.* the canopen library's"):
        swapped.check(pdo, "RPDO1", random.Random(3))
    # unsigned read as signed: same size, same order, the decoding differs for some payload
    signed = Layout(struct.Struct("<hi"), 48)
    with pytest.raises(InputError, match=r"RPDO1: the driver"):
        signed.check(pdo, "RPDO1", random.Random(3))
    short = Layout(struct.Struct("<H"), 16)
    with pytest.raises(InputError, match=r"not the 2 bytes the driver packs"):
        short.check(pdo, "RPDO1", random.Random(3))

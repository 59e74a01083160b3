"""Raw Modbus TCP requests whose fields the Modbus application protocol refuses (exception 03,
ILLEGAL DATA VALUE; MODBUS Application Protocol V1.1b3 §6.5, §6.12, §6.17) sent to the twins,
the built-in one and the profile one: refused, and nothing written. The requests are built by
pymodbus (its framer) and then one field is changed, as a hostile client would; the answers are
decoded by pymodbus."""

from __future__ import annotations

import socket
import struct
from pathlib import Path

import pytest
from pymodbus.framer import FramerSocket
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.bit_message import ReadCoilsRequest, WriteSingleCoilRequest
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    WriteMultipleRegistersRequest,
)
from rths_hil.drivers.modbus.transport import illegal_data_value
from rths_hil.sim_backends.twin import default_plant, start_twin

pytestmark = pytest.mark.timing  # twins in threads, over sockets

MODBUS_MAP = Path(__file__).resolve().parents[2] / "examples" / "controllers" / "modbus_map.toml"
FRAMER = FramerSocket(DecodePDU(False))


def frame(pdu, tid: int = 1, unit: int = 1) -> bytearray:
    pdu.dev_id, pdu.transaction_id = unit, tid
    return bytearray(FRAMER.buildFrame(pdu))


def ask(sock: socket.socket, data: bytes):
    sock.sendall(bytes(data))
    sock.settimeout(1.0)
    used, _, _, pdu = FRAMER.decode(sock.recv(512))
    assert used and pdu
    return FRAMER.decoder.decode(pdu)


def coil_0x1234(address: int) -> bytearray:
    f = frame(WriteSingleCoilRequest(address=address, bits=[True]))
    struct.pack_into(">H", f, 10, 0x1234)  # the output value (ON is 0xFF00)
    return f


def fc16_byte_count_9(address: int) -> bytearray:
    f = frame(WriteMultipleRegistersRequest(address=address, registers=[0x4120, 0]))
    f[12] = 9  # byte count 9 for 2 registers, with 9 data bytes
    f += b"\x00" * 5
    struct.pack_into(">H", f, 4, len(f) - 6)  # the MBAP length
    return f


def fc16_quantity_32767(address: int) -> bytearray:
    f = frame(WriteMultipleRegistersRequest(address=address, registers=[0x4120, 0]))
    struct.pack_into(">H", f, 10, 32767)  # the quantity, with 4 data bytes
    return f


def test_the_check_follows_the_standard() -> None:
    good = [bytes(frame(WriteSingleCoilRequest(address=1, bits=[b])))[7:] for b in (True, False)]
    good.append(bytes(frame(WriteMultipleRegistersRequest(address=5, registers=[1] * 123)))[7:])
    good.append(bytes(frame(ReadHoldingRegistersRequest(address=0, count=125)))[7:])
    assert not any(illegal_data_value(p) for p in good)
    bad = [
        bytes(coil_0x1234(1))[7:],
        bytes(fc16_byte_count_9(100))[7:],
        bytes(fc16_quantity_32767(100))[7:],
    ]
    # past the limits (pymodbus's request classes refuse to build them): 124 registers
    # written, 126 read
    f = frame(WriteMultipleRegistersRequest(address=5, registers=[1] * 123))
    f += b"\x00\x01"
    struct.pack_into(">HB", f, 10, 124, 248)
    bad.append(bytes(f)[7:])
    f = frame(ReadHoldingRegistersRequest(address=0, count=125))
    struct.pack_into(">H", f, 10, 126)
    bad.append(bytes(f)[7:])
    assert all(illegal_data_value(p) for p in bad)


@pytest.mark.parametrize("profile", [None, MODBUS_MAP])
def test_twins_answer_illegal_fields_with_exception_03(profile) -> None:
    extra = {"profile": str(profile)} if profile else {}
    twin = start_twin("modbus", default_plant(), port=0, **extra)
    c = twin.connection
    coil = 2 if profile else 0  # the acknowledge coil of the map; the built-in e-stop coil
    try:
        with socket.create_connection((c.get("host", "127.0.0.1"), c["port"]), 1.0) as s:
            r = ask(s, coil_0x1234(coil))
            assert r.function_code == 0x85 and r.exception_code == 3, r
            r = ask(s, frame(ReadCoilsRequest(address=coil, count=1)))
            assert r.bits[0] is False  # not taken as ON
            if profile:
                for bad in (fc16_byte_count_9(100), fc16_quantity_32767(100)):
                    r = ask(s, bad)
                    assert r.function_code == 0x90 and r.exception_code == 3, r
                r = ask(s, frame(ReadHoldingRegistersRequest(address=100, count=2)))
                assert r.registers == [0, 0]  # the set-point was not written
                ok = ask(s, frame(WriteSingleCoilRequest(address=coil, bits=[True])))
                assert ok.function_code == 5  # a well-formed request is still served
    finally:
        twin.stop()


@pytest.mark.parametrize("profile", [None, MODBUS_MAP])
def test_twins_answer_requests_split_across_segments(profile) -> None:
    """Two reads written together, the second cut in the middle and its rest sent later (TCP
    may deliver a pipelined write in any segments): each twin answers both, the first at once
    (MODBUS Messaging on TCP/IP V1.0b §3.1: the MBAP length delimits a request, not the
    segment)."""
    extra = {"profile": str(profile)} if profile else {}
    twin = start_twin("modbus", default_plant(), port=0, **extra)
    c = twin.connection
    coil = 2 if profile else 0
    first = frame(ReadCoilsRequest(address=coil, count=1), tid=7)
    second = frame(ReadCoilsRequest(address=coil, count=1), tid=8)
    try:
        with socket.create_connection((c.get("host", "127.0.0.1"), c["port"]), 1.0) as s:
            s.settimeout(1.0)
            s.sendall(bytes(first + second[:5]))
            used, _, tid, pdu = FRAMER.decode(s.recv(512))
            assert used and tid == 7 and pdu[0] == 1, (used, tid, pdu)
            s.sendall(bytes(second[5:]))
            used, _, tid, pdu = FRAMER.decode(s.recv(512))
            assert used and tid == 8 and pdu[0] == 1, (used, tid, pdu)
    finally:
        twin.stop()

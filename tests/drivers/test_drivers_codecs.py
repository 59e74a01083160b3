"""Wire formats checked against the field's libraries, and malformed frames from fake peers.

* CAN: the driver's compiled DBC codec against ``cantools`` encode/decode of the same DBC.
* Modbus: the driver's request bytes against pymodbus's ``ReadWriteMultipleRegistersRequest``
  built by ``FramerSocket`` / ``FramerRTU``; responses built by pymodbus decoded by the driver.
* Serial: frames built by hand from the documented format (cobs + binascii.crc_hqx + struct).
* Every malformed frame kind is counted under its reason and never raises.
"""

from __future__ import annotations

import binascii
import copy
import math
import os
import random
import socket
import struct
import tty

import can
import cantools
import pytest
from cobs import cobs
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU, ExceptionResponse
from pymodbus.pdu.register_message import (
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
)
from rths_hil.drivers.base import Driver, Status, extend_seq
from rths_hil.drivers.can import CANDriver, virtual_rx_queue
from rths_hil.drivers.can.codec import DBC_PATH, Frame, load
from rths_hil.drivers.modbus import Link, ModbusDriver
from rths_hil.drivers.registry import available, create_driver, driver_class
from rths_hil.drivers.serial import SerialDriver
from rths_hil.sim_backends.endpoints.base import TwinController
from rths_hil.sim_backends.endpoints.can import CANTwin
from rths_hil.sim_backends.faults import Faults
from rths_hil.sim_backends.twin import default_plant

from rths_hil.errors import InputError

DB = cantools.database.load_file(str(DBC_PATH))


# -- CAN ----------------------------------------------------------------------------------------
class _CaptureBus:
    def __init__(self) -> None:
        self.sent: list[can.Message] = []

    def send(self, msg: can.Message) -> None:
        self.sent.append(can.Message(arbitration_id=msg.arbitration_id, data=bytes(msg.data)))


def test_can_command_bytes_decode_with_cantools() -> None:
    drv = CANDriver(channel="unused")
    drv._bus = _CaptureBus()  # type: ignore[assignment]
    rng = random.Random(1)
    for _ in range(200):
        seq = rng.randrange(0, 10**6)
        disp = rng.uniform(-0.5, 0.5)
        enable = rng.random() < 0.5
        drv.send(seq, disp, enable)
        msg = drv._bus.sent[-1]
        assert msg.arbitration_id == 0x100
        dec = DB.decode_message(msg.arbitration_id, msg.data)
        assert dec["Seq"] == seq % 65536
        assert dec["Control"] == int(enable)
        assert dec["Displacement"] == pytest.approx(disp, abs=0.5e-7 + 1e-15)
    drv.estop()
    drv.heartbeat()
    estop, hb = drv._bus.sent[-2:]
    assert estop.arbitration_id < min(m.frame_id for m in DB.messages if m.name != "EStop")
    assert (
        DB.decode_message(estop.arbitration_id, estop.data, decode_choices=True)["EStopKey"]
        == "ESTOP"
    )
    assert DB.decode_message(hb.arbitration_id, hb.data) == {"Counter": 1}


def test_can_feedback_from_cantools_decodes_in_driver() -> None:
    drv = CANDriver(channel="unused")
    fb = DB.get_message_by_name("Feedback")
    rng = random.Random(2)
    flagged = 0  # samples the controller flags SENSOR_INVALID: delivered without a measurement
    for k in range(200):
        disp = round(rng.uniform(-0.8, 0.8) / 1e-7) * 1e-7
        force = round(rng.uniform(-4e6, 4e6) / 0.5) * 0.5
        status = rng.randrange(0, 64)
        data = fb.encode({"Seq": k % 256, "Status": status, "Displacement": disp, "Force": force})
        drv._last_sent = k
        out = drv._handle(can.Message(arbitration_id=fb.frame_id, data=data, is_extended_id=False))
        assert out is not None
        assert (out.seq, out.status) == (k, status)
        if status & Status.SENSOR_INVALID:
            flagged += 1
            assert math.isnan(out.displacement)
        else:
            assert out.displacement == pytest.approx(disp, abs=1e-12)
        assert out.force == pytest.approx(force, abs=1e-6)
    # The INVALID raw value of the DBC's value table decodes to NaN.
    data = fb.encode(
        {"Seq": 200 % 256, "Status": Status.SENSOR_INVALID, "Displacement": "INVALID", "Force": 1.0}
    )
    drv._last_sent = 200
    out = drv._handle(can.Message(arbitration_id=fb.frame_id, data=data, is_extended_id=False))
    assert math.isnan(out.displacement) and out.force == 1.0
    assert flagged > 0 and drv.stats.invalid_values == flagged + 1


def test_can_codec_pack_unpack_equals_cantools() -> None:
    codecs = load()
    rng = random.Random(3)
    for codec in (codecs.command, codecs.feedback):
        msg = DB.get_message_by_frame_id(codec.frame_id)
        for _ in range(100):
            raw = [rng.randint(*codec.raw_range(i)) for i in range(len(codec.names))]
            data = codec.pack(*raw)
            assert codec.unpack(data) == raw
            assert DB.decode_message(codec.frame_id, data, scaling=False) == dict(
                zip(codec.names, raw, strict=True)
            )
            assert msg.encode(dict(zip(codec.names, raw, strict=True)), scaling=False) == data


def test_can_malformed_frames_are_counted() -> None:
    channel = "malformed-can"
    with CANDriver(channel=channel) as drv, can.Bus(interface="virtual", channel=channel) as peer:
        drv.send(0, 0.0)
        peer.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x180, data=bytes(5), is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x180, data=bytes(8), is_extended_id=True))
        peer.send(can.Message(arbitration_id=0x180, data=bytes(8), is_error_frame=True))
        good = DB.encode_message(
            "Feedback", {"Seq": 0, "Status": 1, "Displacement": 0.001, "Force": 2.5}
        )
        peer.send(can.Message(arbitration_id=0x180, data=good, is_extended_id=False))
        fb = drv.receive(1.0)
        assert fb is not None and fb.displacement == pytest.approx(0.001) and fb.force == 2.5
        assert drv.stats.malformed_reasons == {"unknown_id": 1, "bad_length": 1, "bad_frame": 2}
        # feedback for a command never sent is not delivered (with an 8-bit echo a number
        # ahead of the last command reads as an old one)
        peer.send(
            can.Message(
                arbitration_id=0x180,
                data=DB.encode_message(
                    "Feedback", {"Seq": 9, "Status": 1, "Displacement": 0, "Force": 0}
                ),
                is_extended_id=False,
            )
        )
        assert drv.receive(0.1) is None
        assert drv.stats.duplicates == 1 and drv.stats.received == 1


def test_can_frame_deepcopy_equals_python_cans_own() -> None:
    """Frame's cheap copy carries every slot of can.Message, as python-can's deepcopy does."""
    slots = [a for a in can.Message.__slots__ if a != "__weakref__"]
    cases = [
        dict(arbitration_id=0x100, data=bytearray(range(8)), is_extended_id=False),
        dict(arbitration_id=0x1ABCDE, data=b"\x01\x02", is_extended_id=True, channel="ch"),
        dict(arbitration_id=0x7FF, is_remote_frame=True, dlc=3, is_extended_id=False),
        dict(arbitration_id=0x10, is_error_frame=True, timestamp=12.5, is_rx=False),
        dict(
            arbitration_id=0x123,
            data=bytes(range(64)),
            is_fd=True,
            bitrate_switch=True,
            error_state_indicator=True,
            channel=1,
        ),
    ]
    for kw in cases:
        frame = Frame(**kw)
        reference = copy.deepcopy(can.Message(**kw))  # python-can's __deepcopy__
        dup = copy.deepcopy(frame)
        assert type(dup) is can.Message
        for name in slots:
            assert getattr(dup, name) == getattr(reference, name), name
            assert type(getattr(dup, name)) is type(getattr(reference, name)), name
        assert dup.data is not frame.data
        frame.data[:1] = b"\xff" if frame.data else b""
        assert dup.data == reference.data  # the copy does not follow the reused frame


def test_can_driver_reads_a_filtered_virtual_bus_through_recv() -> None:
    channel = "filtered-can"
    with can.Bus(interface="virtual", channel=channel) as plain:
        assert virtual_rx_queue(plain) is plain.queue
    assert virtual_rx_queue(None) is None
    filters = [{"can_id": 0x180, "can_mask": 0x7FF, "extended": False}]
    with (
        CANDriver(channel=channel, bus_options={"can_filters": filters}) as drv,
        can.Bus(interface="virtual", channel=channel) as peer,
    ):
        assert drv._rxq is None  # python-can applies the filter in recv()
        drv.send(0, 0.0)
        peer.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False))
        good = DB.encode_message(
            "Feedback", {"Seq": 0, "Status": 1, "Displacement": -0.002, "Force": -7.5}
        )
        peer.send(can.Message(arbitration_id=0x180, data=good, is_extended_id=False))
        fb = drv.receive(1.0)
        assert fb is not None and (fb.displacement, fb.force) == (pytest.approx(-0.002), -7.5)
        assert drv.stats.malformed_reasons == {}  # 0x123 never reached the driver


def test_can_twin_feedback_bytes_equal_cantools() -> None:
    """The twin's compiled feedback encoder against cantools, clamping and INVALID included."""
    twin = CANTwin(TwinController(default_plant(0.0, 1.0, dt=1e-3)), channel="unused")
    msg = DB.get_message_by_name("Feedback")
    d_lo, d_hi = -(2**23), 2**23 - 1
    rng = random.Random(4)
    values = [rng.uniform(-1.0, 1.0) for _ in range(300)] + [0.8388607, -0.8388608, 5.0, -5.0]
    forces = [rng.uniform(-5e6, 5e6) for _ in range(300)] + [4194303.5, -4194304.0, 1e9, -1e9]
    values += [math.nan, math.inf, 0.1]
    forces += [1.0, -1.0, -math.inf]
    for k, (d, f) in enumerate(zip(values, forces, strict=True)):
        status = rng.randrange(0, 64)
        frames = twin._encode(k, d, f, status)
        assert len(frames) == 1 and frames[0].arbitration_id == msg.frame_id

        def raw(x, scale):
            if not math.isfinite(x):
                return "INVALID"
            # the controller never sends the reserved INVALID value for a real measurement
            return max(d_lo + 1, min(d_hi, round(x / scale)))

        expected = msg.encode(
            {
                "Seq": k % 256,
                "Status": status,
                "Displacement": raw(d, 1e-7),
                "Force": raw(f, 0.5),
            },
            scaling=False,
        )
        assert bytes(frames[0].data) == expected, (k, d, f)


def test_can_bad_dbc_and_bad_interface() -> None:
    with pytest.raises(InputError, match="cannot load DBC"):
        CANDriver(dbc="/nonexistent.dbc")
    with pytest.raises(InputError, match="cannot open interface"):
        CANDriver(interface="no-such-interface").open()


# -- Modbus -------------------------------------------------------------------------------------
def _modbus_pair(transport: str) -> tuple[ModbusDriver, int]:
    """A driver whose descriptor is one end of a socket pair; returns (driver, peer fd)."""
    kw = {"device": "unused"} if transport == "rtu" else {}
    drv = ModbusDriver(transport=transport, **kw)
    a, b = socket.socketpair()
    a.setblocking(False)
    link = Link(None, lambda: (a, None, a.fileno()))
    link.units[drv.device_id] = drv
    link.connect()
    drv._link = link
    drv._peer = b  # keep it alive
    return drv, b.fileno()


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_modbus_request_bytes_equal_pymodbus(transport: str) -> None:
    drv, peer = _modbus_pair(transport)
    framer = (FramerSocket if transport == "tcp" else FramerRTU)(DecodePDU(False))
    rng = random.Random(4)
    for _ in range(50):
        seq, disp, enable = rng.randrange(0, 10**6), rng.uniform(-1, 1), rng.random() < 0.5
        drv.send(seq, disp, enable)
        got = os.read(peer, 4096)
        raw = round(disp / 1e-7) & 0xFFFFFFFF
        req = ReadWriteMultipleRegistersRequest(
            read_address=16,
            read_count=7,
            write_address=0,
            write_registers=[seq & 0xFFFF, int(enable), raw >> 16, raw & 0xFFFF],
            dev_id=1,
            transaction_id=seq & 0xFFFF if transport == "tcp" else 0,
        )
        assert got == framer.buildFrame(req)
    drv.close()


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_modbus_pymodbus_response_decodes_in_driver(transport: str) -> None:
    drv, peer = _modbus_pair(transport)
    framer = (FramerSocket if transport == "tcp" else FramerRTU)(DecodePDU(True))
    disp_raw, force_raw = -1234567, 98765432
    for seq in (3, 4):
        block = struct.pack(">HHii", seq, Status.ENABLED, disp_raw, force_raw)
        regs = [*struct.unpack(">6H", block), binascii.crc_hqx(block, 0xFFFF)]
        resp = ReadWriteMultipleRegistersResponse(registers=regs, dev_id=1, transaction_id=seq)
        drv.send(seq, 0.0)
        os.read(peer, 4096)
        os.write(peer, framer.buildFrame(resp))
        fb = drv.receive(1.0)
        assert fb is not None
        assert (fb.seq, fb.status) == (seq, Status.ENABLED)
        assert fb.displacement == pytest.approx(disp_raw * 1e-7, abs=1e-15)
        assert fb.force == pytest.approx(force_raw * 0.01, abs=1e-9)
    drv.close()


def test_modbus_tcp_malformed_frames_are_counted() -> None:
    drv, peer = _modbus_pair("tcp")
    framer = FramerSocket(DecodePDU(True))

    def response(seq: int, dev_id: int = 1, crc_delta: int = 0, tid: int | None = None) -> bytes:
        block = struct.pack(">HHii", seq, 1, 1000, 2000)
        regs = [
            *struct.unpack(">6H", block),
            (binascii.crc_hqx(block, 0xFFFF) + crc_delta) & 0xFFFF,
        ]
        r = ReadWriteMultipleRegistersResponse(
            registers=regs, dev_id=dev_id, transaction_id=seq if tid is None else tid
        )
        return framer.buildFrame(r)

    drv.send(7, 0.0)
    os.read(peer, 4096)
    os.write(peer, response(7, dev_id=9))  # another unit
    os.write(peer, response(7, crc_delta=1))  # FB_CRC wrong
    os.write(peer, response(7, tid=8))  # transaction id does not match the echoed SEQ
    os.write(peer, framer.buildFrame(ExceptionResponse(23, 2, device_id=1, transaction=7)))
    short = ReadWriteMultipleRegistersResponse(registers=[7, 1, 0], dev_id=1, transaction_id=7)
    os.write(peer, framer.buildFrame(short))
    os.write(peer, response(7))
    fb = drv.receive(1.0)
    assert fb is not None and fb.seq == 7 and fb.displacement == pytest.approx(1e-4)
    assert drv.stats.malformed_reasons == {
        "unknown_id": 1,
        "bad_crc": 1,
        "bad_frame": 1,
        "modbus_exception": 1,
        "bad_length": 1,
    }
    os.write(peer, b"\x00\x07\x00\x05\x00\x03\x01\x17")  # protocol id 5: not Modbus
    assert drv.receive(0.05) is None
    assert drv.stats.malformed_reasons["bad_header"] == 1
    drv.close()


def test_modbus_rtu_bad_crc_and_foreign_unit() -> None:
    drv, peer = _modbus_pair("rtu")
    framer = FramerRTU(DecodePDU(True))
    block = struct.pack(">HHii", 2, 1, 5, 6)
    regs = [*struct.unpack(">6H", block), binascii.crc_hqx(block, 0xFFFF)]
    good = framer.buildFrame(ReadWriteMultipleRegistersResponse(registers=regs, dev_id=1))
    drv.send(2, 0.0)
    os.read(peer, 4096)
    os.write(peer, Faults.flip_bit(good, 6))
    assert drv.receive(0.05) is None
    os.write(peer, framer.buildFrame(ReadWriteMultipleRegistersResponse(registers=regs, dev_id=4)))
    assert drv.receive(0.05) is None
    os.write(peer, good)
    fb = drv.receive(1.0)
    assert fb is not None and fb.force == pytest.approx(0.06)
    assert drv.stats.malformed_reasons == {"bad_crc": 1, "unknown_id": 1}
    drv.close()


def test_modbus_connection_errors_are_input_errors() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nobody listens there
    with pytest.raises(InputError, match="cannot connect"):
        ModbusDriver(port=port).open()
    with pytest.raises(InputError, match="needs device"):
        ModbusDriver(transport="rtu")
    with pytest.raises(
        InputError, match=r"^driver\.connection\.transport: must be one of tcp, rtu, got 'udp'$"
    ):
        create_driver("modbus", transport="udp")


# -- serial -------------------------------------------------------------------------------------
def _frame(body: bytes) -> bytes:
    return cobs.encode(body + struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))) + b"\x00"


def test_serial_frames_by_hand() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with SerialDriver(os.ttyname(slave)) as drv:
            drv.send(123456, -0.0123, enable=True)
            data = os.read(master, 4096)
            assert data.endswith(b"\x00") and data.count(b"\x00") == 1
            raw = cobs.decode(data[:-1])
            body, crc = raw[:-2], struct.unpack("<H", raw[-2:])[0]
            assert crc == binascii.crc_hqx(body, 0xFFFF)
            assert struct.unpack("<BIBd", body) == (0x01, 123456, 1, -0.0123)
            drv.estop()
            raw = cobs.decode(os.read(master, 4096)[:-1])
            assert raw[:2] == b"\x02\xa5"

            good = _frame(struct.pack("<BIBdd", 0x81, 123456, 3, 0.25, -7.5))
            bad_crc = bytearray(cobs.decode(good[:-1]))
            bad_crc[6] ^= 0x10
            os.write(master, b"\x05\x01\x00")  # COBS code byte pointing past the frame
            os.write(master, cobs.encode(bytes(bad_crc)) + b"\x00")
            os.write(master, _frame(struct.pack("<BIBdd", 0x42, 123456, 3, 0.25, -7.5)))
            os.write(master, _frame(struct.pack("<BIBd", 0x81, 123456, 3, 0.25)))
            os.write(master, _frame(b"\x81"))
            os.write(master, b"\x00\x00" + good)
            fb = drv.receive(1.0)
            assert (fb.seq, fb.status, fb.displacement, fb.force) == (123456, 3, 0.25, -7.5)
            assert drv.stats.malformed_reasons == {
                "bad_cobs": 1,
                "bad_crc": 1,
                "unknown_id": 1,
                "bad_length": 2,
            }
    finally:
        os.close(master)
        os.close(slave)


def test_serial_loop_url_and_missing_device() -> None:
    with SerialDriver("loop://") as drv:  # our own command comes back: not a feedback frame
        drv.send(0, 0.001)
        assert drv.receive(0.05) is None
        assert drv.stats.malformed_reasons == {"unknown_id": 1}
        assert drv.stats.timeouts == 1
    with pytest.raises(InputError, match="cannot open"):
        SerialDriver("/dev/does-not-exist").open()


# -- shared pieces ------------------------------------------------------------------------------
def test_extend_seq_brute_force() -> None:
    rng = random.Random(5)
    for _ in range(2000):
        bits = rng.choice([8, 16])
        ref = rng.randrange(0, 10**6)
        true = ref - rng.randrange(0, 1 << bits)
        assert extend_seq(true & ((1 << bits) - 1), ref, bits) == true


def test_registry() -> None:
    names = available()
    assert {"can", "modbus", "serial"} <= set(names)
    assert driver_class("can") is CANDriver
    assert issubclass(driver_class("serial"), Driver)
    drv = create_driver("modbus", host="127.0.0.1", port=1502)
    assert isinstance(drv, ModbusDriver) and drv.port == 1502
    with pytest.raises(InputError, match="unknown driver 'profibus'"):
        create_driver("profibus")
    with pytest.raises(
        InputError,
        match=r"^driver\.connection\.baud_rate: unknown key \(did you mean 'baudrate'\?\)",
    ):
        create_driver("serial", url="loop://", baud_rate=9600)


def test_fault_plan_text() -> None:
    f = Faults.parse("drop=5,9; delay=12:0.02,13:0.5; corrupt=20\nstuck_from=100; p_drop=0.01")
    assert f.drop == {5, 9} and f.delay == {12: 0.02, 13: 0.5} and f.corrupt == {20}
    assert f.stuck_from == 100 and f.p_drop == 0.01
    with pytest.raises(InputError, match="'explode=1'"):
        Faults.parse("explode=1")
    with pytest.raises(InputError, match="cannot read"):
        Faults.parse("drop=five")
    with pytest.raises(InputError, match="probability"):
        Faults(p_drop=2.0)

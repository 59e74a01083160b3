"""Link budget arithmetic (rths_hil.linkbudget, the protocols' link models) against hand-worked
and brute-force frames.

References: the issue's hand-worked numbers (an 8-byte classic CAN frame is 111–135 bits;
command + feedback per channel at 1024 Hz ≈ 28 % of 1 Mbit/s), CAN frames built bit by bit
(CRC-15 and bit stuffing computed here) from cantools-encoded DBC messages, Modbus RTU frames
built by pymodbus's FramerRTU, serial frames built by the driver's own encoder, CAN frames
through a serial line as python-can's ``slcan`` and ``serial`` interfaces write them, and a real
pseudo-terminal for the "no limit" case.
"""

from __future__ import annotations

import os
import random

import cantools
import pytest
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import (
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
)
from rths_hil.drivers.can.codec import DBC_PATH
from rths_hil.drivers.can.linkbudget import (
    can_fd_frame_time,
    can_frame_bits,
    can_serial_frame_chars,
)
from rths_hil.drivers.modbus.linkbudget import rtu_frame_bytes, rtu_transaction_time
from rths_hil.drivers.serial.framing import COMMAND, FEEDBACK, T_COMMAND, T_FEEDBACK, encode_frame
from rths_hil.drivers.serial.linkbudget import cobs_frame_bytes, serial_frame_bytes

from rths_hil.errors import InputError
from rths_hil.linkbudget import check_links, format_loads, link_key, link_load

FS = 1024.0
CAN_1M = {"interface": "socketcan", "channel": "can0", "bitrate": 1_000_000}


# -- classic CAN, bit by bit ------------------------------------------------------------------
def _bits(value: int, n: int) -> list[int]:
    return [(value >> (n - 1 - i)) & 1 for i in range(n)]


def _crc15(bits: list[int]) -> int:
    """CAN CRC-15, polynomial 0x4599 (ISO 11898-1), bit-serial."""
    crc = 0
    for b in bits:
        nxt = b ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= 0x4599
    return crc


def _stuffed_frame_bits(can_id: int, data: bytes) -> int:
    """Bits on the bus of a standard data frame, built and stuffed bit by bit, + 3-bit IFS."""
    head = [0, *_bits(can_id, 11), 0, 0, 0, *_bits(len(data), 4)]  # SOF, id, RTR, IDE, r0, DLC
    body = head + [b for byte in data for b in _bits(byte, 8)]
    body += _bits(_crc15(body), 15)
    stuffed, run, last = 0, 0, None
    for b in body:  # after 5 equal bits, a complementary stuff bit (which starts a new run)
        if b == last:
            run += 1
        else:
            run, last = 1, b
        if run == 5:
            stuffed += 1
            run, last = 1, 1 - b
    return len(body) + stuffed + 1 + 2 + 7 + 3  # CRC delimiter, ACK slot+delim, EOF, IFS


def test_can_frame_bits_hand_worked():
    # 8 bytes, 11-bit id: 1+11+1+1+1+4 + 64 + 15 + 1+1+1 + 7 + 3 = 111; stuff ≤ ⌊97/4⌋ = 24
    assert can_frame_bits(8, stuffing=False) == 111
    assert can_frame_bits(8) == 135
    assert can_frame_bits(1) == 47 + 8 + (34 + 8 - 1) // 4 == 65
    assert can_frame_bits(0, stuffing=False) == 47
    assert can_frame_bits(8, extended=True) == 131 + (54 + 64 - 1) // 4
    with pytest.raises(InputError):
        can_frame_bits(9)


def test_can_frames_from_the_dbc_stay_within_the_bound():
    """Real Command/Feedback frames (cantools), stuffed bit by bit: 111 ≤ bits ≤ 135."""
    db = cantools.database.load_file(str(DBC_PATH))
    cmd, fb = db.get_message_by_name("Command"), db.get_message_by_name("Feedback")
    rng = random.Random(13)
    worst = 0
    frames = [
        (0x100, bytes(8)),  # all zeros: the longest runs
        (0x100, b"\xff" * 8),
        (0x180, bytes([0x0F, 0x83, 0xE0, 0xF8, 0x3E, 0x0F, 0x83, 0xE0])),  # 5-bit alternating runs
    ]
    for _ in range(300):
        frames.append(
            (
                cmd.frame_id,
                cmd.encode(
                    {
                        "Seq": rng.randrange(65536),
                        "Displacement": rng.uniform(-0.2, 0.2),
                        "Control": 1,
                    }
                ),
            )
        )
        frames.append(
            (
                fb.frame_id,
                fb.encode(
                    {
                        "Seq": rng.randrange(256),
                        "Status": 1,
                        "Displacement": rng.uniform(-0.5, 0.5),
                        "Force": rng.uniform(-1e6, 1e6),
                    }
                ),
            )
        )
    for can_id, data in frames:
        n = _stuffed_frame_bits(can_id, data)
        assert can_frame_bits(8, stuffing=False) <= n <= can_frame_bits(8)
        worst = max(worst, n)
    assert worst > 111  # stuffing happens on real frames


def test_can_load_per_channel_and_refusal():
    one = link_load("can", CAN_1M, 1, FS)
    # (135 + 135) bits × 1024 Hz / 1 Mbit/s = 27.6 %
    assert one.load == pytest.approx(270 * 1024 / 1e6)
    assert 0.27 < one.load < 0.28
    three = link_load("can", CAN_1M, 3, FS)
    assert three.load == pytest.approx(0.8294, abs=1e-4)  # 83 %: above the 80 % default
    with pytest.raises(InputError):
        check_links([three])
    check_links([three], limit=0.85)
    two = link_load("can", CAN_1M, 2, FS)
    check_links([two])
    four = link_load("can", CAN_1M, 4, FS)
    with pytest.raises(InputError) as e:
        check_links([two, four])
    msg = str(e.value)
    assert "\n" not in msg
    assert "can socketcan:can0" in msg and "111 %" in msg
    # fits: 0.8 / (4 × 270 µs) = 740.7 Hz; 0.8 / (270 µs × 1024) = 2.9 → 2 channels
    assert "≤ 740 Hz" in msg and "≤ 2 channels" in msg and "CAN FD" in msg
    # 500 kbit/s: one channel 55 % fits, two (111 %) need 1 Mbit/s
    check_links([link_load("can", {**CAN_1M, "bitrate": 500_000}, 1, FS)])
    with pytest.raises(InputError) as e:
        check_links([link_load("can", {**CAN_1M, "bitrate": 500_000}, 2, FS)])
    assert "a bit rate of 1 Mbit/s" in str(e.value)
    # heartbeats add (47 + 8 + ⌊41/4⌋) = 65 bits per heartbeat
    hb = link_load("can", CAN_1M, 2, FS, heartbeat_hz=10.0)
    assert hb.load == pytest.approx((2 * 270 * 1024 + 2 * 65 * 10) / 1e6)


def test_can_fd_hand_worked():
    # 8 bytes: nominal 17 + 4 + 13 = 34 bits; data 5 + 64 + (⌊85/4⌋ − 4 = 17) + 4 + 17 + 6 = 113
    assert can_fd_frame_time(8, 1e6, 5e6) == pytest.approx(34e-6 + 113 / 5e6)
    # 64 bytes: data 5 + 512 + (⌊533/4⌋ − 4 = 129) + 4 + 21 + 7 = 678
    assert can_fd_frame_time(64, 1e6, 5e6) == pytest.approx(34e-6 + 678 / 5e6)
    # 25 bytes are carried in a 32-byte frame
    assert can_fd_frame_time(25) == can_fd_frame_time(32)
    # without bit-rate switching an 8-byte FD frame is longer than the classic one (135 bits)
    assert can_fd_frame_time(8, 1e6, 1e6) * 1e6 == 34 + 113 > 135


def test_no_limit_links(tmp_path):
    virtual = link_load("can", {"interface": "virtual", "channel": "x"}, 4, FS)
    assert virtual.load is None and "no limit" in virtual.summary()
    assert "1105920 bit/s" in virtual.detail  # 4 × 270 × 1024
    # a bitrate on a virtual bus: the load is shown, not enforced
    info = link_load("can", {"interface": "virtual", "bitrate": 1_000_000}, 4, FS)
    assert info.load == pytest.approx(1.10592) and not info.enforced
    check_links([virtual, info])
    master, slave = os.openpty()
    try:
        pty = os.ttyname(slave)
        for ld in (
            link_load("modbus", {"transport": "rtu", "device": pty}, 2, FS),
            link_load("serial", {"url": pty, "baudrate": 9600}, 1, FS),
            link_load("serial", {"url": "loop://"}, 1, FS),
            link_load("modbus", {"host": "127.0.0.1", "port": 1502}, 4, FS),
            link_load("modbus", {"host": "localhost"}, 4, FS),
        ):
            assert ld.load is None, ld
            assert "no limit" in ld.summary()
    finally:
        os.close(master)
        os.close(slave)
    assert link_load("mylab", {"x": 1}, 1, FS).load is None


def test_modbus_rtu_frames_equal_pymodbus():
    req_n, resp_n = rtu_frame_bytes()
    req = ReadWriteMultipleRegistersRequest(
        read_address=16,
        read_count=7,
        write_address=0,
        write_registers=[0x1234, 1, 0x0001, 0xE240],
        dev_id=1,
    )
    resp = ReadWriteMultipleRegistersResponse(registers=list(range(7)), dev_id=1)
    assert req_n == len(FramerRTU(DecodePDU(False)).buildFrame(req)) == 21
    assert resp_n == len(FramerRTU(DecodePDU(True)).buildFrame(resp)) == 19


def test_modbus_rtu_transaction_time():
    # (21 + 19 + 2 × 3.5) characters × 11 bits / 115 200 baud = 4.488 ms (the issue's ≈ 4.3 ms
    # counted 38 bytes; drivers/modbus/driver.py's map has 40)
    t = rtu_transaction_time(115200)
    assert t == pytest.approx(47 * 11 / 115200)
    assert 4.3e-3 < t < 4.6e-3
    assert rtu_transaction_time(115200, "N", 1) == pytest.approx(47 * 10 / 115200)
    assert rtu_transaction_time(115200, spec_silence=True) == pytest.approx(
        40 * 11 / 115200 + 3.5e-3
    )
    ld = link_load("modbus", {"transport": "rtu", "device": "/dev/ttyUSB0"}, 1, FS)
    assert ld.load == pytest.approx(t * 1024)  # 460 %: cannot run at 1024 Hz at all
    with pytest.raises(InputError) as e:
        check_links([ld])
    msg = str(e.value)
    assert "modbus rtu /dev/ttyUSB0" in msg and "460 %" in msg
    assert "≤ 178 Hz" in msg  # 0.8 / 4.488 ms
    # at 100 Hz one channel fits: 44.9 %
    assert link_load("modbus", {"transport": "rtu", "device": "/dev/ttyS0"}, 1, 100).load == (
        pytest.approx(100 * t)
    )


def test_serial_frames_equal_the_driver_encoder():
    cmd = encode_frame(COMMAND.pack(T_COMMAND, 0x1234, 1, 0.0123456))
    fb = encode_frame(FEEDBACK.pack(T_FEEDBACK, 0x1234, 1, 0.0123, 2469.5))
    assert serial_frame_bytes() == (len(cmd), len(fb)) == (18, 26)
    assert cobs_frame_bytes(254) == 254 + 2 + 1
    # 921 600 baud, 8N1: (18 + 26) × 10 bits × 1024 Hz = 450 560 bit/s = 48.9 %
    ld = link_load("serial", {"url": "/dev/ttyUSB0", "baudrate": 921600}, 1, FS)
    assert ld.load == pytest.approx(44 * 10 * 1024 / 921600)
    check_links([ld])
    slow = link_load("serial", {"url": "/dev/ttyUSB0", "baudrate": 115200}, 1, FS)
    assert slow.load == pytest.approx(3.911, abs=1e-3)
    with pytest.raises(InputError) as e:
        check_links([slow])
    assert "921600 baud" in str(e.value) and "≤ 209 Hz" in str(e.value)


def test_modbus_tcp_on_a_network():
    ld = link_load("modbus", {"host": "192.168.1.20"}, 4, FS)
    # 4 × 8 × (25 + 23 + 2 × 90) bits × 1024 Hz / 100 Mbit/s
    assert ld.load == pytest.approx(4 * 8 * 228 * 1024 / 1e8)
    check_links([ld])


def test_link_keys_group_channels():
    assert link_key("can", {"interface": "virtual", "channel": "a"}) == link_key(
        "can", {"channel": "a", "bitrate": 500000}
    )
    assert link_key("modbus", {"host": "10.0.0.1", "port": 502, "device_id": 1}) == link_key(
        "modbus", {"host": "10.0.0.1", "port": 502, "device_id": 2}
    )
    assert link_key("modbus", {"host": "10.0.0.1"}) != link_key("modbus", {"host": "10.0.0.2"})
    lines = format_loads([link_load("can", CAN_1M, 2, FS)]).splitlines()
    assert lines == ["link can socketcan:can0: 55.3 % (" + lines[0].split("(", 1)[1]]


def test_bad_arguments():
    with pytest.raises(InputError):
        link_load("can", CAN_1M, 0, FS)
    with pytest.raises(InputError):
        link_load("can", CAN_1M, 1, 0.0)
    with pytest.raises(InputError) as e:
        link_load("can", {**CAN_1M, "bitrate": "fast"}, 1, FS)
    assert "bitrate" in str(e.value)
    with pytest.raises(InputError):
        link_load("modbus", {"transport": "rtu", "device": "/dev/ttyS0", "parity": "X"}, 1, FS)


# -- CAN through a serial line (python-can slcan / serial) -------------------------------------
@pytest.mark.parametrize("interface", ["slcan", "serial"])
def test_can_serial_line_frames_as_python_can_writes_them(interface):
    """Each data length: the bytes python-can's interface writes to a loop:// line."""
    import can

    opts = {"sleep_after_open": 0.0} if interface == "slcan" else {}
    bus = can.Bus(interface=interface, channel="loop://", **opts)
    port = bus.serialPortOrig if interface == "slcan" else bus._ser
    try:
        port.read(port.in_waiting)  # slcan's "O\r" on opening
        for n in range(9):
            msg = can.Message(arbitration_id=0x180, data=bytes(range(n)), is_extended_id=False)
            bus.send(msg)
            wrote = port.read(port.in_waiting)
            assert len(wrote) == can_serial_frame_chars(interface, n), (n, wrote)
    finally:
        bus.shutdown()


def test_can_serial_line_load_and_refusal():
    # python-can serial framing, 8-byte command and feedback: 19 + 19 bytes of 10 bits
    usb = {"interface": "serial", "channel": "/dev/ttyUSB0", "bus_options": {"baudrate": 921600}}
    ld = link_load("can", usb, 1, FS)
    assert ld.load == pytest.approx(38 * 10 * FS / 921600) and ld.kind == "serial"
    # slcan at python-can's default 115 200 baud: 22 + 22 characters, ≈ 3.9 × the line
    acm = {"interface": "slcan", "channel": "/dev/ttyACM0"}
    ld = link_load("can", acm, 1, FS)
    assert ld.load == pytest.approx(44 * 10 * FS / 115200)
    # needs 115200 · 3.91 / 0.8 ≈ 563 kbaud: the next standard rate is 921 600
    with pytest.raises(InputError, match=r"slcan:/dev/ttyACM0 is 391 % .*fit: .* 921600 baud$"):
        check_links([ld])
    # the baud rate from the channel suffix; the CAN bus behind it binds when it is slower
    fast = link_load("can", {**acm, "channel": "/dev/ttyACM0@3000000", "bitrate": 125_000}, 1, FS)
    assert fast.kind == "can" and fast.load == pytest.approx(2 * 135 * FS / 125_000)
    with pytest.raises(InputError, match="baud rate must be a number"):
        link_load("can", {**acm, "bus_options": {"tty_baudrate": "x"}}, 1, FS)


def test_can_serial_line_on_a_pseudo_terminal_has_no_limit():
    """The served CAN twin's null-modem pair: no line rate."""
    from rths_hil.sim_backends.endpoints.nullmodem import NullModem

    with NullModem() as cable:
        for interface in ("slcan", "serial"):
            ld = link_load("can", {"interface": interface, "channel": cable.bridge_path}, 4, FS)
            assert ld.load is None and "pseudo-terminal" in ld.summary()
            assert "no limit" in ld.summary()


def test_modbus_rtu_units_on_one_line_sum_their_transactions():
    # one master, one line: the units' FC 23 transactions queue. 115 200 baud 8E1:
    # T = (21 + 19 + 7) × 11 / 115 200 = 4.488 ms per unit and step.
    t = 47 * 11 / 115200
    line = {"transport": "rtu", "device": "/dev/ttyUSB0"}
    two_at_50 = link_load("modbus", line, 2, 50.0)
    assert two_at_50.load == pytest.approx(2 * t * 50) == pytest.approx(0.44878, abs=1e-5)
    check_links([two_at_50])  # 44.9 %: fits
    assert two_at_50.channels == 2 and "2 × FC 23" in two_at_50.detail
    # the same two units at 100 Hz: 2 × 4.488 ms × 100 = 89.8 % > 80 %
    two_at_100 = link_load("modbus", line, 2, 100.0)
    assert two_at_100.load == pytest.approx(0.89757, abs=1e-5)
    with pytest.raises(InputError) as e:
        check_links([two_at_100])
    msg = str(e.value)
    assert "90 % loaded with 2 channels at 100 Hz" in msg
    assert "≤ 89 Hz" in msg  # 0.8 / (2 × 4.488 ms) = 89.1 Hz
    assert "≤ 1 channel per link" in msg  # 0.8 / (4.488 ms × 100 Hz) = 1.78
    assert "230400 baud" in msg and "Modbus TCP" in msg
    # units on one TCP connection to the loopback: no limit, whatever their number
    assert link_load("modbus", {"host": "127.0.0.1", "port": 1502}, 8, FS).load is None


# -- a twin's own pseudo-terminal has no line rate; a real serial port is checked ----------------
def test_twin_pty_is_not_refused_on_a_line_rate_it_does_not_have():
    """Modbus RTU and serial without a device: the twin opens its own pseudo-terminal pair, so
    115 200 baud at 1024 Hz (460 % of a real line) is not refused; the same settings on a real
    serial port are refused with the hand-worked load (rtu_transaction_time · 1024)."""
    twin = link_load("modbus", {"transport": "rtu", "baudrate": 115200}, 1, FS)
    assert twin.load is None and not twin.limited
    assert "twin's own pseudo-terminal" in twin.summary() and "no limit" in twin.summary()
    assert "real serial port" in twin.summary() and twin.link == "modbus rtu twin pty"
    check_links([twin])
    ser = link_load("serial", {"baudrate": 9600}, 1, FS)
    assert ser.load is None and "twin's own pseudo-terminal" in ser.detail
    check_links([ser])
    real = link_load(
        "modbus", {"transport": "rtu", "baudrate": 115200, "device": "/dev/ttyS0"}, 1, FS
    )
    assert real.load == pytest.approx(rtu_transaction_time(115200) * FS)
    with pytest.raises(InputError, match=r"modbus rtu /dev/ttyS0 is 460 % loaded"):
        check_links([real])
    real_ser = link_load("serial", {"url": "/dev/ttyS0", "baudrate": 9600}, 1, FS)
    assert real_ser.load is not None and real_ser.load > 1.0
    with pytest.raises(InputError, match=r"serial /dev/ttyS0"):
        check_links([real_ser])


def test_builtin_modbus_rtu_with_its_twin_runs_at_115200_baud(tmp_path, capsys):
    """``rths-hil run`` with the built-in Modbus RTU driver and its twin at 115 200 baud and
    1024 Hz runs (lockstep) over the twin's pseudo-terminal; the same run on a named serial
    port is refused with one line, exit 2."""
    from rths_hil.cli import main
    from rths_hil.records.recorder import read_run

    cfg = os.path.join(os.path.dirname(__file__), "..", "..", "examples", "modbus.toml")
    out = tmp_path / "rtu"
    conn = 'driver.connection={transport="rtu", baudrate=115200}'
    args = ["run", cfg, "--lockstep", "--duration", "0.5", "--out", str(out), "--set", conn]
    assert main(args) == 0
    run = read_run(out)
    assert run.meta["twin"]["transport"] == "rtu"
    assert len(run.record) == 512 and bool(run.record["feedback_ok"].all())
    capsys.readouterr()
    real = 'driver.connection={transport="rtu", baudrate=115200, device="/dev/ttyS0"}'
    assert main([*args[:-1], real, "--set", "twin.enabled=false"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "modbus rtu /dev/ttyS0 is 460 % loaded" in err[0]

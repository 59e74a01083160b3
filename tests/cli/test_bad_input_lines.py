"""Bad frames and devices on a twin's line."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time

import pytest

from tests.helpers.cli import one_line_exit_2 as _one_line_exit_2


def _serve(*args: str):
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "rths_hil", "twin", "serve", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()
    return proc, line


# a twin served as its own process, read against the wall clock: run apart from the parallel
# tests (the "timing" marker, pyproject.toml; make test); the refused devices (in-process
# ``main``, no process started) run with the parallel tests
@pytest.mark.timing
def test_served_can_twin_survives_a_malformed_frame_from_a_second_writer():
    from rths_hil.drivers.can import CANDriver

    proc, line = _serve("--driver", "can", "--interface", "serial")
    try:
        m = re.search(r"(/dev/pts/\d+)", line)
        assert m, line
        path = m.group(1)
        fd = os.open(path, os.O_WRONLY | os.O_NOCTTY)
        try:
            # python-can serial frames: 0xAA, 4-byte timestamp, DLC, 4-byte id, data, 0xBB;
            # a DLC of 15 and a wrong end byte, as a second writer on the line could send
            os.write(fd, b"\xaa" + b"\0" * 4 + b"\x0f" + b"\x01\0\0\0" + b"\0" * 16)
            os.write(fd, b"\xaa" + b"\0" * 4 + b"\x02" + b"\x01\0\0\0" + b"\0\0" + b"\0")
        finally:
            os.close(fd)
        time.sleep(0.5)
        assert proc.poll() is None, proc.stderr.read()
        drv = CANDriver(interface="serial", channel=path)
        drv.open()
        try:
            replies = []
            for seq in range(1, 6):
                drv.send(seq, 0.0005 * seq)
                t_end = time.monotonic() + 2.0
                fb = None
                while fb is None and time.monotonic() < t_end:
                    fb = drv.receive(0.05)
                replies.append(fb)
        finally:
            drv.close()
        got = [fb for fb in replies if fb is not None]
        assert len(got) >= 4, replies  # the twin still answers after the garbage
        assert max(fb.seq for fb in got) >= 4
    finally:
        proc.send_signal(2)
        _, err = proc.communicate(timeout=20)
    assert "Traceback" not in err, err
    m = re.search(r"(\d+) malformed", err)
    assert m and int(m.group(1)) >= 2, err


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--driver", "serial", "--device", "/bogus/ttyUSB9"], "serves no device"),
        (["--driver", "modbus", "--transport", "rtu", "--device", "/bogus/ttyUSB9"], "No such"),
        (["--driver", "modbus", "--transport", "rtu", "--device", "/etc/hostname"], "not a serial"),
    ],
)
def test_twin_serve_device_that_is_not_a_serial_device(capsys, argv, needle):
    _one_line_exit_2(["twin", "serve", *argv], capsys, "--device", needle)

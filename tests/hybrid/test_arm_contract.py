"""The arming contract of :meth:`rths_hil.drivers.base.Driver.arm`: no set-point the actuator
would follow (issue 33, item 4), checked on small drivers that record what they write.

* set-point and enable in one frame (``atomic_command``): one disabled command, carrying the
  last position the driver measured (0 before any reply), never a target;
* set-point written apart from the enable: the position is read first without writing
  (``poll``) and the arming command writes exactly it; when it cannot be read nothing is
  written and arming gives ``None`` (a start refused on hardware).
"""

from __future__ import annotations

import math

from rths_hil.drivers.base import Driver, Feedback


class Recording(Driver):
    """A driver whose controller answers every command with ``position`` (and records them)."""

    name = "recording"
    honours_deadline = True

    def __init__(self, position: float) -> None:
        super().__init__()
        self.position = position
        self.written: list[tuple[int, float, bool]] = []
        self._pending: Feedback | None = None

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def estop(self) -> None:
        pass

    def _send_raw(self, seq: int, displacement: float, enable: bool) -> None:
        self.written.append((seq, displacement, enable))
        self._pending = Feedback(seq, self.position, 0.0, 0)

    def _recv_internal(self, deadline: float) -> Feedback | None:
        fb, self._pending = self._pending, None
        return fb


class SetpointRegister(Recording):
    """A register map: the set-point is applied when written, apart from the enable."""

    atomic_command = False

    def __init__(self, position: float, readable: bool = True) -> None:
        super().__init__(position)
        self.readable = readable
        self.polls = 0

    def poll(self, timeout, receive=None):
        self.polls += 1
        return Feedback(-1, self.position, 0.0, 0) if self.readable else None


def test_atomic_driver_arms_disabled_with_the_last_measured_position():
    drv = Recording(position=0.005)
    fb = drv.arm(0.1)
    assert fb is not None and fb.displacement == 0.005  # where the actuator is
    assert drv.written == [(0, 0.0, False)]  # nothing measured before: 0, disabled
    drv.send(0, 0.005, True)
    assert drv.receive(0.1) is not None
    drv.position = 0.0049
    drv.arm(0.1)  # a second run: the last measured position, still disabled
    assert drv.written[-1] == (0, 0.005, False)


def test_setpoint_register_is_written_with_where_the_actuator_is():
    drv = SetpointRegister(position=0.005)
    fb = drv.arm(0.1)
    assert drv.polls == 1 and fb is not None
    assert drv.written == [(0, 0.005, False)]  # read first, then exactly that


def test_unreadable_position_writes_nothing():
    drv = SetpointRegister(position=math.nan, readable=True)
    assert drv.arm(0.1) is None and drv.written == []
    drv = SetpointRegister(position=0.005, readable=False)
    assert drv.arm(0.1) is None and drv.written == []

"""Force-controlled channels on the driver side (issue #35): ``Driver.set_control``, the force
set-point roles of the controller profiles, and the refusals (one line) of a built-in
fixed-format driver and of a profile without a force role."""

from __future__ import annotations

import pytest
from rths_hil.drivers.base import Driver, Feedback
from rths_hil.drivers.registry import create_driver

from rths_hil.errors import InputError


# ------------------------------------------------------------------------------------------
# the base contract
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "conn"), [("can", {}), ("modbus", {}), ("serial", {"url": "loop://"})]
)
def test_builtin_fixed_format_drivers_refuse_force_with_one_line(name, conn):
    drv = create_driver(name, **conn)
    assert drv.control_modes == ("displacement",)
    with pytest.raises(InputError) as exc:
        drv.set_control("force")
    msg = str(exc.value)
    assert "\n" not in msg
    assert f"driver {name!r}" in msg and "'force'" in msg
    drv.set_control("displacement")
    assert drv.control == "displacement"


class _Echo(Driver):
    """A driver answering each command with a fixed measurement (the base contract only)."""

    name = "echo"
    honours_deadline = True
    control_modes = ("displacement", "force")

    def __init__(self, atomic: bool, measured: tuple[float, float]) -> None:
        super().__init__()
        self.atomic_command = atomic
        self.measured = measured
        self.sent: list[tuple[int, float, bool]] = []

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def estop(self) -> None:
        pass

    def _send_raw(self, seq, displacement, enable):
        self.sent.append((seq, displacement, enable))

    def _recv_internal(self, deadline):
        if not self.sent:
            return None
        return Feedback(self.sent[-1][0], *self.measured, 0)

    def poll(self, timeout, receive=None):
        return Feedback(-1, *self.measured, 0)


@pytest.mark.parametrize("atomic", [True, False])
def test_arming_in_force_mode_holds_the_measured_force(atomic):
    drv = _Echo(atomic, (0.0123, -4567.8))
    drv.set_control("force")
    if atomic:  # the atomic arming command carries the last measured force
        drv.send(7, 0.0, False)  # an earlier run's last command
        assert drv.receive(0.1) is not None
    fb = drv.arm(0.1)
    assert fb is not None and fb.force == pytest.approx(-4567.8)
    seq, value, enable = drv.sent[-1]
    assert (seq, enable) == (0, False)
    assert value == pytest.approx(-4567.8)  # a force set-point, not the position 0.0123


def test_force_command_checked_as_a_force():
    drv = _Echo(True, (0.0, 0.0))
    drv.set_control("force")
    with pytest.raises(InputError, match="command force for step 3 is not finite"):
        drv.send(3, float("nan"))

"""``twin serve`` refuses a fault plan or a bit rate that cannot be carried out, in one line with
exit 2, before it serves anything (a runaway at an infinite speed, an e-stop "ignored" 5 times,
a negative bit rate)."""

from __future__ import annotations

import pytest
from rths_hil.sim_backends.faults import Faults

from rths_hil.errors import InputError
from tests.helpers.cli import one_line_exit_2


@pytest.mark.parametrize(
    ("plan", "needle"),
    [
        ("runaway_rate=inf", "fault runaway_rate=inf: must be a finite speed"),
        ("runaway_rate=nan", "fault runaway_rate=nan: must be a finite speed"),
        ("estop_ignored=5", "fault estop_ignored=5: must be 0"),
        ("estop_ignored=-1", "fault estop_ignored=-1: must be 0"),
    ],
)
def test_a_fault_plan_that_cannot_be_carried_out(capsys, plan, needle):
    with pytest.raises(InputError, match=needle):
        Faults.parse(plan)
    one_line_exit_2(["twin", "serve", "--driver", "modbus", "--faults", plan], capsys, needle)


def test_the_plans_that_can_be_carried_out_still_parse():
    f = Faults.parse("runaway_from=10; runaway_rate=-0.5; estop_ignored=1")
    assert f.runaway_rate == -0.5 and f.estop_ignored == 1
    assert Faults.parse("estop_ignored=0").estop_ignored == 0


@pytest.mark.parametrize("rate", ["-5", "0", "abc", "9000000"])
def test_a_bit_rate_that_is_none(capsys, rate):
    one_line_exit_2(
        ["twin", "serve", "--driver", "can", "--interface", "slcan", f"--bitrate={rate}"],
        capsys, "--bitrate",
    )  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--driver", "modbus", "--bitrate", "500000"], "--bitrate: an option of the can and "),
        (["--driver", "can", "--device-id", "2"], "--device-id: an option of the modbus twins"),
    ],
)
def test_another_protocols_option_is_refused_not_ignored(capsys, argv, needle):
    one_line_exit_2(["twin", "serve", *argv], capsys, needle)

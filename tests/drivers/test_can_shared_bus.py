"""CAN drivers as nodes of one python-can bus (the base both CAN drivers share,
``rths_hil.drivers.can.SharedBusDriver``): one driver per feedback identifier, and a feedback
frame read by one node handed to the node it is for. Frames are encoded by cantools from the
shipped DBC, as a controller would send them."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import cantools
import pytest
from rths_hil.drivers.can import CANDriver
from rths_hil.drivers.can.profile import CANProfileDriver

from rths_hil.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
DBC = cantools.database.load_file(str(ROOT / "drivers" / "can" / "actuator.dbc"))
FEEDBACK = DBC.get_message_by_name("Feedback")
EXAMPLES = ROOT / "examples" / "controllers"


def _feedback(node: int, displacement: float, force: float, seq: int = 0) -> can.Message:
    data = FEEDBACK.encode(
        {"Seq": seq, "Status": 0x01, "Displacement": displacement, "Force": force}
    )
    return can.Message(arbitration_id=FEEDBACK.frame_id + node, data=data, is_extended_id=False)


@contextmanager
def _two_nodes(channel: str) -> Iterator[tuple[CANDriver, CANDriver, can.BusABC]]:
    """Nodes 0 and 1 open on one virtual bus, and the controller's end of it."""
    a = CANDriver(channel=channel, node=0)
    b = CANDriver(channel=channel, node=1)
    controller = can.Bus(interface="virtual", channel=channel)
    a.open()
    b.open()
    try:
        yield a, b, controller
    finally:
        controller.shutdown()
        a.close()
        b.close()


def test_a_second_driver_for_a_node_is_refused_until_the_first_closes() -> None:
    a = CANDriver(channel="shared-bus-1", node=3)
    b = CANDriver(channel="shared-bus-1", node=3)
    a.open()
    try:
        with pytest.raises(InputError) as err:
            b.open()
        assert str(err.value) == "CAN driver: node 3 is already open on channel 'shared-bus-1'"
        other = CANDriver(channel="shared-bus-1", node=4)  # another node shares the bus
        other.open()
        other.close()
    finally:
        a.close()
    b.open()
    b.close()


def test_a_frame_for_another_node_reaches_that_node() -> None:
    with _two_nodes("shared-bus-2") as (a, b, controller):
        a.send(0, 0.0, enable=True)
        b.send(0, 0.0, enable=True)
        controller.send(_feedback(1, 0.0025, -300.5))  # node 1's, read first by node 0
        controller.send(_feedback(0, -0.001, 42.0))
        fa = a.receive(1.0)
        fb = b.receive(1.0)
        assert fa is not None and fb is not None
        assert (fa.displacement, fa.force) == (pytest.approx(-0.001, abs=1e-7), 42.0)
        assert (fb.displacement, fb.force) == (pytest.approx(0.0025, abs=1e-7), -300.5)
        assert a.stats.malformed == 0 and b.stats.malformed == 0


def test_a_frame_for_no_node_is_counted() -> None:
    a = CANDriver(channel="shared-bus-3", node=0)
    controller = can.Bus(interface="virtual", channel="shared-bus-3")
    a.open()
    try:
        a.send(0, 0.0, enable=True)
        controller.send(_feedback(5, 0.0, 0.0))
        assert a.receive(0.05) is None
        assert a.stats.malformed_reasons == {"unknown_id": 1}
    finally:
        controller.shutdown()
        a.close()


def test_the_profile_driver_refuses_a_profile_of_another_protocol() -> None:
    with pytest.raises(InputError) as err:
        CANProfileDriver(str(EXAMPLES / "modbus_map.toml"))
    assert str(err.value) == (
        f"can driver: profile {EXAMPLES / 'modbus_map.toml'} is not a CAN profile"
    )


def test_a_node_read_late_leaves_the_other_nodes_replies_to_them() -> None:
    """A receive that returns far past its deadline (``rths_hil.drivers.base.DEADLINE_SLACK``,
    here a stalled machine) is counted. Were node 0 then read through a reader thread (the
    fallback of a driver that may block), that thread would take node 1's replies off the
    shared bus into node 1's inbox while node 1 waits on the bus, and node 1 would miss them
    (33 of these 40 did): every reply to node 1 must reach it."""
    with _two_nodes("shared-bus-5") as (a, b, controller):
        a._overran(0.06)  # node 0's receive came back 60 ms late (the driver's fallback)
        a.send(0, 0.0, enable=True)
        assert a.receive(0.001) is None  # node 0 receives as the loop does (its thread, if any)
        missed = 0
        for seq in range(1, 41):
            b.send(seq, 0.0, enable=True)
            # the controller answers 2 ms later, while node 1 waits on the bus
            reply = threading.Timer(0.002, controller.send, [_feedback(1, 0.0, 0.0, seq=seq)])
            reply.start()
            fb = b.receive(0.1)
            reply.join()
            if fb is None or fb.seq != seq:
                missed += 1
            a.receive(0.0)  # node 0 keeps receiving (its reader thread, if it has one, stays)
        assert missed == 0
        assert b.stats.timeouts == 0
        assert a.stats.deadline_overruns == 1  # counted all the same

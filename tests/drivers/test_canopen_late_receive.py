"""Two CiA 402 axes on one bus, one of whose receives came back far past its deadline
(``rths_hil.drivers.base.DEADLINE_SLACK``: a stalled machine). The late receive is counted;
were that axis then read through a reader thread (the fallback of a driver that may block),
the thread would pump the other axis's TPDOs off the bus while that axis waits on the bus, and
its replies would be missed (its hand-back went unconfirmed)."""

from __future__ import annotations

import logging
from pathlib import Path

from rths_hil.drivers.canopen import CANopenDriver

from rths_hil.config import load_config
from rths_hil.hybrid import RTHSLoop

ROOT = Path(__file__).resolve().parents[2]
TWO_AXES = ROOT / "examples" / "controllers" / "cia402_two_axes.toml"


def test_an_axis_read_late_leaves_the_other_axis_its_replies(tmp_path, monkeypatch, caplog):
    opened = CANopenDriver.open

    def open_late(self: CANopenDriver) -> None:
        opened(self)
        if self.node_id == 1:
            self._overran(0.06)  # node 1's receive came back 60 ms late

    monkeypatch.setattr(CANopenDriver, "open", open_late)
    cfg = load_config(
        TWO_AXES, ["loop.console=0", "output.plot=false", "compensation.enabled=false"]
    )
    loop = RTHSLoop(cfg, tmp_path / "two", mode="lockstep", duration=1.0)
    with caplog.at_level(logging.WARNING):
        res = loop.run()
    assert res.status == "completed" and res.missed_replies == 0
    a, b = (ch.driver for ch in loop.channels)
    assert (a.node_id, a.stats.deadline_overruns) == (1, 1)
    assert a.stats.timeouts == b.stats.timeouts == 0
    unconfirmed = [r.getMessage() for r in caplog.records if "did not confirm" in r.getMessage()]
    assert unconfirmed == []
    assert "not scheduled in time" in caplog.text

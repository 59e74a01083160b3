"""One step's exchange with the controllers: send the commands, collect the replies within a
budget, hold what is missing.

Every paced or lockstep exchange with controllers goes through a :class:`StepIO`: the loop's
step (:class:`~.step.Step`), the start and end phases (:class:`~.phases.Phases`) and
commissioning (:class:`rths_hil.commission.controller.Controller`); the OpenSees site's
actuators are the loop's channels, so its exchange is the loop's. A :class:`StepIO` holds one
``(send, receive)`` pair per controller (a driver's, or a channel's with its
:class:`~.phases.Link`) and the :class:`~.pacer.ReplyBudget`; what a caller does with a reply or
its absence (a channel's state and reply gaps, the safety checks, a round trip) stays the
caller's. The deadline before the sends is the :class:`~.pacer.Pacer`'s.

The exchange allocates nothing per step: the replies, their clocks and the last reply of each
controller are kept in lists made once (``docs/loop.md``, "Step order").

The controller status bits the callers judge replies by (enabled, latched) are here too.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from rths_hil.drivers.base import Feedback, Status

from .pacer import ReplyBudget

__all__ = ["ENABLED", "ESTOP", "FAULT", "LATCHED", "WATCHDOG", "StepIO"]

ENABLED = int(Status.ENABLED)
ESTOP = int(Status.ESTOP_ACTIVE)
FAULT = int(Status.FAULT)
WATCHDOG = int(Status.WATCHDOG)
#: A latch the arming command (or ``enable = False``) acknowledges: e-stop, fault, watchdog.
LATCHED = ESTOP | FAULT | WATCHDOG

Send = Callable[[int, float, bool], None]
Receive = Callable[[float], "Feedback | None"]


class StepIO:
    """Send a step's commands, collect its replies within the budget, hold what is missing.

    Parameters
    ----------
    links : sequence of (send, receive)
        One pair per controller: ``send(seq, command, enable)`` and ``receive(timeout)``
        (feedback or ``None``).
    budget : ReplyBudget
        How long the replies are waited for.
    shared : bool, optional
        Whether the replies share one limit from the send (:meth:`ReplyBudget.limit`): each
        waits only what is left of it. Otherwise each waits the full ``budget.timeout``.
        Default: shared with several controllers or the automatic wait.

    Attributes
    ----------
    replies : list of Feedback or None
        The last :meth:`collect`'s replies (``None``: missed).
    clocks : list of float
        When each of them came, or its wait ended (``time.perf_counter`` s).
    """

    __slots__ = ("budget", "clocks", "links", "receivers", "replies", "shared")

    def __init__(
        self,
        links: Sequence[tuple[Send, Receive]],
        budget: ReplyBudget,
        shared: bool | None = None,
    ) -> None:
        self.links = list(links)
        self.receivers = [receive for _, receive in self.links]
        n = len(self.links)
        self.budget = budget
        self.shared = bool(n > 1 or budget.auto) if shared is None else bool(shared)
        self.replies: list[Feedback | None] = [None] * n
        self.clocks = [0.0] * n

    def send(self, seq: int, commands: Sequence[float], enable: bool = True) -> None:
        """Send command ``commands[j]`` with sequence ``seq`` to every controller ``j``."""
        for (send, _), c in zip(self.links, commands, strict=True):
            send(seq, c, enable)

    def collect(self, now: float, deadline: float = 0.0) -> list[Feedback | None]:
        """Every controller's reply to the commands sent at ``now`` for ``deadline``.

        Shared, the replies must come by :meth:`ReplyBudget.limit` (``now`` + timeout, or
        earlier with the automatic wait); otherwise each gets ``budget.timeout``. Fills
        :attr:`replies` (``None``: missed, the caller holds what it had) and :attr:`clocks`;
        returns :attr:`replies`.
        """
        perf = time.perf_counter
        replies, clocks = self.replies, self.clocks
        if self.shared:
            t_lim = self.budget.limit(now, deadline)
            for j, receive in enumerate(self.receivers):
                rem = t_lim - perf()
                fb = receive(rem if rem > 0.0 else 0.0)
                clocks[j] = perf()
                replies[j] = fb
        else:
            timeout = self.budget.timeout
            for j, receive in enumerate(self.receivers):
                fb = receive(timeout)
                clocks[j] = perf()
                replies[j] = fb
        return replies

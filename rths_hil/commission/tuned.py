"""The tuned fragment (``tuned.toml``): each channel's identified plant as configuration."""

from __future__ import annotations

import logging
import math
from typing import Any

from .report import ChannelReport

log = logging.getLogger(__name__)

__all__ = ["GAP_MARGIN", "WATCHDOG_SHARE", "tuned_fragment"]

#: ``safety.watchdog_timeout`` of the tuned fragment: this share of the controller's own
#: watchdog when it is known …
WATCHDOG_SHARE = 0.75
#: … else this × the longest reply gap measured (at least the key's default).
GAP_MARGIN = 2.0


def _watchdog_timeout(rep: ChannelReport, fs: float) -> tuple[float, str]:
    """The fragment's ``safety.watchdog_timeout`` for a channel and how it was chosen.

    The controller's own watchdog known: :data:`WATCHDOG_SHARE` of it — the bridge bears the
    controller's and the link's pauses (a driver's give-up on a dropped request included) up
    to shortly before the controller would latch by itself. Unknown: :data:`GAP_MARGIN` × the
    longest reply gap, never tighter than the key's default (a latency window of a few
    seconds does not see every pause of a controller's network stack nor every stall of this
    computer). At least three periods.
    """
    from ..config import SCHEMA

    gap = rep.reply_gap if math.isfinite(rep.reply_gap) else 0.0
    lower = max(GAP_MARGIN * gap, 3.0 / fs)
    wd = rep.controller_watchdog
    if wd:
        value = WATCHDOG_SHARE * wd
        how = f"{WATCHDOG_SHARE:g} × the controller's watchdog ({wd:g} s)"
        if lower > value:
            how += (
                f"; the longest reply gap ({gap * 1e3:.2f} ms) × {GAP_MARGIN:g} is longer: "
                "the link's pauses come close to the controller's watchdog"
            )
            log.warning("%s: %s", rep.name or "actuator", how)
        return round(value, 4), how
    floor = float(SCHEMA["safety"]["watchdog_timeout"].default)
    value = max(lower, floor)
    how = (
        f"{GAP_MARGIN:g} × the longest reply gap ({gap * 1e3:.2f} ms), at least the default "
        f"{floor * 1e3:g} ms and 3 periods (the controller's watchdog unknown)"
    )
    return round(value, 4), how


def tuned_fragment(reports: list[ChannelReport], plan: Any) -> str:
    """The configuration fragment of the identified plants (``tuned.toml``; module docstring).

    One ``[compensation]`` and ``[safety]`` table for a configuration without
    ``[[actuators]]``, else one ``[[actuators]]`` entry per channel (merged by name into the
    including file's, ``docs/config.md``).
    """
    import tomli_w

    def tables(rep: ChannelReport) -> tuple[dict[str, Any], dict[str, Any]]:
        p = rep.plant
        assert p is not None
        comp = {
            "method": "model",
            "delay": round(p.delay, 6),
            "model_delay": -1.0,
            "model_time_constant": round(p.lag, 6),
            "model_gain": round(p.gain, 5),
            "amplitude": 1.0,
        }
        wd, _ = _watchdog_timeout(rep, plan.fs)
        return comp, {"watchdog_timeout": wd}

    head = [
        "# Written by rths-hil commission: the plant of each channel as the loop sees it",
        f"# ({plan.cfg.source or 'the default configuration'}, {plan.fs:g} Hz). Include it with",
        '#   include = ["<this directory>/tuned.toml"]',
        "# in the test's configuration (its own keys win over these).",
    ]
    for rep in reports:
        p = rep.plant
        assert p is not None
        _, how = _watchdog_timeout(rep, plan.fs)
        head.append(
            f"# {rep.name or 'actuator'}: delay {p.delay * 1e3:.2f} ms, lag {p.lag * 1e3:.2f} ms, "
            f"gain {p.gain:.4f} (fit {p.fit:.1%}); watchdog_timeout = {how}"
        )
    if len(reports) == 1 and not plan.cfg.get("actuators"):
        comp, safety = tables(reports[0])
        doc: dict[str, Any] = {"compensation": comp, "safety": safety}
    else:
        entries = []
        for rep in reports:
            comp, safety = tables(rep)
            entries.append({"name": rep.name, "compensation": comp, "safety": safety})
        doc = {"actuators": entries}
    return "\n".join(head) + "\n\n" + tomli_w.dumps(doc)

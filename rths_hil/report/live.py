"""The live console line: :class:`LiveLine` formats the status the loop hands over every
``loop.console`` seconds (step rate, p99 lateness, online A and d, peak displacement, margin to
the nearest limit). The loop computes the numbers off the step path (every 0.5 s by default);
formatting and printing happen here."""

from __future__ import annotations

import math
import sys
from typing import IO, Any

__all__ = ["LiveLine", "format_live"]


def _number(v: Any) -> float | None:
    """A finite number from a summary or event field, else ``None``.

    Events keep a non-finite float by name (``"nan"``, :func:`~rths_hil.formats.json_safe`).
    """
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    return float(v) if math.isfinite(v) else None


def _fmt(v: float | None, scale: float = 1.0, spec: str = ".3f", signed: bool = False) -> str:
    if v is None or not math.isfinite(v):
        return "—"
    return format(v * scale, ("+" if signed else "") + spec)


def format_live(s: dict[str, Any]) -> str:
    """One console line from the loop's status dict.

    Displacements in mm. ``margin`` is the share of the nearest safety limit still unused
    (``displacement limit 77 % left``: the peak so far is 23 % of ``safety.max_displacement``).
    The progress percentage is left out when the run has no planned end (``open_ended``: an
    OpenSees site runs until the client ends; ``n`` is then only the cap), α when compensation
    is off (``compensation`` False), the missed replies (``missed``) while there are none.
    """
    name, frac = s.get("margin", ("none", math.inf))
    if s.get("channel"):  # several channels: the one nearest a limit
        name = f"{s['channel']} {name}"
    margin = "no limits" if not math.isfinite(frac) else f"{name} limit {frac * 100:.0f} % left"
    lat = f"p99 late {s['p99_lateness'] * 1e3:.3f} ms" if s.get("mode") == "paced" else "lockstep"
    prog = "" if s.get("open_ended") else f" ({100.0 * s['k'] / s['n']:3.0f} %)"
    alpha = f" | α {s['alpha']:.2f}" if s.get("compensation", True) else " | compensation off"
    # missed replies (held measurements, not a fault) once there are any
    missed = f" | missed {s['missed']}" if s.get("missed") else ""
    # the stability indicator beside the FEI, once it has a valid window
    stab = _number(s.get("stability"))
    stab_text = f" S {stab:.2f}" if stab is not None else ""
    return (
        f"t {s['t']:7.2f} s{prog} | {s['rate']:7.0f} steps/s | {lat}"
        f" | overruns {s['overruns']}{missed}"
        f" | {('[' + s['channel'] + '] ') if s.get('channel') else ''}"
        f"A {_fmt(s['amplitude'], spec='.4f')}"
        f" d {_fmt(s['delay'], 1e3, '.2f', True)} ms{stab_text}"
        f" | peak {s['peak_displacement'] * 1e3:.2f} mm"
        f" | margin: {margin}{alpha}"
    )


class LiveLine:
    """A callable for :class:`rths_hil.hybrid.RTHSLoop` ``live=``: prints the status line.

    On a terminal the line is rewritten in place (carriage return); otherwise (logs, CI) every
    ``every``-th status is printed on its own line.
    """

    def __init__(self, stream: IO[str] | None = None, every: int = 10) -> None:
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every = max(1, int(every))
        self._n = 0
        self._width = 0

    def __call__(self, status: dict[str, Any]) -> None:
        line = format_live(status)
        if self.tty:
            pad = max(0, self._width - len(line))
            self.stream.write("\r" + line + " " * pad)
            self._width = len(line)
        elif self._n % self.every == 0:
            self.stream.write(line + "\n")
        self._n += 1
        self.stream.flush()

    def finish(self) -> None:
        """End the in-place line."""
        if self.tty and self._width:
            self.stream.write("\n")
            self.stream.flush()
            self._width = 0

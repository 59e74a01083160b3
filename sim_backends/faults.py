"""Fault injection for twins: what a real bus and a real controller can do to the bridge.

A :class:`Faults` plan is given to a twin endpoint (:mod:`rths_hil.sim_backends.endpoints`); the
endpoint applies it to the command it receives and to the feedback it sends. Faults are keyed by the
command sequence number ``k`` so that tests are deterministic; optional probabilities (seeded) add
random frame faults for soak runs.

Frame faults (applied to the feedback frame(s) of step ``k``)
    ``drop`` (never sent), ``delay`` (sent after a pause; the endpoint does nothing else
    meanwhile, as a stalled controller), ``corrupt`` (one bit flipped after the checksum was
    computed, so the receiver must detect it), ``duplicate`` (sent twice), and ``drop_command``
    (the command of step ``k`` is lost: the plant is not stepped and nothing is sent back).
Measurement faults (applied to the values of step ``k`` and later)
    ``stuck_from`` (the measured displacement freezes at its last value), ``runaway_from`` (the
    measured displacement ramps away at ``runaway_rate`` m/s on top of the plant's response,
    whatever the command), ``nan`` (the displacement of those steps is NaN, status
    ``SENSOR_INVALID``).
Link faults
    ``disconnect_from``: from step ``k`` on the endpoint goes away (closes its socket or
    pseudo-terminal, or falls silent on a CAN bus).
Controller faults
    ``estop_ignored=1``: the e-stop command does not latch (a broken e-stop chain; what
    ``rths-hil commission`` must catch).

A plan can be written as text for ``rths-hil twin serve --faults``, e.g.
``"drop=5,9; delay=12:0.02; corrupt=20; stuck_from=100; p_drop=0.01; seed=3"``.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field, fields

from rths_hil.errors import InputError

__all__ = ["Faults"]

_SET_FIELDS = ("drop", "drop_command", "corrupt", "duplicate", "nan")
_INT_FIELDS = ("stuck_from", "runaway_from", "disconnect_from", "seed", "estop_ignored")
_FLOAT_FIELDS = ("runaway_rate", "p_drop", "p_corrupt", "p_duplicate")


@dataclass
class Faults:
    """A deterministic (plus optional seeded random) fault plan keyed by command sequence number.

    Attributes
    ----------
    drop, drop_command, corrupt, duplicate, nan : set of int
        Steps whose feedback is dropped / whose command is lost / whose feedback has one bit
        flipped / whose feedback is sent twice / whose measured displacement is NaN.
    delay : dict of int to float
        Steps whose feedback is held back by the given number of seconds.
    stuck_from, runaway_from, disconnect_from : int or None
        First step of a stuck sensor / a runaway / a disconnection.
    runaway_rate : float
        Runaway speed (m/s).
    p_drop, p_corrupt, p_duplicate : float
        Probability per step of each frame fault, drawn from ``random.Random(seed)``.
    seed : int
        Seed of the random frame faults.
    estop_ignored : int
        1: the controller does not latch an e-stop (a broken e-stop chain, for commissioning
        tests); 0 (default): it latches.
    """

    drop: set[int] = field(default_factory=set)
    drop_command: set[int] = field(default_factory=set)
    delay: dict[int, float] = field(default_factory=dict)
    corrupt: set[int] = field(default_factory=set)
    duplicate: set[int] = field(default_factory=set)
    nan: set[int] = field(default_factory=set)
    stuck_from: int | None = None
    runaway_from: int | None = None
    runaway_rate: float = 0.05
    disconnect_from: int | None = None
    p_drop: float = 0.0
    p_corrupt: float = 0.0
    p_duplicate: float = 0.0
    seed: int = 0
    estop_ignored: int = 0

    def __post_init__(self) -> None:
        for name in _SET_FIELDS:
            setattr(self, name, {int(k) for k in getattr(self, name)})
        self.delay = {int(k): float(v) for k, v in dict(self.delay).items()}
        for name in ("p_drop", "p_corrupt", "p_duplicate"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise InputError(f"fault {name}={p}: a probability must be within [0, 1]")
        if any(v < 0 or not math.isfinite(v) for v in self.delay.values()):
            raise InputError("fault delay: pauses must be finite and >= 0 s")
        if not math.isfinite(self.runaway_rate):
            raise InputError(
                f"fault runaway_rate={self.runaway_rate}: must be a finite speed (m/s)"
            )
        if self.estop_ignored not in (0, 1):
            raise InputError(
                f"fault estop_ignored={self.estop_ignored}: must be 0 (the controller latches "
                "an e-stop) or 1 (it does not)"
            )
        self._rng = random.Random(self.seed)
        self._stuck_value: float | None = None

    # -- text form ------------------------------------------------------------------------------
    @classmethod
    def parse(cls, text: str) -> Faults:
        """Read a plan such as ``"drop=5,9; delay=12:0.02; stuck_from=100; p_drop=0.01"``.

        Raises
        ------
        InputError
            Unknown fault name or unreadable value (the message names it).
        """
        kwargs: dict[str, object] = {}
        known = {f.name for f in fields(cls)}
        for raw in text.replace("\n", ";").split(";"):
            item = raw.strip()
            if not item:
                continue
            name, sep, value = (s.strip() for s in item.partition("="))
            if not sep or name not in known:
                raise InputError(
                    f"fault plan item {item!r}: expected NAME=VALUE with NAME one of "
                    f"{', '.join(sorted(known))}"
                )
            try:
                if name in _SET_FIELDS:
                    kwargs[name] = {int(v) for v in value.split(",") if v.strip()}
                elif name == "delay":
                    pairs = (p.split(":") for p in value.split(",") if p.strip())
                    kwargs[name] = {int(k): float(v) for k, v in pairs}
                elif name in _INT_FIELDS:
                    kwargs[name] = int(value)
                else:
                    kwargs[name] = float(value)
            except ValueError as exc:
                raise InputError(
                    f"fault plan item {item!r}: cannot read the value ({exc})"
                ) from None
        return cls(**kwargs)  # type: ignore[arg-type]

    def rearm(self) -> None:
        """Back to the start of the plan (a new run on the same twin): same random draws."""
        self._rng = random.Random(self.seed)
        self._stuck_value = None

    # -- used by the endpoints ------------------------------------------------------------------
    def command_lost(self, seq: int) -> bool:
        """True if the command of step ``seq`` never reaches the controller."""
        return seq in self.drop_command

    def disconnected(self, seq: int) -> bool:
        """True if the link is gone at step ``seq``."""
        return self.disconnect_from is not None and seq >= self.disconnect_from

    def measure(
        self, seq: int, displacement: float, force: float, dt: float
    ) -> tuple[float, float, bool]:
        """Apply the measurement faults of step ``seq``; return (disp, force, invalid)."""
        if self.runaway_from is not None and seq >= self.runaway_from:
            displacement += self.runaway_rate * dt * (seq - self.runaway_from + 1)
        if self.stuck_from is not None and seq >= self.stuck_from:
            if self._stuck_value is None:
                self._stuck_value = displacement
            displacement = self._stuck_value
        elif self.stuck_from is not None:
            self._stuck_value = displacement  # last good value before the sensor sticks
        if seq in self.nan:
            return math.nan, force, True
        return displacement, force, False

    def reply_plan(self, seq: int) -> tuple[int, float, bool]:
        """How to send the feedback of step ``seq``: (copies, pause in s, corrupt)."""
        rng = self._rng
        copies = 1
        if seq in self.drop or (self.p_drop and rng.random() < self.p_drop):
            copies = 0
        elif seq in self.duplicate or (self.p_duplicate and rng.random() < self.p_duplicate):
            copies = 2
        corrupt = seq in self.corrupt or bool(self.p_corrupt and rng.random() < self.p_corrupt)
        return copies, self.delay.get(seq, 0.0), corrupt

    @staticmethod
    def flip_bit(frame: bytes, index: int, bit: int = 0) -> bytes:
        """Return ``frame`` with bit ``bit`` of byte ``index`` flipped (a line error)."""
        b = bytearray(frame)
        b[index] ^= 1 << bit
        return bytes(b)

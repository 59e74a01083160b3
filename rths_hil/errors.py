"""Exception types shared by the package and mapped to exit codes by the CLI.

* :class:`InputError` — bad input (configuration, record file, frame, CLI argument). The CLI
  prints its message as one line and exits with code 2.
* :class:`SafetyTrip` — a safety rule tripped and the e-stop was sent. Exit code 3.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input. The message must say what is wrong and where (file, row, key path)."""


class SafetyTrip(RuntimeError):
    """A safety rule tripped during a run; carries the rule name and its reason."""

    def __init__(self, rule: str, reason: str) -> None:
        super().__init__(f"{rule}: {reason}")
        self.rule = rule
        self.reason = reason

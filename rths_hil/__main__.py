"""``python -m rths_hil`` is the same as ``rths-hil``."""

from .cli import entry

entry()

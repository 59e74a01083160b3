"""``python -m rths_hil`` is the same as ``rths-hil``."""

from ._entry import entry

entry()

"""Names of the record's columns.

A record of one actuator names its per-channel columns plainly (``target``, ``measured`` …); a
record of several actuators suffixes each per-channel column with ``_<channel name>``
(``target_left``, ``measured_left`` …). :func:`column_name` is that rule, in one place, for the
writers (the plan, the recorder) and the readers (report, studies, live view).
"""

from __future__ import annotations

__all__ = ["channel_suffix", "column_name"]


def channel_suffix(channel: str | None) -> str:
    """Suffix of a channel's columns: ``""`` for the only channel, else ``_<name>``.

    Examples
    --------
    >>> channel_suffix("left"), channel_suffix(None)
    ('_left', '')
    """
    return f"_{channel}" if channel else ""


def column_name(base: str, channel: str | None = None) -> str:
    """Column of ``base`` for ``channel`` (``None`` or ``""`` for a single-channel record).

    Examples
    --------
    >>> column_name("measured", "left"), column_name("measured")
    ('measured_left', 'measured')
    """
    return base + channel_suffix(channel)

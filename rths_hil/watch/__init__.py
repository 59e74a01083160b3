"""``rths-hil watch``: the operator's live view of a run in the browser.

A separate process follows the run directory's crash-safe record (:mod:`.source`) and serves a
Bokeh page (:mod:`.app`, :mod:`.server`); the loop does not know it is watched. See
``docs/watch.md``.
"""

from .source import RunFollower, RunState, find_channels, find_writer

__all__ = ["RunFollower", "RunState", "find_channels", "find_writer"]

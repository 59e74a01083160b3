"""Operator output of a run: the live console line, the end-of-run summary, the PNG report.

* :mod:`~rths_hil.report.live`: :class:`LiveLine` formats the status the loop hands over every
  ``loop.console`` seconds.
* :mod:`~rths_hil.report.summary`: :func:`summarize` reads a run directory back and computes the
  whole-record FEI, the tracking metrics, online-estimate statistics, lateness and the e-stop
  outcome (``summary.json``); :func:`format_summary` renders it for the console.
* :mod:`~rths_hil.report.figure`: :func:`plot_report` draws ``report.png`` (the FEI paper's
  Fig. 5.1 and 5.2 style).
"""

from .figure import plot_report
from .live import LiveLine, format_live
from .summary import exact_fei_points, format_summary, summarize

__all__ = [
    "LiveLine",
    "exact_fei_points",
    "format_live",
    "format_summary",
    "plot_report",
    "summarize",
]

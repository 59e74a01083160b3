"""The Python API: configure a test from a dict or a file, run it, read its record back.

What ``rths-hil run`` does, from a notebook or a script (``docs/api.md``)::

    import rths_hil

    cfg = rths_hil.configure(compensation={"alpha": 20}, loop={"fs": 1024})
    result = rths_hil.run(cfg, mode="lockstep", duration="10 s", run_dir="runs/nb-1")
    run = rths_hil.open_run(result.run_dir)
    run.record["measured"]          # numpy structured array, SI units
    df = run.to_dataframe()         # pandas DataFrame indexed by time
    s = run.summary()               # whole-record FEI, J1–J3, TI, e-stop, lateness

Configuration values go through the same schema as a TOML file or ``--set``: unknown keys,
wrong types, units and ranges raise :class:`rths_hil.errors.InputError` with the same one-line
message the command line prints (exit code 2 there).
"""

from __future__ import annotations

import copy
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .config import (
    Config,
    apply_overrides,
    default_config,
    load_config,
    merge,
    toml_value,
)
from .errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    from .hybrid.result import RunResult
    from .records.recorder import RunData

log = logging.getLogger(__name__)

__all__ = ["Run", "configure", "open_run", "run"]

Overrides = Mapping[str, Any] | Iterable[str] | None


def _override_items(overrides: Overrides, sections: Mapping[str, Any]) -> list[str]:
    """``section.key=value`` items (the ``--set`` form) from overrides of any form.

    A dict of dotted keys, strings, and ``section={key: value}`` keyword arguments, in that order.
    """
    items: list[str] = []
    if overrides is None:
        pass
    elif isinstance(overrides, str):
        items.append(overrides)
    elif isinstance(overrides, Mapping):
        for k, v in overrides.items():
            if not isinstance(k, str):
                raise InputError(
                    f"overrides: key {k!r} is of type {type(k).__name__}; expected a dotted "
                    "key such as 'compensation.alpha'"
                )
            items.append(_item(k, v))
    elif not isinstance(overrides, Iterable):
        raise InputError(
            f"overrides: expected a dict of dotted keys or a list of 'section.key=value' "
            f"strings, got {type(overrides).__name__} {overrides!r}"
        )
    else:
        for o in overrides:
            if not isinstance(o, str):
                raise InputError(f"override {o!r}: expected 'section.key=value' or a dict")
            items.append(o)
    for section, table in sections.items():
        if not isinstance(table, Mapping):
            raise InputError(
                f"{section}={table!r}: a section is a dict of keys, e.g. {section}={{'key': value}}"
            )
        items += [_item(f"{section}.{k}", v) for k, v in table.items()]
    return items


def _item(key: str, value: Any) -> str:
    """One ``key=value`` item with the value written as TOML (what ``--set`` reads)."""
    if hasattr(value, "item") and not isinstance(value, str | bytes):  # numpy scalars
        value = value.item()
    if isinstance(value, Path):
        value = str(value)
    try:
        return f"{key}={toml_value(value)}"
    except TypeError:
        raise InputError(f"{key}: {value!r} is not a configuration value") from None


def configure(
    config: str | Path | Mapping[str, Any] | Config | None = None,
    overrides: Overrides = None,
    **sections: Mapping[str, Any],
) -> Config:
    """A validated configuration, as ``rths-hil run [CONFIG] --set …`` would build it.

    Parameters
    ----------
    config : str, Path, dict or Config, optional
        A TOML file; a dict shaped like one (``{"loop": {"fs": 2048}, "actuators": [...]}``);
        a :class:`~rths_hil.config.Config` (copied); ``None`` for the embedded default (the
        FEI paper's NEES-711 setup over the CAN twin).
    overrides : dict or list of str, optional
        Dotted keys and values applied over ``config``: ``{"compensation.alpha": 20,
        "safety.displacement_limit": "40 mm"}``, or ``--set`` strings
        (``["compensation.alpha=20"]``).
    **sections : dict
        Per-section overrides, applied last: ``compensation={"alpha": 20, "enabled": True}``.

    Returns
    -------
    Config

    Raises
    ------
    InputError
        Unknown key, wrong type, unit or range, unreadable file: one line naming the key.
    """
    items = _override_items(overrides, sections)
    if config is None or isinstance(config, str | Path):
        base = load_config(config)
    elif isinstance(config, Config):
        base = copy.deepcopy(config)
    elif isinstance(config, Mapping):
        for k in config:
            if not isinstance(k, str):
                raise InputError(
                    f"config: key {k!r} is of type {type(k).__name__}; a configuration dict has "
                    "section names as keys ({'loop': {'fs': 1024}, ...})"
                )
        base = default_config()
        base.base_dir = Path.cwd()
        base.source = "<dict>"
        merge(base, dict(config), "<dict>")
    else:
        raise InputError(
            f"config: expected a TOML path, a dict or a Config, got {type(config).__name__}"
        )
    return apply_overrides(base, items, "rths_hil.configure")


def run(
    config: str | Path | Mapping[str, Any] | Config | None = None,
    overrides: Overrides = None,
    *,
    run_dir: str | Path | None = None,
    mode: str | None = None,
    duration: float | str | None = None,
    plant: Any = None,
    live: Any = None,
    summary: bool = True,
    report: bool = False,
    **sections: Mapping[str, Any],
) -> RunResult:
    """Configure (:func:`configure`) and run one test; return its :class:`RunResult`.

    Parameters
    ----------
    config, overrides, **sections
        As :func:`configure`.
    run_dir : str or Path, optional
        Run directory (default: a new one under ``output.dir``). It must not hold a run.
    mode : {"lockstep", "paced"}, optional
        Overrides ``loop.mode`` (lockstep: virtual time, deterministic; paced: wall clock).
    duration : float or str, optional
        Simulated seconds (``10``, ``"10 s"``, ``"500ms"``; 0 = the whole record).
    plant, live
        As :class:`rths_hil.hybrid.RTHSLoop` (a twin plant for what-ifs; a status callback).
    summary, report : bool
        Write ``summary.json`` (default) and ``report.png`` (off by default) as the command
        line does.

    Returns
    -------
    RunResult
        ``status`` (completed, trip, operator_stop), ``steps``, ``trip``, ``run_dir`` …; a
        safety trip is a result, not an exception.
    """
    from .hybrid import RTHSLoop
    from .units import parse_time

    cfg = configure(config, overrides, **sections)
    if run_dir is not None and not isinstance(run_dir, str | os.PathLike):
        raise InputError(f"run_dir: expected a path (str or Path), got {type(run_dir).__name__}")
    if isinstance(duration, str):
        duration = parse_time(duration, "duration")
    elif duration is not None and (
        isinstance(duration, bool) or not isinstance(duration, int | float)
    ):
        raise InputError(
            f"duration: expected seconds as a number or a string such as '10 s', got "
            f"{type(duration).__name__} {duration!r}"
        )
    if mode is not None and mode not in ("lockstep", "paced"):
        raise InputError(f"mode: expected 'lockstep' or 'paced', got {mode!r}")
    result = RTHSLoop(cfg, run_dir, plant=plant, live=live, mode=mode, duration=duration).run()
    if summary or report:
        from .report import plot_report, summarize

        s = summarize(result.run_dir)
        if report and result.steps > 1:
            plot_report(result.run_dir, summary=s)
    return result


class Run:
    """A run directory read back: the record, the events, the metadata, the summary.

    Attributes
    ----------
    record : numpy.ndarray
        Structured array, one row per step, SI units (``record["measured"]`` in m,
        ``record["force"]`` in N, ``record["fei_delay"]`` in s); ``record.dtype.names`` lists
        the columns (``docs/records.md``).
    events : list of dict
        The event log (start, trips, e-stop, end …).
    meta : dict
        ``meta.json``: configuration, mode, rate, channels, column units.
    path : Path
        The run directory.
    """

    def __init__(self, data: RunData) -> None:
        self._data = data
        self.record = data.record
        self.events = data.events
        self.meta = data.meta
        self.path = data.path

    @property
    def fs(self) -> float:
        """Loop rate (Hz)."""
        return self._data.fs

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r}, {len(self.record)} rows at {self.fs:g} Hz)"

    def to_dataframe(self):
        """The record as a :class:`pandas.DataFrame` indexed by ``time`` (s), SI units.

        Needs pandas (``pip install pandas``; not a dependency of rths_hil itself).
        """
        try:
            import pandas as pd
        except ImportError:
            raise InputError("Run.to_dataframe needs pandas: pip install pandas") from None
        df = pd.DataFrame({name: self.record[name] for name in self.record.dtype.names})
        return df.set_index("time")

    def summary(self) -> dict[str, Any]:
        """The run's summary (:func:`rths_hil.report.summarize`; also writes summary.json).

        Raises
        ------
        InputError
            The run has no ``meta.json`` (its mode, driver, planned length and e-stop outcome
            are unknown: a summary would hold ``None`` for them).
        """
        from .records.recorder import META_FILE
        from .report import summarize

        if not self.meta:
            raise InputError(
                f"{self.path / META_FILE}: missing or empty: the run's mode, driver and planned "
                "length are unknown, so it cannot be summarised (the record is still readable)"
            )

        return summarize(self.path)

    def summary_text(self) -> str:
        """The summary as the console prints it."""
        from .report import format_summary

        return format_summary(self.summary())

    def plot(self, path: str | Path | None = None):
        """The report figure (:func:`rths_hil.report.plot_report`).

        Returned for a notebook, or saved to ``path`` (then its path is returned).
        """
        from .report import plot_report

        if path is None:
            return plot_report(self.path, keep_figure=True)
        return plot_report(self.path, path)


def open_run(run_dir: str | Path) -> Run:
    """Read a run directory (also of a tripped or crashed run): :class:`Run`.

    Raises
    ------
    InputError
        ``run_dir`` is not a path, or not a readable run directory (one line).
    """
    from .records.recorder import read_run

    if not isinstance(run_dir, str | os.PathLike):
        raise InputError(f"run_dir: expected a path (str or Path), got {type(run_dir).__name__}")
    return Run(read_run(run_dir))

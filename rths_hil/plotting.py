"""Figures shared by the CLI commands (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .errors import InputError
from .fei import MovingFEIResult


def save_figure(fig, path: str | Path, dpi: int) -> Path:
    """Write ``fig`` to ``path`` (format from the suffix, PNG without one) and close it, or raise.

    The figure is rendered into memory first and written with one checked write and close, so
    a full disk (``/dev/full``), a read-only directory or a name too long is an
    :class:`~rths_hil.errors.InputError` naming the file, never a figure silently lost. The
    figure is closed (its memory released) either way.
    """
    import matplotlib.pyplot as plt

    out = Path(path)
    fmt = out.suffix.lstrip(".").lower() or "png"
    buf = io.BytesIO()
    try:
        fig.savefig(buf, dpi=dpi, format=fmt)
    except ValueError as exc:  # an unknown format
        raise InputError(f"{out}: cannot write a figure: {exc}") from None
    finally:
        plt.close(fig)
    try:
        with open(out, "wb") as fh:
            fh.write(buf.getvalue())
    except OSError as exc:
        raise InputError(f"{out}: cannot write the figure: {exc.strerror or exc}") from None
    return out


def shade_invalid(
    ax, t: np.ndarray, valid: np.ndarray, label: str | None = "invalid window"
) -> None:
    """Shade the spans of ``t`` where ``valid`` is False on axis ``ax``."""
    if t.size == 0:
        return
    bad = ~np.asarray(valid, dtype=bool)
    if not bad.any():
        return
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(int), [0]])))
    for k, (a, b) in enumerate(zip(edges[::2], edges[1::2], strict=True)):
        ax.axvspan(t[a], t[min(b, t.size - 1)], color="0.85", lw=0, label=label if k == 0 else None)


def plot_moving_fei(
    time: np.ndarray,
    target: np.ndarray,
    measured: np.ndarray,
    result: MovingFEIResult,
    path: str | Path,
    title: str = "",
    amplitude_band: tuple[float, float] | None = None,
    delay_band: tuple[float, float] | None = None,
) -> Path:
    """The FEI paper's Fig. 5.1/5.2-style figure: target/measured overlay, A(t) and d(t) of the
    windows.

    Parameters
    ----------
    time, target, measured : ndarray
        The record (s, m, m).
    result : MovingFEIResult
        Moving-window FEI of the record; ``t_end`` on the record's time axis.
    path : str or Path
        PNG to write.
    title : str
        Figure title.
    amplitude_band, delay_band : (float, float), optional
        Tolerance bands to draw (A limits; d limits in s).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True, constrained_layout=True)
    ax = axes[0]
    ax.plot(time, 1e3 * target, lw=1.0, label="target")
    ax.plot(time, 1e3 * measured, lw=0.8, label="measured")
    ax.set_ylabel("displacement (mm)")
    ax.legend(loc="upper right")
    t = result.t_end + (time[0] if time.size else 0.0)
    for ax, values, label, band, scale in (
        (axes[1], result.amplitude, "A", amplitude_band, 1.0),
        (axes[2], result.delay, "d (ms)", delay_band, 1e3),
    ):
        shade_invalid(ax, t, result.valid)
        ax.plot(t, scale * values, lw=1.0, color="C2")
        if band is not None:
            for b in band:
                ax.axhline(scale * b, color="C3", ls="--", lw=0.8)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[1].axhline(1.0, color="0.4", lw=0.6)
    axes[2].axhline(0.0, color="0.4", lw=0.6)
    axes[2].set_xlabel("time (s)")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, 110)

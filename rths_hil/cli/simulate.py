"""``rths-hil simulate``: the FEI paper's Fig. 4.1 simulation, written as a record CSV.

An SDOF structure (linear or Bouc-Wen, CR integration) under a ground motion gives the target
displacement; the actuator block model (fractional transport delay + gain,
:class:`rths_hil.sim_backends.delay.DelayGain`) gives the measured one. The record CSV has the
columns ``time,target,measured,ground_accel,force`` (s, m, m, m/s², N) and is what ``rths-hil
evaluate`` reads. See ``docs/simulation.md``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..units import positive_number
from .options import (
    add_command,
    add_ground_motion_argument,
    add_simulation_arguments,
    simulation_from_args,
)

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` sub-command."""
    p = add_command(
        sub,
        "simulate",
        __doc__,
        run,
        help="simulate an SDOF + delay/gain actuator under a ground motion (FEI paper, Fig. 4.1)",
    )
    add_ground_motion_argument(p, "bundled El Centro 1940", several=False)
    p.add_argument("--fn", required=True, help="natural frequency of the structure (Hz)")
    p.add_argument(
        "--bouc-wen",
        action="store_true",
        help="Bouc-Wen restoring force (the FEI paper's Eq. 4.1-4.2: x_y 10 mm, k_a 11.765 kN/mm, "
        "eta 0, beta 0.55, gamma 0.45, q 2)",
    )
    add_simulation_arguments(p, gain="1", delay="0")
    p.add_argument("--method", choices=("cr", "newmark"), default="cr", help="integrator")
    p.add_argument("--out", required=True, help="record CSV to write")
    p.add_argument(
        "--plot",
        nargs="?",
        const="",
        default=None,
        metavar="PNG",
        help="also plot the histories (default file: OUT with .png)",
    )


def run(args: argparse.Namespace) -> int:
    """Run the simulation and write the record; returns the exit code."""
    from rths_hil.sim_backends.delay import DelayGain

    from ..groundmotion import default_record, resolve
    from ..records.csvfiles import write_record
    from ..structures.sdof import SDOFResponse, simulate_sdof

    zeta, gain, delay, fs, pga = simulation_from_args(args)
    fn = positive_number(args.fn, "--fn (natural frequency, Hz)")
    if fn >= fs / 2:
        raise InputError(f"--fn {fn:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz")
    gm = default_record() if args.record is None else resolve(args.record)
    from ..resources import check_memory

    # the resampled record, the SDOF response and the delay's complex spectra: ~64 bytes a sample
    check_memory(64 * gm.duration * fs, f"--fs {fs:g} Hz over the record's {gm.duration:g} s")
    gm = gm.resampled(fs)
    if pga is not None:  # after resampling, so that the simulated PGA is exactly this
        gm = gm.scaled(pga)
    if delay * fs >= gm.npts:
        raise InputError(f"--delay {args.delay} is longer than the record ({gm.duration:g} s)")

    resp = simulate_sdof(
        gm.accel,
        fs,
        fn,
        zeta,
        bouc_wen=True if args.bouc_wen else None,
        method=args.method,
        full=True,
    )
    assert isinstance(resp, SDOFResponse)  # full=True
    measured = DelayGain(delay=delay, gain=gain, dt=1.0 / fs).simulate(resp.x)
    out = Path(args.out)
    if not out.parent.is_dir():
        raise InputError(f"--out: directory {str(out.parent)!r} does not exist")
    try:
        write_record(
            out,
            {
                "time": gm.time,
                "target": resp.x,
                "measured": measured,
                "ground_accel": gm.accel,
                "force": resp.force,
            },
            fmt="%.12g",
        )
    except OSError as exc:
        raise InputError(f"--out: cannot write {str(out)!r} ({exc.strerror})") from None
    structure = "Bouc-Wen" if args.bouc_wen else "linear"
    print(
        f"wrote {out}: {gm.npts} samples at {fs:g} Hz ({gm.duration:.2f} s), {structure} SDOF "
        f"fn = {fn:g} Hz, zeta = {zeta:g}, record {gm.name} PGA {gm.pga:.4g} m/s², "
        f"peak target {1e3 * float(np.max(np.abs(resp.x))):.3f} mm, gain {gain:g}, "
        f"delay {1e3 * delay:g} ms"
    )
    if args.plot is not None:
        png = Path(args.plot) if args.plot else out.with_suffix(".png")
        _plot(png, gm.time, resp.x, measured, gm.accel, resp.force, title=f"{gm.name}, {structure}")
        print(f"wrote {png}")
    return 0


def _plot(path: Path, t, target, measured, ag, force, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    axes[0].plot(t, ag, lw=0.6, color="0.3")
    axes[0].set_ylabel("ground accel (m/s²)")
    axes[1].plot(t, 1e3 * target, lw=0.8, label="target")
    axes[1].plot(t, 1e3 * measured, lw=0.8, ls="--", label="measured")
    axes[1].set_ylabel("displacement (mm)")
    axes[1].legend(fontsize=8)
    axes[2].plot(t, 1e-3 * force, lw=0.8)
    axes[2].set_ylabel("restoring force (kN)")
    axes[2].set_xlabel("time (s)")
    axes[0].set_title(title)
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    from ..plotting import save_figure

    save_figure(fig, path, 110)

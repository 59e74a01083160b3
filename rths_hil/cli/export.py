"""``rths-hil export RUN_DIR [--csv] [--hdf5] [--mat] [--out DIR] [--columns A,B]``: convert a
record.

Writes ``record.csv`` (the record CSV format read by ``rths-hil evaluate``; columns named as in
the run's ``record.npy``), ``record.h5`` (the ``hdf5`` extra: h5py) and/or ``record.mat``
(MATLAB, :func:`scipy.io.savemat`). ``--csv`` is the default. Works on runs that crashed or
tripped: every flushed row is exported.
"""

from __future__ import annotations

import argparse

from .options import add_command


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``export`` to the top-level parser."""
    p = add_command(
        sub,
        "export",
        __doc__,
        main,
        help="export a run directory's record to CSV / HDF5 / MATLAB",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="run directory written by rths-hil run")
    p.add_argument("--csv", action="store_true", help="write record.csv (default)")
    p.add_argument(
        "--hdf5", action="store_true", help="write record.h5 (pip install 'rths-hil[hdf5]')"
    )
    p.add_argument("--mat", action="store_true", help="write record.mat (MATLAB, v5)")
    p.add_argument("--out", metavar="DIR", help="output directory (default: RUN_DIR)")
    p.add_argument(
        "--columns",
        metavar="A,B,...",
        help="export only these columns (time is always first), e.g. target,command,measured",
    )


def main(args: argparse.Namespace) -> int:
    """Export; print the files written."""
    from ..errors import InputError
    from ..records.recorder import export_run

    csv = args.csv or not (args.hdf5 or args.mat)
    cols = None
    if args.columns is not None:
        cols = [c.strip() for c in args.columns.split(",") if c.strip()]
        if not cols:
            raise InputError(
                f"--columns {args.columns!r}: no column name in it (e.g. target,command,measured)"
            )
    for path in export_run(
        args.run_dir, csv=csv, hdf5=args.hdf5, out_dir=args.out, columns=cols, mat=args.mat
    ):
        print(path)
    return 0

"""Exception types shared by the package and mapped to exit codes by the CLI.

* :class:`InputError` — bad input (configuration, record file, frame, CLI argument). The CLI
  prints its message as one line and exits with code 2.

:func:`require` checks that an optional dependency (an *extra* of the package: ``hdf5``,
``studies``, ``live``, ``opensees``) is installed, and otherwise raises an :class:`InputError`
whose one line names the extra to install.
"""

from __future__ import annotations

import importlib.util

#: The optional features: extra name → (import name, what it brings).
EXTRAS: dict[str, tuple[str, str]] = {
    "hdf5": ("h5py", "HDF5 export"),
    "studies": ("distributed", "Dask studies and sweeps"),
    "live": ("bokeh", "the live view in the browser"),
    "opensees": ("openseespy", "OpenSeesPy models (the examples' OpenSees client)"),
}


class InputError(ValueError):
    """Bad user input. The message must say what is wrong and where (file, row, key path)."""


def require(extra: str, what: str) -> None:
    """Raise :class:`InputError` naming ``pip install 'rths-hil[extra]'`` when it is missing.

    The module of the extra ``extra`` (:data:`EXTRAS`) cannot be imported; ``what`` is the
    feature asked for (``"rths-hil watch"``). Only looks the module up (no import: start-up
    stays fast).
    """
    module = EXTRAS[extra][0]
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        raise InputError(
            f"{what} needs {module}, which is not installed: pip install 'rths-hil[{extra}]'"
        )


def check_regular_file(path, what: str, max_bytes: int | None = None) -> None:
    """Refuse a ``path`` that is not a regular file (before anything reads it).

    A FIFO blocks its reader until a writer comes, ``/dev/zero`` never ends: read as a
    configuration or a record either hangs for ever or fills the memory. ``max_bytes`` bounds
    the size of a file read whole into memory. A missing file is left to the reader (its own
    message names it).

    Raises
    ------
    InputError
        Not a regular file, or larger than ``max_bytes``, naming ``path`` and ``what``.
    """
    import os
    import stat

    try:
        st = os.stat(path)
    except OSError:
        return
    if not stat.S_ISREG(st.st_mode):
        kind = (
            "a FIFO"
            if stat.S_ISFIFO(st.st_mode)
            else "a device"
            if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
            else "a directory"
            if stat.S_ISDIR(st.st_mode)
            else "not a regular file"
        )
        raise InputError(f"{path}: {what} must be a regular file, this is {kind}")
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputError(
            f"{path}: {what} of {st.st_size} bytes is larger than the {max_bytes} bytes accepted"
        )

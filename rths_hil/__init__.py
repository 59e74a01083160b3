"""rths_hil — hardware-in-the-loop bridge for real-time hybrid simulation (RTHS).

The core package: the frequency-domain evaluation index (FEI) and its moving windows
(:mod:`rths_hil.fei`), tracking metrics (:mod:`rths_hil.metrics`), the numerical substructure
(:mod:`rths_hil.structures.sdof`, MDOF in :mod:`rths_hil.structures.mdof`,
:mod:`rths_hil.groundmotion`),
the link budget of each bus (:mod:`rths_hil.linkbudget`), compensation, Kalman delay/gain
estimation (:mod:`rths_hil.estimation`), the real-time loop, safety rules
(:mod:`rths_hil.safety`), crash-safe records, studies, the discrepancy workflow and the
``rths-hil`` command line (:mod:`rths_hil.cli`), and the Python API of the same
(:func:`configure`, :func:`run`, :func:`open_run`; :mod:`rths_hil.api`, ``docs/api.md``).

Data flows one way through a step::

    ground motion -> structure -> compensator -> driver <-> twin/hardware
        -> evaluators (FEI, Kalman) -> safety -> recorder
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["InputError", "__version__", "configure", "open_run", "run"]

# the Python API (rths_hil.api, docs/api.md), imported on first use: ``import rths_hil``
# stays light for the command line
_API = {"configure", "open_run", "run", "Run"}


def __getattr__(name: str):
    if name in _API:
        from . import api

        return getattr(api, name)
    if name == "InputError":
        from .errors import InputError

        return InputError
    raise AttributeError(f"module 'rths_hil' has no attribute {name!r}")

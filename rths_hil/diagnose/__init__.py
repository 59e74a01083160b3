"""Discrepancy diagnosis: where a twin and a measurement disagree and which effect is missing.

``rths-hil diagnose RECORD.csv [--model twin.toml] --out DIR`` (see ``docs/diagnose.md``):

* :func:`diagnose` — the loop: simulate, localise, fit every candidate of
  :data:`CANDIDATES`, name the most significant by BIC, add it, repeat;
* :func:`localise` — when / at which frequencies / in which regime the residual leaves its
  noise band;
* :func:`write_outputs` — ``report.json``, the augmented model file and the PNG;
* :mod:`rths_hil.diagnose.synthetic` — records with hidden effects (tests, confusion study).
"""

from .candidates import CANDIDATES, REFITS, simulate_model
from .localise import Localisation, localise, noise_level
from .output import plot_diagnosis, summary_lines, write_outputs
from .workflow import (
    DEFAULT_THRESHOLD,
    DEFAULT_TIE_MARGIN,
    MIN_CYCLES,
    MIN_DURATION_S,
    Diagnosis,
    Gap,
    Step,
    check_record,
    diagnose,
)

__all__ = [
    "CANDIDATES",
    "DEFAULT_THRESHOLD",
    "DEFAULT_TIE_MARGIN",
    "MIN_CYCLES",
    "MIN_DURATION_S",
    "REFITS",
    "Diagnosis",
    "Gap",
    "Localisation",
    "Step",
    "check_record",
    "diagnose",
    "localise",
    "noise_level",
    "plot_diagnosis",
    "simulate_model",
    "summary_lines",
    "write_outputs",
]

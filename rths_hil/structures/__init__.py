"""Numerical substructures: what the structure does between one measured force and the next target.

* :mod:`rths_hil.structures.sdof` — SDOF frames (linear or Bouc-Wen) and the CR integrator;
* :mod:`rths_hil.structures.mdof` — MDOF models (shear buildings, given matrices) and their
  CR stepper;
* :mod:`rths_hil.structures.stages` — the structure as the runner sees it (SDOF, MDOF, OpenSees).
"""

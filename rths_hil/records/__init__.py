"""Records: what a run writes and what the tools read back.

* :mod:`rths_hil.records.recorder` — the crash-safe run directory (``record.npy``, events,
  metadata);
* :mod:`rths_hil.records.columns` — the record's columns, defined once (name, dtype, unit, source);
* :mod:`rths_hil.records.run` — the run's recorder with its metadata, and one row per step;
* :mod:`rths_hil.records.csvfiles` — record CSV files (``simulate`` writes, ``evaluate`` reads).
"""

"""Helpers the tests share, imported as ``tests.helpers.<module>``.

* :mod:`.loop` — run a test configuration through the loop and read its run directory back
  (also the ``run_loop`` fixture of ``tests/conftest.py``);
* :mod:`.procs` — the twin and the bridge as their own processes;
* :mod:`.twin_signals` — SDOF responses to the bundled ground motions;
* :mod:`.watch_records` — run directories written for the live view;
* :mod:`.opensees_site` — the OpenSees example model against the bridge;
* :mod:`.cli` — the bad-input contract (exit 2, one line);
* :mod:`.records` — deterministic record rows;
* :mod:`.openfresco` — an OpenFresco client speaking to the bridge's site;
* :mod:`.fei_refs` — brute-force FEI references.
"""

"""Helpers the tests share, imported as ``tests.helpers.<module>``.

* :mod:`.loop` — run a test configuration through the loop and read its run directory back
  (also the ``run_loop`` fixture of ``tests/conftest.py``);
* :mod:`.procs` — the twin and the bridge as their own processes;
* :mod:`.twin_signals` — SDOF responses to the bundled ground motions;
* :mod:`.watch_records` — run directories written for the live view;
* :mod:`.opensees_site` — the OpenSees example model against the bridge.
"""

"""The virtual-CAN twin served from the loop thread (``twin.inline``) is the same twin.

Lockstep is deterministic, so the record of a run with the twin in its own thread and the record
with the twin served inline must be identical, column by column, e-stop included.
"""

from __future__ import annotations

import numpy as np
import pytest
from rths_hil.sim_backends.twin import default_plant, start_twin

from rths_hil.errors import InputError
from tests.helpers.loop import run_loop

COLUMNS = ("target", "command", "measured", "force", "fei_amplitude", "fei_delay", "kf_delay")


def _run(tmp_path, name, inline, *extra):
    inline_set = f"twin.inline={'true' if inline else 'false'}"
    r = run_loop(tmp_path / name, None, "loop.mode=lockstep", "loop.duration=4", inline_set, *extra)
    return r.loop, r.result, r.run


@pytest.mark.parametrize("extra", [(), ("safety.displacement_limit=0.004",)])
def test_inline_and_threaded_twin_give_the_same_record(tmp_path, extra):
    loop_i, res_i, run_i = _run(tmp_path, "inline", True, *extra)
    loop_t, res_t, run_t = _run(tmp_path, "thread", False, *extra)
    assert loop_i.twin.inline and not loop_t.twin.inline
    assert res_i.status == res_t.status
    assert len(run_i.record) == len(run_t.record) > 1000
    for col in COLUMNS:
        np.testing.assert_array_equal(run_i.record[col], run_t.record[col], err_msg=col)
    if extra:  # the limit trips: both twins latched the e-stop
        assert res_i.status == "trip"
        assert loop_i.twin.controller.stats.estops == loop_t.twin.controller.stats.estops == 1


def test_inline_needs_an_in_process_transport():
    with pytest.raises(InputError, match="inline"):
        start_twin("modbus", default_plant(), threaded=False)

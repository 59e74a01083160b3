"""A delay given as a bare number is seconds: one above 1 s (``compensation.delay = "25"``, an
α of 25 601 at 1024 Hz) is refused with the unit named, not compensated."""

from __future__ import annotations

import pytest

from rths_hil.config import load_config
from rths_hil.errors import InputError


@pytest.mark.parametrize("key", ["delay", "delay_min", "delay_max", "model_delay"])
@pytest.mark.parametrize("value", ["25", '"25"', '"1.5"'])
def test_a_bare_number_above_one_second_names_the_unit(key, value):
    with pytest.raises(InputError) as err:
        load_config(None, [f"compensation.{key}={value}"])
    msg = str(err.value)
    assert f"compensation.{key}: must be ≤ 1 s" in msg
    assert "a bare number is in seconds" in msg and "ms" in msg and "\n" not in msg


def test_with_its_unit_the_same_number_is_what_it_says():
    cfg = load_config(None, ['compensation.delay="25 ms"'])
    assert cfg["compensation"]["delay"] == pytest.approx(0.025)
    with pytest.raises(InputError) as err:  # 2 s said in seconds: out of range, no hint
        load_config(None, ['compensation.delay="2 s"'])
    assert "must be ≤ 1 s, got 2" in str(err.value)
    assert "bare number" not in str(err.value)
    # alpha is the other way to give the delay: 1 + delay·fs
    cfg = load_config(None, ["compensation.alpha=26.6"])
    assert cfg["compensation"]["delay"] == pytest.approx(25.6 / 1024)

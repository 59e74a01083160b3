"""check_table: the one validator of configuration sections, profile tables and model files."""

from __future__ import annotations

import pytest

from rths_hil.config import REQUIRED, Key, check_table
from rths_hil.errors import InputError

KEYS = {
    "delay": Key("float", 0.0, unit="s", lo=0),
    "address": Key("int", REQUIRED, lo=0, hi=65535),
    "order": Key("choice", "big", choices=("big", "little")),
    "note": Key("str", None),
}


def test_values_are_coerced_to_si_and_defaults_filled() -> None:
    out = check_table({"address": 7, "delay": "12 ms"}, KEYS, "lab.toml", "roles.setpoint")
    assert out == {"address": 7, "delay": pytest.approx(0.012), "order": "big", "note": None}
    assert list(out)[:2] == ["address", "delay"]  # the table's order first


def test_without_defaults_only_the_keys_given() -> None:
    assert check_table({"address": 3}, KEYS, defaults=False) == {"address": 3}


@pytest.mark.parametrize(
    ("table", "message"),
    [
        (
            {"address": 1, "adress": 2},
            "lab.toml: roles.x.adress: unknown key (did you mean 'address'?); known keys: "
            "delay, address, order, note",
        ),
        ({}, "lab.toml: roles.x.address: missing"),
        ({"address": 70000}, "lab.toml: roles.x.address: must be ≤ 65535, got 70000"),
        ({"address": 1, "delay": "-2 ms"}, "lab.toml: roles.x.delay: must be ≥ 0 s, got -0.002"),
        ({"address": True}, "lab.toml: roles.x.address: expected an integer, got true"),
        (
            {"address": 1, "order": "middle"},
            "lab.toml: roles.x.order: must be one of big, little, got 'middle'",
        ),
        ([1, 2], "lab.toml: roles.x: expected a table, got an array"),
    ],
)
def test_bad_tables_are_refused_in_one_line(table, message) -> None:
    with pytest.raises(InputError) as exc:
        check_table(table, KEYS, "lab.toml", "roles.x")
    assert str(exc.value) == message


def test_a_missing_key_says_why_and_a_top_level_key_has_no_dot() -> None:
    with pytest.raises(InputError, match=r"^m\.toml: address: required by model 'x'$"):
        check_table({}, KEYS, "m.toml", missing="required by model 'x'")
    with pytest.raises(InputError, match=r"^adress: unknown key \(did you mean 'address'\?\)"):
        check_table({"adress": 1}, KEYS)

"""The shared readers and writers (rths_hil.formats) and the one positive-number check."""

from __future__ import annotations

import json
import math
import os
import tomllib

import numpy as np
import pytest
from rths_hil.sim_backends.modelfile import dump_model, load_model

from rths_hil.errors import InputError
from rths_hil.formats import json_safe, json_text, read_toml, toml_key, toml_value
from rths_hil.units import positive_number

ODD = 'quote " back \\ tab \t newline \n bell \x07 µ é'


@pytest.mark.parametrize(
    "value",
    [
        0.1,
        np.float64(0.1),
        np.float32(0.5),
        np.int64(4),
        np.bool_(True),
        1e-300,
        -0.0,
        3,
        ODD,
        [np.float64(1.5), 2, "a"],
        {"plain": 1, "with space": np.float32(2.0), "é": ODD},
    ],
)
def test_toml_value_reads_back_unchanged(value) -> None:
    back = tomllib.loads(f"v = {toml_value(value)}")["v"]
    expected = value.item() if isinstance(value, np.generic) else value
    if isinstance(value, list):
        expected = [x.item() if isinstance(x, np.generic) else x for x in value]
    if isinstance(value, dict):
        expected = {k: (x.item() if isinstance(x, np.generic) else x) for k, x in value.items()}
    assert back == expected
    assert type(back) is type(expected)


@pytest.mark.parametrize("value", [math.nan, np.float64("nan"), math.inf, -math.inf])
def test_toml_nonfinite_floats_are_written_as_toml_nan_and_inf(value) -> None:
    text = toml_value(value)
    assert text in ("nan", "inf", "-inf")
    back = tomllib.loads(f"v = {text}")["v"]
    assert (math.isnan(back) and math.isnan(value)) or back == value


def test_toml_key_quotes_only_what_it_must() -> None:
    assert toml_key("time_constant") == "time_constant"
    assert tomllib.loads(f"{toml_key('a b.c')} = 1") == {"a b.c": 1}


def test_model_file_round_trip_with_numpy_parameters(tmp_path) -> None:
    spec = {
        "actuator": {
            "model": "servo_lag",
            "delay": np.float64(0.012),
            "gain": np.float64(0.5),
            "time_constant": np.float64(0.008),
        }
    }
    path = tmp_path / "twin.toml"
    dump_model(spec, path, header=ODD)
    back = load_model(path)
    assert back.actuator.delay == 0.012 and back.actuator.gain == 0.5
    assert back.actuator.params == {"time_constant": 0.008}


def test_read_toml_errors_are_one_line_naming_the_file(tmp_path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[loop\nfs = 1\n")
    with pytest.raises(InputError, match=r"^.*bad\.toml: invalid TOML \(TOML syntax error\)"):
        read_toml(bad, "config")
    latin = tmp_path / "latin.toml"
    latin.write_bytes(b"name = '\xe9'\n")
    with pytest.raises(InputError, match=r"latin\.toml: not a UTF-8 text file"):
        read_toml(latin, "model file")
    with pytest.raises(InputError, match="profile x: cannot read profile"):
        read_toml(tmp_path / "missing.toml", "profile", label="profile x")
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="FIFO"):
        read_toml(fifo, "config")  # refused before anything reads it (no hang)
    big = tmp_path / "big.toml"
    big.write_text("a = 1\n" * 100)
    with pytest.raises(InputError, match=r"big\.toml"):
        read_toml(big, "config", max_bytes=64)
    good = tmp_path / "good.toml"
    good.write_text("[loop]\nfs = 1024\n")
    assert read_toml(good, "config") == {"loop": {"fs": 1024}}


def test_json_safe_one_rule_per_kind_of_file() -> None:
    value = {
        "a": np.float64("nan"),
        "b": [math.inf, -math.inf, np.float32(0.25)],
        "c": np.arange(3, dtype=np.int64),
        "d": (np.bool_(False), 1),
        5: "key",
    }
    absent = json_safe(value)
    assert absent == {
        "a": None,
        "b": [None, None, 0.25],
        "c": [0, 1, 2],
        "d": [False, 1],
        "5": "key",
    }
    named = json_safe(value, "name")
    assert named["a"] == "nan" and named["b"][:2] == ["inf", "-inf"]
    text = json_text(value)
    assert text.endswith("\n") and json.loads(text) == absent  # strict JSON: no NaN token


@pytest.mark.parametrize(
    ("value", "allow_zero", "message"),
    [
        ("abc", False, "must be a number"),
        (None, False, "must be a number"),
        (math.nan, False, r"must be a finite number > 0"),
        (math.inf, False, r"must be a finite number > 0"),
        (0.0, False, r"must be a finite number > 0"),
        (-1.0, True, r"must be a finite number ≥ 0"),
    ],
)
def test_positive_number_refuses_with_one_line(value, allow_zero, message) -> None:
    with pytest.raises(InputError, match=f"x {message}"):
        positive_number(value, "x", allow_zero=allow_zero)


def test_positive_number_accepts() -> None:
    assert positive_number("2.5", "x") == 2.5
    assert positive_number(0, "x", allow_zero=True) == 0.0
    assert positive_number(np.float32(1.5), "x") == 1.5

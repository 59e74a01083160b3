"""Non-physical structures, NaN rows and configuration round trips."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.config import MASS_RANGE, STIFFNESS_RANGE, load_config, to_toml
from tests.helpers.cli import one_line_exit_2 as _one_line_exit_2

SHEAR = """
[structure]
kind = "shear_building"
masses = [{m}, 2.0e5]
stiffnesses = [{k}, 1.0e8]
[[actuators]]
name = "a"
dof = 1
"""


@pytest.mark.parametrize(
    "m, k, needle",
    [
        ("1e-300", "1.2e8", "structure.masses[0]: must be ≥ 0.001 kg, got 1e-300"),
        ("2.0e5", "1.2e300", "structure.stiffnesses[0]: must be ≤ 1e+12 N/m, got 1.2e+300"),
    ],
)
def test_non_physical_storey_is_refused_with_key_and_value(tmp_path, capsys, m, k, needle):
    cfg = tmp_path / "s.toml"
    cfg.write_text(SHEAR.format(m=m, k=k))
    _one_line_exit_2(
        ["run", str(cfg), "--lockstep", "--duration", "1", "-q", "--out", str(tmp_path / "r")],
        capsys,
        needle,
    )
    assert not (tmp_path / "r").exists()


def test_sdof_mass_bounds_via_set(capsys, tmp_path):
    out = str(tmp_path / "r")
    _one_line_exit_2(
        ["run", "--lockstep", "-q", "--out", out, "--set", "structure.mass=1e-300"],
        capsys,
        "structure.mass",
        "1e-300",
    )


def test_plausible_extremes_are_accepted():
    """The bounds refuse the absurd, not the unusual: a 1 g bench storey and a 1e12 N/m core."""
    lo_m, hi_m = MASS_RANGE
    lo_k, hi_k = STIFFNESS_RANGE
    cfg = load_config(
        None,
        [
            "structure.kind=shear_building",
            f"structure.masses=[{lo_m}, {hi_m}]",
            f"structure.stiffnesses=[{lo_k}, {hi_k}]",
        ],
    )
    assert cfg["structure"]["masses"] == [lo_m, hi_m]


def test_calibrate_on_a_record_with_a_nan_row(tmp_path, capsys):
    t = np.arange(3000) / 1024.0
    x = 0.01 * np.sin(2 * np.pi * t)
    rows = np.column_stack([t, x, x])
    path = tmp_path / "nan.csv"
    lines = ["time,command,measured"] + [f"{a:.10g},{b:.10g},{c:.10g}" for a, b, c in rows]
    lines[701] = "nan,nan,nan"
    path.write_text("\n".join(lines) + "\n")
    _one_line_exit_2(
        ["twin", "calibrate", str(path), "--out", str(tmp_path / "tw.toml")],
        capsys,
        f"{path}:702",  # file line 702: lines[0] is the header, line 1
        "non-finite",
    )
    assert not (tmp_path / "tw.toml").exists()


@pytest.mark.parametrize(
    "text",
    ["runs/a\nb", 'tab\tand "quotes" and \\ backslash', "bell\x07 and del\x7f", "ünï{timestamp}"],
)
def test_show_config_round_trips_any_string(tmp_path, capsys, text):
    cfg = load_config(None, [f"output.dir={text}"])
    written = to_toml(cfg.as_dict())
    assert tomllib.loads(written)["output"]["dir"] == text
    # through the CLI: the printed configuration loads back to the same configuration
    assert main(["run", "--show-config", "--set", f"output.dir={text}"]) == 0
    out = capsys.readouterr().out
    p = tmp_path / "shown.toml"
    p.write_text(out, encoding="utf-8")
    again = load_config(p)
    assert again["output"]["dir"] == text
    assert again.as_dict() == cfg.as_dict()


def test_show_config_round_trips_the_two_actuator_example():
    cfg = load_config("examples/two_actuators.toml")
    data = tomllib.loads(to_toml(cfg.as_dict()))
    assert [a["name"] for a in data["actuators"]] == ["storey1", "storey3"]
    assert data["actuators"][1]["transform"] == [0.0, -1.0, 1.0]

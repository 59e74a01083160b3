"""The Python API (``rths_hil.configure / run / open_run``, docs/api.md)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import rths_hil
from rths_hil.cli import main as cli
from rths_hil.config import load_config
from rths_hil.errors import InputError

ROOT = Path(__file__).resolve().parents[2]


def test_docs_api_example_runs_as_written(tmp_path, monkeypatch, capsys):
    """Every ```python cell of docs/api.md, in order, in one namespace (its asserts check
    the numbers it prints: the FEI delay against the closed form of the α left over)."""
    monkeypatch.chdir(tmp_path)
    text = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    cells = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(cells) == 4
    ns: dict = {}
    for i, cell in enumerate(cells):
        exec(compile(cell, f"docs/api.md cell {i + 1}", "exec"), ns)
    out = capsys.readouterr().out
    assert "rths_hil.configure: compensation.alpah: unknown key (did you mean 'alpha'?)" in out
    assert (ns["out"] / "report.png").stat().st_size > 10_000


def test_dict_overrides_equal_the_set_strings():
    strings = ["compensation.alpha=20", 'safety.displacement_limit="40 mm"', "loop.fs=2048"]
    ref = load_config(None, strings).as_dict()
    by_dotted = rths_hil.configure(
        None,
        {
            "compensation.alpha": np.float64(20),
            "safety.displacement_limit": "40 mm",
            "loop.fs": 2048,
        },
    )
    by_section = rths_hil.configure(
        compensation={"alpha": 20}, safety={"displacement_limit": 0.04}, loop={"fs": 2048}
    )
    # a dict is read like a file: its α at its own loop rate
    by_dict = rths_hil.configure(
        {"loop": {"fs": 2048}, "compensation": {"alpha": 20}},
        {"safety.displacement_limit": "4 cm"},
    )
    for cfg in (by_dotted, by_section, by_dict):
        assert cfg.as_dict() == ref
    assert rths_hil.configure(None, strings).as_dict() == ref


def test_a_config_passed_in_is_not_changed():
    base = rths_hil.configure()
    alpha = base["compensation"]["alpha"]
    out = rths_hil.configure(base, compensation={"alpha": alpha + 1})
    assert out["compensation"]["alpha"] == alpha + 1 and base["compensation"]["alpha"] == alpha


@pytest.mark.parametrize(
    ("args", "kwargs", "needle"),
    [
        ((None, {"compensation.alpah": 20}), {}, "compensation.alpah: unknown key"),
        ((None, {"loop.fs": "fast"}), {}, "loop.fs"),
        ((), {"compensation": 20}, "a section is a dict of keys"),
        ((), {"nope": {"a": 1}}, "nope"),
        (({"loop": {"fs": -5}},), {}, "<dict>: loop.fs"),
        ((None, {"loop.fs": object()}), {}, "is not a configuration value"),
        ((3.5,), {}, "expected a TOML path, a dict or a Config"),
        (("missing.toml",), {}, "missing.toml: cannot read config"),
        ((None, 42), {}, "overrides: expected a dict of dotted keys"),
        (({1: 2},), {}, "config: key 1 is of type int"),
        ((None, {1: 2}), {}, "overrides: key 1 is of type int"),
    ],
)
def test_bad_input_raises_input_error_with_one_line(args, kwargs, needle):
    with pytest.raises(InputError) as exc:
        rths_hil.configure(*args, **kwargs)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"run_dir": 123}, "run_dir: expected a path (str or Path), got int"),
        ({"duration": [1]}, "duration: expected seconds as a number or a string"),
        ({"duration": True}, "duration: expected seconds"),
        ({"mode": "fast"}, "mode: expected 'lockstep' or 'paced', got 'fast'"),
    ],
)
def test_run_arguments_are_checked_before_anything_starts(tmp_path, monkeypatch, kwargs, needle):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError) as exc:
        rths_hil.run(None, {"output.plot": False}, **{"mode": "lockstep", **kwargs})
    assert needle in str(exc.value) and "\n" not in str(exc.value)
    assert not (tmp_path / "runs").exists()  # no run directory was made


@pytest.mark.parametrize("bad", [123, None, 4.5])
def test_open_run_names_its_argument(bad):
    with pytest.raises(InputError, match=r"run_dir: expected a path \(str or Path\), got "):
        rths_hil.open_run(bad)


def test_api_run_equals_the_command_line_run(tmp_path):
    """The same test from the API (dict overrides, keyword arguments) and from
    ``rths-hil run --set``: identical records (lockstep is deterministic)."""
    sets = ["compensation.alpha=20", "loop.console=0", "output.plot=false"]
    args = ["run", "--lockstep", "--duration", "2", "-q", "--out", str(tmp_path / "cli")]
    assert cli([*args, *[x for s in sets for x in ("--set", s)]]) == 0
    res = rths_hil.run(
        compensation={"alpha": 20},
        loop={"console": 0},
        mode="lockstep",
        duration="2 s",
        run_dir=tmp_path / "api",
    )
    assert res.status == "completed" and res.steps == 2048
    a = rths_hil.open_run(tmp_path / "api")
    b = rths_hil.open_run(tmp_path / "cli")
    assert a.record.dtype == b.record.dtype
    for name in ("target", "command", "measured", "force", "fei_delay"):
        np.testing.assert_array_equal(a.record[name], b.record[name])
    assert (tmp_path / "api" / "summary.json").is_file()
    # the old entry point with --set strings still runs
    from rths_hil.hybrid import run as loop_run

    r = loop_run(None, ["compensation.alpha=20", "loop.console=0"], mode="lockstep",
                 duration=0.5, run_dir=tmp_path / "old")  # fmt: skip
    assert r.status == "completed" and r.steps == 512


def test_to_dataframe_is_the_record(tmp_path):
    res = rths_hil.run(loop={"console": 0}, mode="lockstep", duration=1, run_dir=tmp_path / "r")
    run = rths_hil.open_run(res.run_dir)
    df = run.to_dataframe()
    assert list(df.columns) == [n for n in run.record.dtype.names if n != "time"]
    np.testing.assert_array_equal(df.index.to_numpy(), run.record["time"])
    np.testing.assert_array_equal(df["measured"].to_numpy(), run.record["measured"])
    assert "1024 rows at 1024 Hz" in repr(run)

"""Configuration schema: defaults, units, overrides, errors with file and key path, docs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from rths_hil.config import (
    SCHEMA,
    default_config,
    load_config,
    parse_override,
    schema_markdown,
    to_toml,
)
from rths_hil.errors import InputError

# no test here runs against the wall clock or starts another process (the refusals go through
# the CLI in-process): they run with the parallel tests, not under the "timing" marker
ROOT = Path(__file__).resolve().parents[2]


def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "run.toml"
    p.write_text(text)
    return p


def test_embedded_default_is_the_nees711_setup():
    cfg = load_config()
    s = cfg["structure"]
    assert s["mass"] == 503400.0 and s["fn"] == 0.77 and s["damping"] == 0.02
    assert s["bouc_wen"] is True
    # the FEI paper's Eq. 4.1-4.2 parameters (Section 4): x_y = 10 mm, η = 0, β = 0.55, γ = 0.45,
    # q = 2
    assert (s["x_y"], s["eta"], s["beta"], s["gamma"], s["q"]) == (0.01, 0.0, 0.55, 0.45, 2.0)
    # k = m (2π fn)² is the FEI paper's k_a = 11.765 kN/mm within 0.2 %
    assert s["mass"] * (2 * math.pi * s["fn"]) ** 2 == pytest.approx(11.765e6, rel=2e-3)
    assert cfg["ground_motion"]["record"] == "default"
    assert cfg["ground_motion"]["pga"] == 0.322
    assert cfg["loop"]["fs"] == 1024.0 and cfg["loop"]["mode"] == "paced"
    assert cfg["driver"]["name"] == "can" and cfg["twin"]["enabled"] is True
    act = cfg["twin"]["actuator"]
    assert 0.02 <= act["time_constant"] + act["delay"] <= 0.05  # "a few tens of ms"
    assert cfg["compensation"]["enabled"] and cfg["fei"]["enabled"]
    # α matches the twin's lag: 1 + (T + delay)·fs
    assert cfg["compensation"]["alpha"] == pytest.approx(
        1 + (act["time_constant"] + act["delay"]) * 1024, abs=0.1
    )
    assert cfg.window_s == pytest.approx(3 / 0.77)


def test_file_values_with_units_are_converted_to_si(tmp_path):
    p = _write(
        tmp_path,
        """
        [loop]
        fs = "2kHz"
        duration = "1500ms"
        [safety]
        displacement_limit = "25mm"
        fei_delay_tol = "8ms"
        [ground_motion]
        pga = "0.05g"
        [structure]
        damping = "5%"
        [fei]
        window = "2.5T"
        """,
    )
    cfg = load_config(p)
    assert cfg["loop"]["fs"] == 2000.0 and cfg["loop"]["duration"] == pytest.approx(1.5)
    assert cfg["safety"]["displacement_limit"] == pytest.approx(0.025)
    assert cfg["safety"]["fei_delay_tol"] == pytest.approx(0.008)
    assert cfg["ground_motion"]["pga"] == pytest.approx(0.05 * 9.80665)
    assert cfg["structure"]["damping"] == pytest.approx(0.05)
    assert cfg.window_s == pytest.approx(2.5 / 0.77)
    assert cfg.source == str(p) and cfg.base_dir == tmp_path.resolve()


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        ("[loop]\nfss = 1\n", ["loop.fss", "unknown key", "did you mean 'fs'"]),
        ("[looop]\nfs = 1\n", ["looop", "unknown key"]),
        ("[loop]\nfs = true\n", ["loop.fs", "expected a number in Hz"]),
        ("[loop]\nfs = '1024ms'\n", ["loop.fs", "Hz"]),
        ("[loop]\nfs = 0.5\n", ["loop.fs", "≥ 1 Hz"]),
        ("[loop]\nmode = 'fast'\n", ["loop.mode", "paced, lockstep"]),
        ("[fei]\nexact_hop = 2.5\n", ["fei.exact_hop", "integer"]),
        ("[twin]\nenabled = 'yes'\n", ["twin.enabled", "true or false"]),
        ("[safety]\nfei_delay_tol = '5 parsecs'\n", ["safety.fei_delay_tol"]),
        ("[structure]\nfn = -1\n", ["structure.fn", "> 0"]),
        ("[structure]\nfn = 600\n", ["structure.fn", "Nyquist"]),
        ("[driver]\nconnection = 3\n", ["driver.connection", "table"]),
        ("loop = 3\n", ["loop", "table"]),
        ("[loop\nfs=1\n", ["TOML syntax error"]),
        ("[compensation]\nalpha = 0.5\n", ["compensation.alpha", "≥ 1"]),
        ("[output]\nflush_interval = 0.5\n", ["output.flush_interval", "0.1"]),
    ],
)
def test_errors_name_the_file_and_the_key_path(tmp_path, text, needles):
    p = _write(tmp_path, text)
    with pytest.raises(InputError) as err:
        load_config(p)
    msg = str(err.value)
    assert msg.startswith(str(p)) and "\n" not in msg
    for needle in needles:
        assert needle in msg


def test_missing_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="cannot read config"):
        load_config(tmp_path / "nope.toml")


def test_overrides_use_toml_semantics_with_string_fallback(tmp_path):
    p = _write(tmp_path, "[loop]\nfs = 2048\n")
    cfg = load_config(
        p,
        [
            "loop.fs=4096",
            "compensation.enabled=false",
            "driver.name=modbus",
            "safety.fei_delay_tol=10ms",
            "driver.connection={host = '127.0.0.1', port = 0}",
            "twin.actuator.delay=0.012",
            "kalman.options.q=1e-6",
        ],
    )
    assert cfg["loop"]["fs"] == 4096.0  # --set wins over the file
    assert cfg["compensation"]["enabled"] is False
    assert cfg["driver"]["name"] == "modbus"
    assert cfg["safety"]["fei_delay_tol"] == pytest.approx(0.010)
    assert cfg["driver"]["connection"] == {"host": "127.0.0.1", "port": 0}
    assert cfg["twin"]["actuator"]["delay"] == 0.012
    assert cfg["twin"]["actuator"]["model"] == "first_order"  # other keys kept
    assert cfg["kalman"]["options"] == {"q": 1e-6}
    # the defaults object is not modified by overrides
    assert default_config()["twin"]["actuator"]["delay"] == 0.005


@pytest.mark.parametrize(
    ("item", "needles"),
    [
        ("loop.fs", ["--set loop.fs", "section.key=value"]),
        ("fs=3", ["--set fs=3", "section.key=value"]),
        ("loop.fs=abc", ["--set loop.fs=abc", "loop.fs"]),
        ("loop.fz=1", ["--set loop.fz=1", "loop.fz", "did you mean 'fs'"]),
        ("loop.fs.x=1", ["loop.fs is not a table"]),
        ("compensation.enabled=1", ["compensation.enabled", "true or false"]),
    ],
)
def test_override_errors(item, needles):
    with pytest.raises(InputError) as err:
        load_config(None, [item])
    for needle in needles:
        assert needle in str(err.value)


def test_parse_override_values():
    assert parse_override("a.b=1") == (["a", "b"], 1)
    assert parse_override("a.b=1.5") == (["a", "b"], 1.5)
    assert parse_override("a.b=true") == (["a", "b"], True)
    assert parse_override('a.b="x y"') == (["a", "b"], "x y")
    assert parse_override("a.b=x y") == (["a", "b"], "x y")
    assert parse_override("a.b.c=[1, 2]") == (["a", "b", "c"], [1, 2])


def test_cross_key_checks():
    with pytest.raises(InputError, match="alpha_min"):
        load_config(None, ["compensation.alpha_min=50", "compensation.alpha_max=20"])
    with pytest.raises(InputError, match=r"fei\.window"):
        load_config(None, ["fei.window=0.001"])
    with pytest.raises(InputError, match="adaptive"):
        load_config(None, ["compensation.adaptive=true", "fei.enabled=false"])


def test_toml_rendering_round_trips(tmp_path):
    cfg = load_config(None, ["loop.fs=2048", "driver.connection={channel='x'}"])
    p = tmp_path / "rt.toml"
    p.write_text(to_toml(cfg))
    again = load_config(p)
    assert again.as_dict() == cfg.as_dict()


def test_every_default_passes_its_own_schema_as_an_override():
    text = to_toml(default_config(), comments=False)
    section, items = None, []
    for line in text.splitlines():
        if line.startswith("["):
            section = line.strip("[]")
        elif line.strip():
            name, value = line.split(" = ", 1)
            items.append(f"{section}.{name}={value}")
    assert len(items) == sum(len(keys) for keys in SCHEMA.values())
    for section, keys in SCHEMA.items():
        for name, key in keys.items():
            assert key.doc and key.unit, f"{section}.{name} lacks a description or unit"
    assert load_config(None, items).as_dict() == default_config().as_dict()


def test_docs_config_md_is_generated_from_the_schema():
    doc = (ROOT / "docs" / "config.md").read_text(encoding="utf-8")
    assert doc.strip() == schema_markdown().strip(), (
        "docs/config.md is out of date: regenerate with "
        "python -c 'from rths_hil.config import schema_markdown; print(schema_markdown())'"
    )


def test_example_configs_load():
    examples = sorted((ROOT / "examples").glob("*.toml"))
    names = {p.stem for p in examples}
    assert {"can", "modbus", "serial"} <= names
    for p in examples:
        cfg = load_config(p)
        assert cfg["driver"]["name"] in {"can", "modbus", "serial"}


def test_coercion_is_public_and_reads_units():
    from rths_hil.config import SCHEMA, coerce

    assert coerce(SCHEMA["loop"]["fs"], "2kHz", "loop.fs") == 2000.0
    assert coerce(SCHEMA["fei"]["window"], " 3T ", "fei.window") == "3T"
    assert coerce(SCHEMA["safety"]["fei_delay_tol"], "15ms", "safety.fei_delay_tol") == 0.015
    with pytest.raises(InputError, match=r"^loop\.fs: cannot read '2 kHz x'"):
        coerce(SCHEMA["loop"]["fs"], "2 kHz x", "loop.fs")
    with pytest.raises(InputError, match=r"^loop\.fs: expected a number in Hz, got true"):
        coerce(SCHEMA["loop"]["fs"], True, "loop.fs")


def test_fei_window_of_fewer_than_8_samples_one_rule_for_config_and_plan():
    from rths_hil.hybrid.plan import build_plan

    # structure.fn: 3 T = 3.9 s; at 2 Hz that is 7.8 samples
    with pytest.raises(InputError, match=r"fei\.window: '3T' is fewer than 8 samples at 2 Hz"):
        load_config(None, ["loop.fs=2", "structure.fn=0.77", "fei.window='3T'"])
    # a shear building's own first mode (√(1e7/1e3)/2π = 15.9 Hz) resolves "1T" in the plan:
    # 1/15.9 s at 64 Hz is 4 samples, while structure.fn (0.77 Hz) would give 83
    sets = [
        "structure.kind='shear_building'",
        "structure.masses=[1e3]",
        "structure.stiffnesses=[1e7]",
        "structure.bouc_wen=false",
        "loop.fs=64",
        "fei.window='1T'",
    ]
    cfg = load_config(None, sets)
    with pytest.raises(InputError, match=r"fei\.window: '1T' is fewer than 8 samples at 64 Hz"):
        build_plan(cfg, duration=0.5)


# ----------------------------------------------------------------------------------------------
# include


def test_include_merges_before_the_files_own_keys(tmp_path):
    (tmp_path / "frag").mkdir()
    (tmp_path / "frag" / "tuned.toml").write_text(
        'include = ["base.toml"]\n[compensation]\nmethod = "model"\ndelay = "12 ms"\n'
        "model_time_constant = 0.008\n[safety]\nwatchdog_timeout = 0.04\n"
    )
    # relative to the including file: frag/base.toml, merged before frag/tuned.toml's keys
    (tmp_path / "frag" / "base.toml").write_text("[compensation]\ndelay = 0.5\norder = 3\n")
    top = _write(tmp_path, 'include = ["frag/tuned.toml"]\n[safety]\nwatchdog_timeout = 0.03\n')
    cfg = load_config(top)
    c = cfg["compensation"]
    assert (c["method"], c["delay"], c["model_time_constant"], c["order"]) == (
        "model", pytest.approx(0.012), 0.008, 3,
    )  # fmt: skip
    assert c["alpha"] == pytest.approx(1 + 0.012 * cfg["loop"]["fs"])
    assert cfg["safety"]["watchdog_timeout"] == 0.03  # the file's own key wins
    # a --set still wins over both
    cfg = load_config(top, ["compensation.delay=0.02"])
    assert cfg["compensation"]["delay"] == pytest.approx(0.02)


def test_include_merges_channels_by_name(tmp_path):
    (tmp_path / "tuned.toml").write_text(
        '[[actuators]]\nname = "a1"\ncompensation = { method = "model", delay = 0.01 }\n'
        "safety = { watchdog_timeout = 0.05 }\n"
    )
    top = _write(
        tmp_path,
        'include = ["tuned.toml"]\n[structure]\nkind = "shear_building"\n'
        "masses = [2e5, 2e5]\nstiffnesses = [1e8, 1e8]\n"
        '[[actuators]]\nname = "a1"\ndof = 1\ncompensation = { amplitude = 1.01 }\n'
        '[[actuators]]\nname = "a2"\ndof = 2\n',
    )
    cfg = load_config(top)
    a1, a2 = cfg["actuators"]
    assert a1["compensation"] == {"method": "model", "delay": 0.01, "amplitude": 1.01}
    assert a1["safety"] == {"watchdog_timeout": 0.05} and a1["dof"] == 1
    assert "compensation" not in a2


@pytest.mark.parametrize(
    ("files", "top", "needle"),
    [
        ({"a.toml": 'include = ["run.toml"]\n'}, 'include = ["a.toml"]\n', "include cycle"),
        ({}, 'include = ["run.toml"]\n', "include cycle"),
        ({}, 'include = ["missing.toml"]\n', "no such file"),
        ({}, "include = [1]\n", "include: expected an array of file paths"),
        ({}, 'include = ["."]\n', "include '.'"),
        (
            {"t.toml": '[[actuators]]\nname = "zz"\n'},
            'include = ["t.toml"]\n[[actuators]]\nname = "a1"\n',
            "'zz'",
        ),
        ({"bad.toml": "[compensation]\ndelay = -1\n"}, 'include = ["bad.toml"]\n', "bad.toml"),
    ],
)
def test_include_refusals_are_one_line_naming_the_include(tmp_path, capsys, files, top, needle):
    from tests.helpers.cli import one_line_exit_2

    for name, text in files.items():
        (tmp_path / name).write_text(text)
    cfg = _write(tmp_path, top)
    err = one_line_exit_2(["run", str(cfg), "--lockstep", "--duration", "0.1"], capsys, needle)
    assert str(cfg) in err


def test_include_through_a_symlink_loop_is_refused(tmp_path):
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    top = _write(tmp_path, 'include = ["loop"]\n')
    with pytest.raises(InputError, match="include 'loop'"):
        load_config(top)

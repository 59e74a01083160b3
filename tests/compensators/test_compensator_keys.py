"""Each built-in compensator declares its own ``compensation.*`` keys (``KEYS``); the schema's
compensation section is the shared keys plus theirs, and docs/config.md lists them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rths_hil.compensators import BUILTIN, compensator_class
from rths_hil.config import SCHEMA, STEP_KEYS, load_config, schema_markdown
from rths_hil.errors import InputError
from rths_hil.keys import Key

ROOT = Path(__file__).resolve().parents[2]
SHARED = ("enabled", "method", "delay", "alpha", "amplitude", "options")
#: the keys each method reads besides the shared ones (as the methods document them)
METHOD_KEYS = {
    "inverse": {"adaptive", "time_constant", "delay_rate", "rate", "delay_min", "delay_max",
                "alpha_min", "alpha_max"},
    "polynomial": {"order"},
    "ats": {"ats_window", "ats_interval", "ats_cutoff", "ats_threshold", "ats_min", "ats_max",
            "ats_rate"},
    "model": {"model_delay", "model_time_constant", "model_gain", "model_num", "model_den",
              "model_cutoff", "model_order", "model_kp"},
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_each_method_declares_its_own_keys(name: str) -> None:
    cls = compensator_class(name)
    assert set(cls.KEYS) == METHOD_KEYS[name]
    assert all(isinstance(k, Key) for k in cls.KEYS.values())
    for key in cls.KEYS:  # the schema's entry is the method's own declaration
        assert SCHEMA["compensation"][key] is cls.KEYS[key]
    # every constructor argument comes from a shared key or one of the method's own
    assert set(cls.ARGUMENTS.values()) <= set(SHARED) | set(cls.KEYS)


def test_the_section_is_the_shared_keys_and_the_methods_keys() -> None:
    section = SCHEMA["compensation"]
    own = [k for name in BUILTIN for k in compensator_class(name).KEYS]
    assert len(own) == len(set(own))  # no key is declared by two methods
    assert list(section) == [*SHARED[:-1], *own, "options"]
    for step, (time, _) in STEP_KEYS.items():  # the step/time pairs are all in the section
        assert step in section and time in section


def test_docs_list_every_methods_keys_with_its_doc() -> None:
    doc = schema_markdown()
    for name in BUILTIN:
        for key, spec in compensator_class(name).KEYS.items():
            assert f"| `{key}` |" in doc and spec.doc in doc, key
    assert (ROOT / "docs" / "config.md").read_text().strip() == doc.strip()


def test_a_methods_key_is_checked_by_its_declaration(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[compensation]\nmethod = "ats"\nats_cutoff = -5\n')
    with pytest.raises(InputError, match=r"compensation\.ats_cutoff: must be > 0 Hz, got -5"):
        load_config(cfg)
    cfg.write_text("[compensation]\nmodel_ordr = 2\n")
    with pytest.raises(InputError, match=r"did you mean 'model_order'\?"):
        load_config(cfg)


@pytest.mark.timing  # starts a fresh interpreter
def test_reading_the_configuration_loads_neither_numba_nor_scipy() -> None:
    code = "import sys, rths_hil.config; print('numba' in sys.modules, 'scipy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"], out.stdout

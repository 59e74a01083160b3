"""Units accepted wherever a length, force or velocity is; plain-text ``--help``."""

from __future__ import annotations

import pytest

from rths_hil.cli import COMMANDS, build_parser
from rths_hil.config import load_config
from rths_hil.errors import InputError
from rths_hil.units import parse_force, parse_length, parse_velocity


@pytest.mark.parametrize(
    ("text", "si"),
    [
        ("2 in", 0.0508),  # 1 in = 25.4 mm exactly
        ("4cm", 0.04),
        ("50 mm", 0.05),
        ("1 ft", 0.3048),
        ("250um", 250e-6),
        ("0.03", 0.03),
    ],
)
def test_lengths(text, si):
    assert parse_length(text) == pytest.approx(si, rel=1e-15)
    cfg = load_config(None, [f'safety.displacement_limit="{text}"'])
    assert cfg["safety"]["displacement_limit"] == pytest.approx(si, rel=1e-15)


@pytest.mark.parametrize(
    ("text", "si"),
    [
        ("100 kN", 1e5),
        ("20 kip", 20 * 1000 * 0.45359237 * 9.80665),  # lbf = lb × g, both exact
        ("10 lbf", 10 * 0.45359237 * 9.80665),
        ("1.5MN", 1.5e6),
        ("500", 500.0),
    ],
)
def test_forces(text, si):
    assert parse_force(text) == pytest.approx(si, rel=1e-14)
    cfg = load_config(None, [f'safety.force_limit="{text}"'])
    assert cfg["safety"]["force_limit"] == pytest.approx(si, rel=1e-14)


def test_velocities():
    assert parse_velocity("200 mm/s") == pytest.approx(0.2, rel=1e-15)
    assert parse_velocity("10 in/s") == pytest.approx(0.254, rel=1e-15)
    cfg = load_config(None, ['safety.velocity_limit="8 cm/s"'])
    assert cfg["safety"]["velocity_limit"] == pytest.approx(0.08, rel=1e-15)


@pytest.mark.parametrize(
    ("item", "needle"),
    [
        ('safety.displacement_limit="3 furlong"', "use m, mm, cm, um, in or ft"),
        ('safety.force_limit="3 t"', "use N, kN, MN, lbf or kip"),
        ('safety.velocity_limit="3 mm/min"', "use m/s, mm/s, cm/s, in/s"),
    ],
)
def test_unknown_units_name_the_accepted_ones(item, needle):
    with pytest.raises(InputError) as exc:
        load_config(None, [item])
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def _parsers(parser):
    yield parser
    for action in parser._actions:
        choices = getattr(action, "choices", None)
        if isinstance(choices, dict):  # the sub-parsers
            for sub in choices.values():
                yield from _parsers(sub)


def test_help_is_plain_text_without_rest_markup():
    parser = build_parser()
    texts = [p.format_help() for p in _parsers(parser)]
    assert len(texts) > len(COMMANDS)  # every command and the sub-commands of study, twin
    for text in texts:
        assert "`" not in text and ":func:" not in text, text[:200]
    run = next(t for t in texts if t.startswith("usage: rths-hil run"))
    assert "also start rths-hil watch on the run" in run

"""Ground-motion loading (PEER AT2, CSV), PGA scaling and resampling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import rths_hil
from rths_hil import groundmotion as gmod
from rths_hil.errors import InputError
from rths_hil.units import G

AT2 = gmod.bundled_path("RSN6_IMPVALL.I_I-ELC180-hor1.AT2")
CHOPRA = gmod.bundled_path("el_centro_1940_NS_chopra_0p02.csv")


def _at2_values(path: Path) -> np.ndarray:
    """Independent reading: every token after the 4th line, as floats."""
    lines = path.read_text().splitlines()[4:]
    return np.array([float(t) for line in lines for t in line.split()])


def test_bundled_records_ship_inside_the_package():
    paths = gmod.bundled_records()
    assert len(paths) == 4
    pkg = Path(rths_hil.__file__).parent
    for p in paths:
        assert pkg in p.parents
    default = gmod.default_record()
    assert Path(default.source) == AT2


def test_at2_real_file():
    gm = gmod.load(AT2)
    assert gm.npts == 5372
    assert gm.dt == pytest.approx(0.01)
    assert gm.accel[0] == pytest.approx(0.9984852e-03 * G, rel=1e-12)
    assert gm.accel[-1] == pytest.approx(-0.1790158e-03 * G, rel=1e-12)
    np.testing.assert_allclose(gm.accel, _at2_values(AT2) * G, rtol=1e-15)
    # README of the data folder: PGA 0.281 g
    assert gm.pga / G == pytest.approx(0.281, abs=5e-4)
    assert gm.duration == pytest.approx(53.71)


def test_csv_real_file():
    gm = gmod.load(CHOPRA)
    assert gm.npts == 1560
    assert gm.dt == pytest.approx(0.02)
    assert gm.accel[1] == pytest.approx(6.3e-3 * G)
    assert gm.pga / G == pytest.approx(0.319, abs=5e-4)


@pytest.mark.parametrize(
    "header",
    [
        "NPTS=   5372, DT=   .0100 SEC,",
        "npts= 5372 dt= 0.01 sec",
        "DT= .0100 SEC, NPTS= 5372",
        "  5372    .0100    NPTS, DT",
        "NPTS=5372,DT=0.0100SEC",
    ],
)
def test_at2_header_variants(tmp_path, header):
    lines = AT2.read_text().splitlines()
    lines[3] = header
    p = tmp_path / "variant.at2"
    p.write_text("\n".join(lines) + "\n")
    gm = gmod.load(p)
    assert gm.npts == 5372 and gm.dt == pytest.approx(0.01)
    np.testing.assert_array_equal(gm.accel, gmod.load(AT2).accel)


def test_at2_units_cm_s2(tmp_path):
    lines = AT2.read_text().splitlines()
    lines[2] = "ACCELERATION TIME SERIES IN UNITS OF CM/S/S"
    p = tmp_path / "cms2.AT2"
    p.write_text("\n".join(lines))
    assert gmod.load(p).accel[0] == pytest.approx(0.9984852e-03 * 0.01)


def _broken(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda ls: ls[:-3], "truncated"),
        (lambda ls: [*ls, "  .1E-03"], "header says NPTS=5372"),
        (lambda ls: ls[:3] + ls[4:], "NPTS"),
        (lambda ls: [*ls[:10], "  .12E-03  abc  .1E-03", *ls[11:]], ":11: not a number"),
        (lambda ls: [*ls[:3], "NPTS=   5372, DT=   -.0100 SEC,", *ls[4:]], "DT="),
        (lambda ls: [*ls[:10], "  nan  .1  .1  .1  .1", *ls[11:]], "non-finite"),
    ],
)
def test_at2_broken_files(tmp_path, edit, message):
    lines = edit(AT2.read_text().splitlines())
    p = _broken(tmp_path, "broken.AT2", "\n".join(lines))
    with pytest.raises(InputError, match=message) as exc:
        gmod.load(p)
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)


def test_at2_empty_file(tmp_path):
    with pytest.raises(InputError, match="not a PEER AT2"):
        gmod.load(_broken(tmp_path, "empty.at2", ""))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("time_s,accel_g\n0,0.1\n0.01,0.2\n0.03,0.1\n0.04,0.0\n", "not uniformly"),
        ("time_s,foo\n0,0.1\n0.01,0.2\n", "no acceleration column"),
        ("x,accel_g\n0,0.1\n0.01,0.2\n", "no time column"),
        ("time_s,accel_g\n0,0.1\n0.01,oops\n", ":3: not a number"),
        ("time_s,accel_g\n0,0.1\n0.01,nan\n", ":3: non-finite"),
        ("time_s,accel_g\n0,0.1\n", "need at least 2"),
        ("time_s,accel_g\n0,0.1\n0.01\n", ":3: expected 2 values"),
        ("", "empty file"),
    ],
)
def test_csv_broken_files(tmp_path, text, message):
    p = _broken(tmp_path, "rec.csv", text)
    with pytest.raises(InputError, match=message):
        gmod.load(p)


def test_csv_column_choice_and_units(tmp_path):
    p = _broken(tmp_path, "two.csv", "time,accel_ms2,other\n0,1.0,5\n0.5,-2.0,6\n1.0,0.5,7\n")
    gm = gmod.load(p)
    np.testing.assert_array_equal(gm.accel, [1.0, -2.0, 0.5])
    assert gm.dt == 0.5
    gm2 = gmod.load(p, column="other", units="cm/s2")
    np.testing.assert_allclose(gm2.accel, [0.05, 0.06, 0.07])
    with pytest.raises(InputError, match="give the units"):
        gmod.load(p, column="other")


def test_unknown_format_and_missing_file(tmp_path):
    p = _broken(tmp_path, "rec.dat", "hello world\n1 2 3\n")
    with pytest.raises(InputError, match="unknown ground-motion format"):
        gmod.load(p)
    with pytest.raises(InputError, match="no such ground-motion file"):
        gmod.load(tmp_path / "nope.AT2")
    # an AT2 with another extension is sniffed
    q = tmp_path / "elc.txt"
    q.write_text(AT2.read_text())
    assert gmod.load(q).npts == 5372


def test_scaling_to_pga():
    gm = gmod.default_record()
    s = gm.scaled("0.0528g")
    assert s.pga == pytest.approx(0.0528 * G, rel=1e-12)
    np.testing.assert_allclose(s.accel / gm.accel[gm.accel != 0][0], s.accel / gm.accel[0])
    np.testing.assert_allclose(s.accel, gm.accel * (0.0528 * G / gm.pga), rtol=1e-13)
    assert gm.scaled(0.322).pga == pytest.approx(0.322)
    for bad in (-1.0, 0.0, "abc", "1 furlong"):
        with pytest.raises(InputError):
            gm.scaled(bad)


def test_resampling_is_band_limited():
    t = np.arange(3000) * 0.01
    x = np.sin(2 * np.pi * 2.0 * t) * np.sin(np.pi * t / t[-1]) ** 2  # tapered 2 Hz tone
    gm = gmod.GroundMotion("tone", 0.01, x)
    up = gm.resampled(1024)
    assert up.dt == 1 / 1024
    assert up.npts == int(np.ceil(3000 * 10.24))
    tu = up.time
    ref = np.sin(2 * np.pi * 2.0 * tu) * np.sin(np.pi * tu / t[-1]) ** 2
    inner = tu < t[-1]
    # a linear interpolation would be off by ~ (2π·2·0.01)²/8 ≈ 2e-3; band-limited is far better
    assert np.max(np.abs(up.accel[inner] - ref[inner])) < 2e-5
    # real record: up then back down reproduces the samples
    elc = gmod.default_record()
    back = elc.resampled(1024).resampled(100)
    err = back.accel[: elc.npts] - elc.accel
    assert np.sqrt(np.mean(err**2)) < 0.01 * np.sqrt(np.mean(elc.accel**2))
    with pytest.raises(InputError):
        elc.resampled(-5)


def test_resolve_bundled_name_and_errors(tmp_path):
    assert gmod.resolve("kobe_1995_nishi_akashi_NIS000").npts == 4096
    with pytest.raises(InputError, match="no such ground-motion file"):
        gmod.resolve(str(tmp_path / "missing.csv"))

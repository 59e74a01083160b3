"""The compensators (polynomial, ats, model), their registry and compensation in time units,
against closed forms, brute-force least squares and a real out-of-tree package."""

from __future__ import annotations

import importlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from rths_hil.sim_backends.delay import fractional_delay

from rths_hil.compensators import BUILTIN, available, build_compensator, compensator_class
from rths_hil.compensators.ats import ATSCompensator
from rths_hil.compensators.base import Compensator
from rths_hil.compensators.inverse import InverseCompensator
from rths_hil.compensators.model import ModelCompensator
from rths_hil.compensators.polynomial import PolynomialCompensator, lagrange_extrapolation
from rths_hil.config import load_config, set_compensation, to_toml
from rths_hil.errors import InputError

FS = 1024.0
DT = 1 / FS
ROOT = Path(__file__).resolve().parents[2]


def _run(comp, x):
    return np.array([comp.step(v) for v in x])


# ---------------------------------------------------------------------------------------------
# polynomial


def test_polynomial_order_one_is_inverse_compensation():
    x = np.cumsum(np.random.default_rng(1).normal(0, 1e-4, 2000))
    for delay in (0.0, 0.01, 0.0237):
        p = PolynomialCompensator(FS, delay, order=1, amplitude=0.97)
        i = InverseCompensator(1 + delay * FS, 0.97)
        p.reset(x[0])
        i.reset(x[0])
        np.testing.assert_allclose(_run(p, x), _run(i, x), rtol=0, atol=1e-15)
        assert p.alpha == pytest.approx(i.alpha)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_polynomial_is_exact_for_polynomials_of_its_order(order):
    tau = 0.02
    t = np.arange(200) * DT
    coef = np.random.default_rng(order).normal(0, 1, order + 1)

    def x(tt):
        return np.polyval(coef, tt)

    p = PolynomialCompensator(FS, tau, order=order)
    y = _run(p, x(t))
    np.testing.assert_allclose(y[order:], x(t[order:] + tau), rtol=1e-9, atol=1e-9)
    # one order higher is not reproduced (the test can fail)
    coef2 = np.append(coef, 0.0) + np.eye(order + 2)[0] * 50.0
    y2 = _run(PolynomialCompensator(FS, tau, order=order), np.polyval(coef2, t))
    assert np.abs(y2[order:] - np.polyval(coef2, t[order:] + tau)).max() > 1e-9


def test_polynomial_weights_sum_to_one_and_match_the_lagrange_closed_form():
    # n = 2, s = 3: ℓ0 = (s+1)(s+2)/2 = 10, ℓ1 = −s(s+2) = −15, ℓ2 = s(s+1)/2 = 6
    assert lagrange_extrapolation(2, 3.0) == pytest.approx([10.0, -15.0, 6.0])
    for n in range(1, 5):
        assert sum(lagrange_extrapolation(n, 17.3)) == pytest.approx(1.0)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_polynomial_amplitude_error_falls_with_the_order_on_a_pure_delay(order):
    # sine through the compensator then a pure delay τ: |A − 1| ~ (ωτ)^(n+1)
    tau, f = 0.02, 1.75
    w = 2 * math.pi * f
    t = np.arange(int(8 * FS)) * DT
    x = np.sin(w * t)
    meas = fractional_delay(_run(PolynomialCompensator(FS, tau, order=order), x), tau, FS)
    sl = slice(int(2 * FS), None)
    amp = np.sqrt(2 * np.mean(meas[sl] ** 2))
    h = sum(
        c * np.exp(-1j * w * j * DT) for j, c in enumerate(lagrange_extrapolation(order, tau * FS))
    )
    assert amp == pytest.approx(abs(h), rel=2e-3)  # the closed-form frequency response
    assert abs(amp - 1) < 1.5 * (w * tau) ** (order + 1)


def test_polynomial_bad_order_is_an_input_error():
    with pytest.raises(InputError, match="order"):
        PolynomialCompensator(FS, 0.02, order=5)


# ---------------------------------------------------------------------------------------------
# ats


def _multisine(n, amp=0.01):
    t = np.arange(n) * DT
    return amp * (np.sin(2 * np.pi * 0.8 * t) + 0.4 * np.sin(2 * np.pi * 1.9 * t + 1.0))


def _open_loop(comp, x, plant):
    """Target x through the compensator and ``plant`` (command history → measured)."""
    cmd = np.zeros(len(x))
    meas = np.zeros(len(x))
    for k in range(len(x)):
        cmd[k] = comp.step(x[k])
        meas[k] = plant(cmd, k)
        comp.observe(x[k], cmd[k], meas[k])
    return cmd, meas


def test_ats_fit_equals_brute_force_least_squares_of_its_window():
    c = ATSCompensator(FS, 0.02, rate=(1e6, 1e6, 1e6), lower=(-1e3,) * 3, upper=(1e3,) * 3)
    rng = np.random.default_rng(3)
    x = _multisine(int(3 * FS)) + rng.normal(0, 1e-5, int(3 * FS))
    d = 13
    cmd = np.zeros(len(x))
    for k in range(len(x)):
        cmd[k] = x[k] + 0.3 * x[k - 1]
        m = 0.95 * cmd[k - d] if k >= d else 0.0
        moved = c._observe(c._st, c._sos, c._ring, cmd[k], m)
        if moved:
            rows = c._ring
            ref = np.linalg.lstsq(rows[:, :3], rows[:, 3], rcond=None)[0]
            np.testing.assert_allclose(c.a, ref, rtol=1e-6)
            last = k
    assert last > 2.5 * FS  # it kept refitting


def test_ats_converges_from_a_wrong_delay_and_gain():
    gain = 0.9  # and a delay of 26 samples (25.4 ms)
    n = int(12 * FS)
    x = _multisine(n)
    c = ATSCompensator(FS, 0.0125)  # 50 % wrong
    _, meas = _open_loop(c, x, lambda cmd, k: gain * cmd[k - 26] if k >= 26 else 0.0)
    # the fitted inverse of g·e^(−sτ) is e^(sτ)/g: a0 ≈ 1/g, a1 ≈ τ/g (band-fit bias aside)
    assert c.a[0] == pytest.approx(1 / gain, rel=0.01)
    assert c.a[1] == pytest.approx(26 / FS / gain, abs=1e-3)
    sl = slice(int(6 * FS), None)
    err = meas[sl] - x[sl]
    assert np.sqrt(np.mean(err**2)) < 0.005 * np.sqrt(np.mean(x[sl] ** 2))
    assert c.alpha == pytest.approx(1 + c.a[1] * FS)


def test_ats_rate_limit_bounds_and_threshold():
    n = int(6 * FS)
    c = ATSCompensator(FS, 0.0, upper=(1.3, 0.015, 0.0032))
    hist = []
    for k, v in enumerate(_multisine(n)):
        cmd = c.step(v)
        c.observe(v, cmd, v if k < 40 else 0.0)  # measured stuck at 0: nothing to fit well
        hist.append(c.a.copy())
    h = np.array(hist)
    step_max = np.array([2.0, 0.05, 0.001]) / 64
    assert np.all(np.abs(np.diff(h, axis=0)) <= step_max + 1e-15)
    assert np.all(h >= [0.7, 0.0, 0.0]) and np.all(h <= [1.3, 0.015, 0.0032])
    # below the threshold (RMS 0.1 mm < 0.254 mm) the coefficients never move
    quiet = ATSCompensator(FS, 0.01)
    _open_loop(quiet, _multisine(n, 1e-4), lambda cmd, k: cmd[k - 5] if k >= 5 else 0.0)
    np.testing.assert_array_equal(quiet.a, quiet.a0_initial)
    assert quiet.updates == 0
    c.reset(0.0)
    np.testing.assert_array_equal(c.a, c.a0_initial)


def test_ats_window_too_short_and_cutoff_above_nyquist_are_input_errors():
    with pytest.raises(InputError, match="ats_window"):
        ATSCompensator(FS, 0.01, window=0.05)
    with pytest.raises(InputError, match="ats_cutoff"):
        ATSCompensator(FS, 0.01, cutoff=600.0)


# ---------------------------------------------------------------------------------------------
# model


def _freq(comp, f):
    z = np.exp(1j * 2 * np.pi * f / comp.fs)
    h = 1.0
    for b0, b1, b2, _, a1, a2 in comp.sos:
        h *= (b0 + b1 / z + b2 / z**2) / (1 + a1 / z + a2 / z**2)
    return h


def test_model_feedforward_inverts_a_first_order_servo_with_delay():
    T, tau, g = 0.02, 0.005, 0.95
    c = ModelCompensator(FS, tau, time_constant=T, gain=g)
    for f in (0.5, 1.0, 2.0):
        w = 2 * np.pi * f
        loop = _freq(c, f) * g * np.exp(-1j * w * tau) / (1 + 1j * w * T)
        assert abs(loop) == pytest.approx(1.0, abs=1e-3)
        assert abs(np.angle(loop)) / w < 1e-4  # < 0.1 ms of residual delay
    # the inverse alone would not be (|C·G| grows well off 1 at 20 Hz: the low-pass)
    assert abs(abs(_freq(c, 20.0)) * g / math.hypot(1, 2 * np.pi * 20 * T) - 1) > 0.01
    assert c.alpha == pytest.approx(1 + (T + tau) * FS)
    c.reset(0.3)
    assert c.step(0.3) == pytest.approx(0.3 / g, rel=1e-9)


def test_model_rational_transfer_function_and_feedback():
    # R(s) = ω²/(s² + 2ζω s + ω²): a second-order servo
    wn, zeta = 2 * np.pi * 15, 0.7
    c = ModelCompensator(FS, 0.0, num=[wn**2], den=[1, 2 * zeta * wn, wn**2], cutoff=100.0)
    for f in (0.5, 2.0):
        s = 2j * np.pi * f
        loop = _freq(c, f) * wn**2 / (s * s + 2 * zeta * wn * s + wn**2)
        assert abs(loop - 1) < 2e-3
    fb = ModelCompensator(FS, 0.0, kp=0.5)
    fb.reset(0.0)
    fb.observe(0.01, 0.01, 0.006)
    assert fb.step(0.0) == pytest.approx(0.5 * 0.004)
    with pytest.raises(InputError, match="right half-plane"):
        ModelCompensator(FS, 0.0, num=[-1.0, 1.0], den=[0.01, 1.0, 1.0])


def test_model_delay_key_overrides_delay_for_the_model_only():
    """model_delay ≥ 0 is the model's τ; the default (−1) takes compensation.delay."""
    wn = 2 * np.pi * 15
    sets = ["compensation.delay=20ms", f"compensation.model_num=[{wn**2}]"]
    sets += [f"compensation.model_den=[1, {1.4 * wn}, {wn**2}]"]
    cfg = load_config(None, sets)
    comp = cfg["compensation"]
    assert comp["model_delay"] == -1.0
    own = ModelCompensator.from_config({**comp, "model_delay": 0.0}, FS)
    shared = ModelCompensator.from_config(comp, FS)
    ref0 = ModelCompensator(FS, 0.0, num=[wn**2], den=[1, 1.4 * wn, wn**2])
    ref20 = ModelCompensator(FS, 0.02, num=[wn**2], den=[1, 1.4 * wn, wn**2])
    assert own.sos == ref0.sos and shared.sos == ref20.sos
    assert own.lead == pytest.approx(ref20.lead - 0.02)


# ---------------------------------------------------------------------------------------------
# registry and configuration

_MODULE = """
from rths_hil.compensators.inverse import Compensator


class ScaledLead(Compensator):
    \"\"\"command = gain·target + lead·(target − previous target)·fs (a lab's own law).\"\"\"

    def __init__(self, fs, gain=1.0, lead=0.0):
        self.fs, self.gain, self.lead = fs, gain, lead
        self.alpha = 1.0 + lead * fs
        self.prev = 0.0
        self.seen = 0

    def reset(self, target=0.0):
        self.prev = target

    def step(self, target):
        out = self.gain * target + self.lead * (target - self.prev) * self.fs
        self.prev = target
        return out

    def observe(self, target, command, measured):
        self.seen += 1


class NotACompensator:
    pass
"""


@pytest.fixture
def lab_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A real distribution on sys.path: a module and its dist-info with entry_points.txt."""
    (tmp_path / "mylab_comp.py").write_text(_MODULE)
    info = tmp_path / "mylab_comp-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mylab-comp\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[rths_hil.compensators]\nscaled = mylab_comp:ScaledLead\n"
        "broken = mylab_comp:NotACompensator\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    yield tmp_path
    sys.modules.pop("mylab_comp", None)


def test_builtin_compensators_load_without_metadata():
    assert set(BUILTIN) == {"inverse", "polynomial", "ats", "model"}
    for name in BUILTIN:
        cls = compensator_class(name)
        assert issubclass(cls, Compensator)
        cfg = load_config(None, [f"compensation.method={name}"])
        comp = build_compensator(cfg["compensation"], 1024.0)
        assert isinstance(comp, cls)
        comp.reset(0.0)
        assert comp.step(0.0) == 0.0
    with pytest.raises(InputError, match=r"unknown compensator 'nope'; available: ats, inverse"):
        compensator_class("nope")


def test_lab_compensator_from_an_entry_point_runs_in_the_loop(lab_package, tmp_path):
    from rths_hil.hybrid import RTHSLoop
    from rths_hil.records.recorder import read_run

    assert available()["scaled"] == "mylab_comp:ScaledLead"
    with pytest.raises(
        InputError, match=r"not a rths_hil\.compensators\.base\.Compensator subclass"
    ):
        compensator_class("broken")
    cfg = load_config(
        None,
        [
            "loop.mode=lockstep",
            "loop.console=0",
            "loop.duration=1",
            "output.plot=false",
            "fei.enabled=false",
            "kalman.enabled=false",
            "compensation.method=scaled",
            "compensation.options={gain=1.5, lead=0.002}",
        ],
    )
    loop = RTHSLoop(cfg, tmp_path / "run")
    res = loop.run()
    assert res.status == "completed"
    rec = read_run(tmp_path / "run").record
    x, c = rec["target"], rec["command"]
    ref = 1.5 * x[1:] + 0.002 * (x[1:] - x[:-1]) * FS
    np.testing.assert_allclose(c[1:], ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(rec["alpha"], 1 + 0.002 * FS)
    bad = load_config(None, ["compensation.method=scaled", "compensation.options={gian=2}"])
    with pytest.raises(InputError, match=r"compensation\.options: .*gian"):
        build_compensator(bad["compensation"], FS)


def test_alpha_is_read_at_its_sources_rate_and_delay_survives_a_change_of_rate(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[loop]\nfs = 1024\n[compensation]\nalpha = 26.6\n")
    for fs in (1024, 2048, 4096):
        c = load_config(p, [f"loop.fs={fs}"])["compensation"]
        assert c["delay"] == pytest.approx(0.025, rel=1e-12)
        assert c["alpha"] == pytest.approx(1 + 0.025 * fs, rel=1e-12)
    # a --set α is read at the final rate, in whatever order
    for sets in (
        ["loop.fs=2048", "compensation.alpha=52.2"],
        ["compensation.alpha=52.2", "loop.fs=2048"],
    ):
        assert load_config(p, sets)["compensation"]["delay"] == pytest.approx(0.025)
    # the last of α and delay wins
    c = load_config(p, ["compensation.alpha=11.24", "compensation.delay=0.02"])["compensation"]
    assert (c["delay"], c["alpha"]) == (0.02, pytest.approx(21.48))
    # both in one file must agree
    p.write_text("[compensation]\nalpha = 26.6\ndelay = 0.02\n")
    with pytest.raises(InputError, match=r"alpha = 26\.6 and compensation\.delay = 0\.02 disagree"):
        load_config(p)
    # the rendered configuration reloads to the same compensation, at another rate too
    cfg = load_config(None, ["compensation.delay=17ms"])
    p.write_text(to_toml(cfg))
    again = load_config(p, ["loop.fs=4096"])["compensation"]
    assert again["delay"] == pytest.approx(0.017) and again["alpha"] == pytest.approx(
        1 + 0.017 * 4096
    )
    # adaptive bounds and rate in time units
    assert again["alpha_max"] == pytest.approx(1 + cfg["compensation"]["delay_max"] * 4096)
    assert again["rate"] == pytest.approx(5.0 * 4)


def test_channel_alpha_and_delay(tmp_path):
    two = ROOT / "examples" / "two_actuators.toml"
    chans = load_config(two, ["loop.fs=2048"]).channels()
    assert [ch.config["compensation"]["delay"] for ch in chans] == pytest.approx([0.01, 0.02])
    assert [ch.config["compensation"]["alpha"] for ch in chans] == pytest.approx([21.48, 41.96])
    chans = load_config(two, ["actuators.storey3.compensation.alpha=11.24"]).channels()
    assert [ch.config["compensation"]["delay"] for ch in chans] == pytest.approx([0.01, 0.01])
    chans = load_config(two, ["compensation.delay=0.005"]).channels()  # every channel
    assert [ch.config["compensation"]["delay"] for ch in chans] == [0.005, 0.005]


def test_programmatic_edits_keep_alpha_and_delay_together():
    from rths_hil.hybrid.plan import build_plan

    cfg = load_config(None, ["loop.mode=lockstep"])
    set_compensation(cfg["compensation"], "alpha", 15.0, 1024.0)
    assert cfg["compensation"]["delay"] == pytest.approx(14 / 1024)
    plan = build_plan(cfg, duration=0.1)
    assert plan.channels[0].compensator.alpha == pytest.approx(15.0)
    cfg["compensation"]["alpha"] = 20.0  # alone: the two disagree, said in one line
    with pytest.raises(InputError, match=r"compensation\.alpha = 20 disagrees with"):
        build_plan(cfg, duration=0.1)


def test_adaptive_with_another_method_and_unknown_method_are_input_errors():
    from rths_hil.hybrid.plan import build_plan

    with pytest.raises(InputError, match="adaptive adapts the inverse method"):
        build_plan(load_config(None, ["compensation.method=ats", "compensation.adaptive=true"]))
    with pytest.raises(InputError, match="unknown compensator 'invrese'"):
        build_plan(load_config(None, ["compensation.method=invrese"]))

"""Candidate explanations of a discrepancy: each catalogue effect, a delay and a gain re-fit.

Every candidate is the current model with one change, fitted to the record by least squares (the sum
of squared residuals ``RSS = Σ (measured − predicted)²``). A new catalogue effect is inserted at its
place in the physical chain (each effect class's ``CHAIN``,
:data:`rths_hil.sim_backends.effects.EFFECT_ORDER`: actuator dynamics, valve flow limit, stops, play
of the load train, then the transducer's zero and drift); ``delay`` and ``gain`` re-fit the
actuator's own parameters.

What to fit and over which range is on each effect's class
(:class:`rths_hil.sim_backends.effects.Effect`:
``FIT``, ``fit_bounds``, ``fit_fixed``, ``low_frequency``, ``PARAMS``); this module holds the
fitting methods (bounded, :mod:`scipy.optimize`; the search spans well beyond the realistic
ranges, which a real actuator may exceed):

====================== =========================================================================
``linear``             ``offset``, ``drift``: ``y = x + v·regressor(t)``, the least-squares
                       solution (closed form).
``scalar``             one parameter, not smooth (clamps) in general (``backlash``,
                       ``velocity_limit``, ``servo_lag``, ``force_feedback``): a log-spaced
                       grid, then bounded Brent between the grid neighbours of the best point.
``stops``              ``stroke_limit``: the two stops act on disjoint samples, so the RSS
                       separates into one term per stop: a grid + Brent per side; a stop the data
                       never reach is not counted as a parameter.
``modulated_delay``    ``time_varying_delay``, ``τ(t) = D + a·sin(2πt/P)``: for each period of a
                       log grid the residual of the best constant delay is regressed
                       (linearised, ``r ≈ −δτ(t)·ẏ``) on ``ẏ`` and ``sin(2πt/P)·ẏ``; the best
                       period starts :func:`scipy.optimize.least_squares` on the exact model.
``delay`` (re-fit)     cross-correlation start (:func:`rths_hil.metrics.j1_delay`), then bounded
                       Brent (:func:`scipy.optimize.minimize_scalar`) within ±3 ms.
``gain`` (re-fit)      closed form without effects, else bounded Brent within ±20 %.
====================== =========================================================================

:func:`polish` re-fits jointly the parameters of several effects (and the actuator's delay and
gain) with :func:`scipy.optimize.least_squares` on the exact model.

When the base model was fitted to the record (no model file), its delay and gain are nuisance
parameters: every candidate's RSS is then taken after their linearised least-squares correction
(``Data.project``), and the candidates that add a low-frequency delay or gain (an effect's
``low_frequency``: ``servo_lag``, ``force_feedback``) give it back to the actuator while they are
fitted.

``force_feedback`` needs the specimen's stiffness and damping: they are regressed from the
record's force column (``F = k_s·y + c_s·ẏ + F0`` on the measured displacement and force
low-passed at 20 Hz, zero phase; ``ẏ`` the backward difference, as in the twin's specimen) or,
without a force column, taken from the model's ``[specimen]``; with neither, the candidate is
skipped (from displacement alone it is a gain plus a lag).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, signal

from rths_hil.sim_backends.effects import EFFECT_ORDER, EFFECTS, Effect
from rths_hil.sim_backends.modelfile import EffectSpec, ModelSpec
from rths_hil.sim_backends.models import make_model

from ..errors import InputError
from ..metrics import j1_delay
from ._fast import fractional_delay, simulate_chain, simulate_effect

log = logging.getLogger(__name__)

__all__ = [
    "CANDIDATES",
    "EFFECT_ORDER",
    "REFITS",
    "Candidate",
    "Data",
    "Fit",
    "Model",
    "delta_bic",
    "fit_candidate",
    "polish",
    "simulate_model",
]

#: Re-fits of the actuator's own parameters, tried before the catalogue effects.
REFITS: tuple[str, ...] = ("delay", "gain")
#: Every candidate, in the order of preference when two explain the record equally well
#: (a re-fit of an existing parameter first, then the effects by their ``PREFERENCE``).
CANDIDATES: tuple[str, ...] = (*REFITS, *sorted(EFFECTS, key=lambda k: EFFECTS[k].PREFERENCE))

_MIN_SPECIMEN_STIFFNESS = 1.0  # N/m: below this the force column does not describe a specimen


@dataclass
class Data:
    """The record the diagnosis works on (SI units, time from 0 at the first sample)."""

    command: np.ndarray
    measured: np.ndarray
    fs: float
    force: np.ndarray | None = None
    project: bool = False
    #: Specimen ``(k_s, c_s, source)`` for the effects that need it
    #: (:func:`specimen_from_record`); ``None`` when unknown.
    specimen: tuple[float, float, str] | None = None

    def __post_init__(self) -> None:
        self.n = len(self.command)
        self.dt = 1.0 / self.fs
        self.t = np.arange(self.n) * self.dt


def _effects(effects: list[EffectSpec], x: np.ndarray, dt: float) -> np.ndarray:
    return simulate_chain(effects, x, dt)


def _head(spec: ModelSpec, command: np.ndarray, dt: float) -> np.ndarray:
    """The model's dynamics in front of the transport delay and gain (the command itself for
    ``delay_gain``)."""
    a = spec.actuator
    if a.model == "delay_gain":
        return np.asarray(command, dtype=float)
    return make_model(a.model, dt, delay=0.0, gain=1.0, **a.params).simulate(command)


def simulate_model(spec: ModelSpec, command: np.ndarray, fs: float) -> np.ndarray:
    """Noiseless displacement of ``spec`` for ``command`` (actuator model then effects)."""
    return Model(spec, Data(np.asarray(command, dtype=float), np.zeros(len(command)), fs)).pred


class Model:
    """The current model with its simulated pieces cached (head, actuator output, prediction)."""

    def __init__(self, spec: ModelSpec, data: Data) -> None:
        self.spec = spec
        self.data = data
        self.head = _head(spec, data.command, data.dt)
        a = spec.actuator
        self.act = a.gain * fractional_delay(self.head, a.delay, data.fs)
        self.pred = _effects(a.effects, self.act, data.dt)
        self._best_delay: tuple[float, np.ndarray] | None = None

    def best_delay(self) -> tuple[float, np.ndarray]:
        """The actuator delay that best fits the record with everything else fixed, and its
        prediction: a cross-correlation start (:func:`rths_hil.metrics.j1_delay`), then
        bounded Brent within ±3 ms (computed once per model)."""
        if self._best_delay is None:
            d = self.data
            a = self.spec.actuator

            def pred_of(tau: float) -> np.ndarray:
                return _effects(a.effects, a.gain * fractional_delay(self.head, tau, d.fs), d.dt)

            shift = j1_delay(self.pred, d.measured, d.fs, max_lag_s=0.2)
            centre = max(a.delay + shift, 0.0)
            lo, hi = max(centre - 3e-3, 0.0), centre + 3e-3
            tau, _ = _scalar_fit(lambda v: _rss(d, pred_of(v)), lo, hi, n_grid=7, log_scale=False)
            self._best_delay = (tau, pred_of(tau))
        return self._best_delay

    @property
    def kinds(self) -> list[str]:
        """Kinds of the effects already in the model."""
        return [e.kind for e in self.spec.actuator.effects]

    def index_for(self, kind: str) -> int:
        """Where a new effect of ``kind`` goes in the chain: before the first effect that comes
        later in :data:`EFFECT_ORDER` (the physical order), else at the end."""
        rank = EFFECT_ORDER[kind]
        for i, e in enumerate(self.spec.actuator.effects):
            if EFFECT_ORDER.get(e.kind, len(EFFECT_ORDER)) > rank:
                return i
        return len(self.spec.actuator.effects)

    def slot(self, kind: str) -> tuple[int, np.ndarray, list[EffectSpec]]:
        """(index, input of the new effect, effects after it) for a new effect of ``kind``."""
        i = self.index_for(kind)
        effects = self.spec.actuator.effects
        if i == len(effects):
            return i, self.pred, []
        return i, _effects(effects[:i], self.act, self.data.dt), list(effects[i:])

    def with_changes(
        self,
        delay: float | None = None,
        gain: float | None = None,
        effect: EffectSpec | None = None,
        index: int | None = None,
    ) -> ModelSpec:
        """A copy of the spec with a new delay/gain and/or one more effect at ``index``
        (default: its place in :data:`EFFECT_ORDER`)."""
        spec = copy.deepcopy(self.spec)
        a = spec.actuator
        if delay is not None:
            a.delay = float(delay)
        if gain is not None:
            a.gain = float(gain)
        if effect is not None:
            a.effects.insert(self.index_for(effect.kind) if index is None else index, effect)
        return spec


@dataclass
class Fit:
    """One fitted candidate.

    Attributes
    ----------
    name : str
        Candidate name (catalogue kind, ``delay`` or ``gain``).
    params : dict
        Fitted parameters (SI), as written to the model file.
    k : int
        Number of free parameters the fit used (for the BIC).
    rss : float
        Sum of squared residuals (m²).
    pred : ndarray
        Prediction of the candidate model (m).
    spec : ModelSpec
        The candidate model.
    note : str
        Anything worth reporting about the fit.
    """

    name: str
    params: dict[str, float]
    k: int
    rss: float
    pred: np.ndarray = field(repr=False)
    spec: ModelSpec = field(repr=False)
    note: str = ""


@dataclass
class Candidate:
    """A candidate that was not fitted (and why)."""

    name: str
    reason: str


def _rss(data: Data, pred: np.ndarray) -> float:
    """Sum of squared residuals; with ``data.project``, after the least-squares correction of
    the actuator's delay and gain, linearised: ``r ≈ ε·p − δ·ṗ`` (a base fitted to the record
    has them as nuisance parameters, re-fitted exactly by :func:`polish` once a candidate is
    named)."""
    r = data.measured - pred
    rr = float(r @ r)
    if not data.project:
        return rr
    pd = np.gradient(pred)
    a11, a12, a22 = float(pred @ pred), float(pred @ pd), float(pd @ pd)
    b1, b2 = float(pred @ r), float(pd @ r)
    det = a11 * a22 - a12 * a12
    if det <= 0:
        return rr
    return max(rr - (a22 * b1 * b1 - 2 * a12 * b1 * b2 + a11 * b2 * b2) / det, 0.0)


def _scalar_fit(
    rss_of: Callable[[float], float],
    lo: float,
    hi: float,
    n_grid: int = 14,
    log_scale: bool = True,
) -> tuple[float, float]:
    """Minimise a 1-D RSS: grid over [lo, hi], then bounded Brent around the best grid point."""
    if log_scale:
        grid = np.geomspace(lo, hi, n_grid)
        to_x: Callable[[float], float] = math.exp
        to_u: Callable[[float], float] = math.log
    else:
        grid = np.linspace(lo, hi, n_grid)
        to_x = to_u = float
    vals = [rss_of(float(g)) for g in grid]
    i = int(np.argmin(vals))
    a = float(grid[max(i - 1, 0)])
    b = float(grid[min(i + 1, n_grid - 1)])
    best_x, best_v = float(grid[i]), float(vals[i])
    if b > a:
        res = optimize.minimize_scalar(
            lambda u: rss_of(to_x(u)),
            bounds=(to_u(a), to_u(b)),
            method="bounded",
            options={"xatol": 1e-4 if log_scale else 1e-4 * (b - a)},
        )
        if res.fun < best_v:
            best_x, best_v = to_x(float(res.x)), float(res.fun)
    return best_x, best_v


def specimen_from_record(data: Data, spec: ModelSpec) -> tuple[float, float, str] | None:
    """Specimen stiffness and damping for ``force_feedback``: from the force column, else the
    model's ``[specimen]``; ``None`` when neither is available."""
    if data.force is not None and np.ptp(data.force) > 0:
        sos = signal.butter(4, min(20.0, 0.4 * data.fs), fs=data.fs, output="sos")
        y = signal.sosfiltfilt(sos, data.measured)
        f = signal.sosfiltfilt(sos, data.force)
        # backward difference, as the twin's Kelvin-Voigt specimen (rths_hil.sim_backends.specimen)
        v = np.concatenate([[0.0], np.diff(y)]) / data.dt
        a = np.column_stack([y, v, np.ones(data.n)])
        (k_s, c_s, _), *_ = np.linalg.lstsq(a, f, rcond=None)
        if k_s > _MIN_SPECIMEN_STIFFNESS:
            return float(k_s), float(max(c_s, 0.0)), "record force column"
    if spec.specimen is not None:
        return spec.specimen.stiffness, spec.specimen.damping, "model [specimen]"
    return None


# -- candidates -------------------------------------------------------------------------------


def _fit_linear(m: Model, d: Data, cls: type[Effect]) -> Fit:
    """``y = x + v·regressor(t)`` (``offset``, ``drift``): closed form at the end of the chain
    (bounded Brent when effects follow it or the delay and gain are projected out)."""
    kind, name = cls.kind, cls.FIT.param
    shape = cls.regressor(d.t)
    i, x, suffix = m.slot(kind)

    def pred_of(v: float) -> np.ndarray:
        return _effects(suffix, x + v * shape, d.dt)

    v = float((d.measured - m.pred) @ shape / (shape @ shape))
    if suffix or d.project:
        span = max(
            abs(v), float(np.std(d.measured - m.pred)) / max(np.sqrt(np.mean(shape**2)), 1e-30)
        )
        v, _ = _scalar_fit(
            lambda u: _rss(d, pred_of(u)), v - 2 * span, v + 2 * span, n_grid=9, log_scale=False
        )
    pred = pred_of(v)
    spec = m.with_changes(effect=EffectSpec(kind, {name: v}), index=i)
    return Fit(kind, {name: v}, 1, _rss(d, pred), pred, spec)


def _fit_delay(m: Model, d: Data) -> Fit:
    tau, pred = m.best_delay()
    return Fit("delay", {"delay": tau}, 1, _rss(d, pred), pred, m.with_changes(delay=tau))


def _fit_gain(m: Model, d: Data) -> Fit:
    a = m.spec.actuator
    base = m.act / a.gain if a.gain != 0 else fractional_delay(m.head, a.delay, d.fs)
    # linearised start: the gain that best scales the current prediction's motion
    p = m.pred - m.pred.mean()
    y = d.measured - d.measured.mean()
    g0 = a.gain * float(p @ y / (p @ p)) if p @ p > 0 else a.gain

    def pred_of(g: float) -> np.ndarray:
        return _effects(a.effects, g * base, d.dt)

    if not a.effects:
        g = float(base @ d.measured / (base @ base))  # linear: closed form
    else:
        g, _ = _scalar_fit(
            lambda v: _rss(d, pred_of(v)), 0.8 * g0, 1.2 * g0, n_grid=7, log_scale=False
        )
    pred = pred_of(g)
    return Fit("gain", {"gain": g}, 1, _rss(d, pred), pred, m.with_changes(gain=g))


def _fit_scalar(m: Model, d: Data, cls: type[Effect]) -> Fit:
    """Fit the one free parameter ``cls.FIT.param`` of a new effect (grid + bounded Brent)
    within ``cls.fit_bounds``, the parameters of ``cls.fit_fixed`` held.

    ``cls.low_frequency(params) -> (delay, gain factor)`` is the low-frequency delay and gain
    the effect adds; when the actuator's delay and gain are nuisance parameters
    (``d.project``), the actuator gives them back (its delay shortened, its gain divided), so
    that the candidate is compared at the delay and gain that suit it rather than at those the
    base absorbed.
    """
    kind, name = cls.kind, cls.FIT.param
    specimen = d.specimen[:2] if d.specimen is not None else None
    fixed = cls.fit_fixed(specimen)
    i, x, suffix = m.slot(kind)
    lo, hi = cls.fit_bounds(x, d.fs, specimen)
    a = m.spec.actuator
    compensate = d.project and cls.low_frequency({name: 1.0, **fixed}) is not None
    prefix = a.effects[:i]

    def actuator_for(v: float) -> tuple[float, float]:
        shift, factor = cls.low_frequency({name: v, **fixed})  # type: ignore[misc]
        return max(a.delay - shift, 0.0), a.gain / factor

    def pred_of(v: float) -> np.ndarray:
        xin = x
        if compensate:
            tau, g = actuator_for(v)
            xin = _effects(prefix, g * fractional_delay(m.head, tau, d.fs), d.dt)
        return _effects(suffix, simulate_effect(kind, {name: v, **fixed}, xin, d.dt), d.dt)

    v, _ = _scalar_fit(lambda v: _rss(d, pred_of(v)), lo, hi)
    pred = pred_of(v)
    params = {name: v, **fixed}
    if compensate:
        tau, g = actuator_for(v)
        spec = m.with_changes(delay=tau, gain=g, effect=EffectSpec(kind, params), index=i)
    else:
        spec = m.with_changes(effect=EffectSpec(kind, params), index=i)
    note = cls.fit_note(params, x, d.fs)
    if cls.FIT.needs_specimen and d.specimen is not None:
        k_s, c_s, source = d.specimen
        note = f"specimen k = {k_s:.4g} N/m, c = {c_s:.4g} N·s/m from the {source}"
    return Fit(kind, params, 1, _rss(d, pred), pred, spec, note=note)


def _fit_stops(m: Model, d: Data, cls: type[Effect]) -> Fit:
    """``stroke_limit``: one grid + Brent per stop."""
    i, p, suffix = m.slot("stroke_limit")
    pmax, pmin = float(np.max(p)), float(np.min(p))
    span = pmax - pmin
    mid = float(np.median(p))

    def side(top: bool) -> tuple[float, bool]:
        if top:
            lo, hi = mid + 0.05 * span, pmax + 1e-3 * span

            def rss_of(v: float) -> float:
                return _rss(d, _effects(suffix, np.minimum(p, v), d.dt))

            edge = pmax
        else:
            lo, hi = -mid + 0.05 * span, -pmin + 1e-3 * span

            def rss_of(v: float) -> float:
                return _rss(d, _effects(suffix, np.maximum(p, -v), d.dt))

            edge = -pmin
        v, _ = _scalar_fit(rss_of, lo, hi, n_grid=16, log_scale=False)
        return v, v < edge

    hi_stop, hi_active = side(True)
    neg_lo, lo_active = side(False)
    lo_stop = -neg_lo
    if hi_active and not lo_active:
        lo_stop = -hi_stop if -hi_stop <= pmin else pmin - 1e-3 * span
    elif lo_active and not hi_active:
        hi_stop = -lo_stop if -lo_stop >= pmax else pmax + 1e-3 * span
    elif not hi_active and not lo_active:
        hi_stop, lo_stop = pmax + 1e-3 * span, pmin - 1e-3 * span
    params = {"limit": 0.5 * (hi_stop - lo_stop), "center": 0.5 * (hi_stop + lo_stop)}
    pred = _effects(suffix, np.clip(p, lo_stop, hi_stop), d.dt)
    k = max(int(hi_active) + int(lo_active), 1)
    fit = Fit(
        "stroke_limit",
        params,
        k,
        _rss(d, pred),
        pred,
        m.with_changes(effect=EffectSpec("stroke_limit", params), index=i),
    )
    if k == 1 and (hi_active or lo_active):
        fit.note = f"only the {'upper' if hi_active else 'lower'} stop is reached"
    elif not (hi_active or lo_active):
        fit.note = "no stop reached: inactive"
    return fit


#: Periods (s) searched for the time-varying delay before the exact refinement.
_TVD_PERIODS = np.geomspace(1.0, 200.0, 64)


def _fit_modulated_delay(m: Model, d: Data, cls: type[Effect]) -> Fit:
    """``time_varying_delay``: linearised search over the period, then exact least squares."""
    a = m.spec.actuator
    base = a.gain * m.head  # the actuator output without its transport delay
    t = d.t
    if d.project:  # the delay is a nuisance parameter, re-fitted with every candidate
        tau = a.delay
        q = _effects(a.effects, a.gain * fractional_delay(m.head, tau, d.fs), d.dt)
    else:  # the best constant delay
        tau, q = m.best_delay()
    qd = np.gradient(q, d.dt)
    r = d.measured - q
    w = qd * qd
    s_all = np.sin(2 * np.pi * np.outer(1.0 / _TVD_PERIODS, t))  # (P, N)
    a11 = float(w.sum())
    a12 = s_all @ w
    a22 = (s_all * s_all) @ w
    b1 = -float(qd @ r)
    b2 = -(s_all @ (qd * r))
    det = a11 * a22 - a12 * a12
    with np.errstate(divide="ignore", invalid="ignore"):
        dd = (a22 * b1 - a12 * b2) / det
        aa = (a11 * b2 - a12 * b1) / det
        gain_ls = dd * b1 + aa * b2  # RSS reduction of the linearised fit
    gain_ls = np.where((aa > 0) & np.isfinite(gain_ls), gain_ls, -np.inf)
    i = int(np.argmax(gain_ls))
    d0 = max(tau + (float(dd[i]) if np.isfinite(gain_ls[i]) else 0.0), 0.0)
    a0 = float(aa[i]) if np.isfinite(gain_ls[i]) else 0.0
    a0 = min(max(a0, 0.0), 0.95 * d0) if d0 > 0 else 0.0
    p0 = float(_TVD_PERIODS[i])

    def pred_of(theta: np.ndarray) -> np.ndarray:
        dm, rho, lp = theta
        params = {"delay": dm, "amplitude": rho * dm, "period": math.exp(lp)}
        return _effects(a.effects, simulate_effect("time_varying_delay", params, base, d.dt), d.dt)

    scale = float(np.sqrt(np.mean(d.measured**2))) or 1.0
    theta0 = np.array([max(d0, 1e-4), a0 / max(d0, 1e-4), math.log(p0)])
    lower = np.array([0.0, 0.0, math.log(0.5)])
    upper = np.array([0.5, 1.0, math.log(1000.0)])
    res = optimize.least_squares(
        lambda th: (d.measured - pred_of(th)) / scale,
        np.clip(theta0, lower, upper),
        bounds=(lower, upper),
        x_scale=np.array([1e-3, 0.1, 0.1]),
        diff_step=1e-4,
        max_nfev=60,
    )
    dm, rho, lp = (float(v) for v in res.x)
    amp, period = rho * dm, math.exp(lp)
    pred = pred_of(res.x)
    # split the mean delay between the actuator (what exceeds the effect's need) and the effect
    eff_delay = min(dm, max(amp, dm - a.delay))
    params = {"delay": eff_delay, "amplitude": amp, "period": period}
    spec = m.with_changes(
        delay=dm - eff_delay, effect=EffectSpec("time_varying_delay", params), index=0
    )
    return Fit(
        "time_varying_delay",
        params,
        3,
        _rss(d, pred),
        pred,
        spec,
        note=f"total mean delay {1e3 * dm:.3f} ms (actuator {1e3 * (dm - eff_delay):.3f} ms)",
    )


#: The fitting methods an effect's ``FIT.method`` names.
_METHODS: dict[str, Callable[[Model, Data, type[Effect]], Fit]] = {
    "linear": _fit_linear,
    "scalar": _fit_scalar,
    "stops": _fit_stops,
    "modulated_delay": _fit_modulated_delay,
}


def fit_candidate(name: str, model: Model, data: Data) -> Fit | Candidate:
    """Fit candidate ``name`` (a re-fit or a catalogue effect) on top of ``model``."""
    if name not in REFITS and name in model.kinds:
        return Candidate(name, "already in the model")
    if name in REFITS and data.project:
        return Candidate(name, "re-fitted with every candidate (base fitted to the record)")
    if name == "delay":
        return _fit_delay(model, data)
    if name == "gain":
        return _fit_gain(model, data)
    cls = EFFECTS[name]
    if cls.FIT.needs_specimen and data.specimen is None:
        return Candidate(name, "needs a force column or a [specimen] in the model (specimen k, c)")
    return _METHODS[cls.FIT.method](model, data, cls)


def delta_bic(n: int, rss_before: float, rss_after: float, k: int) -> float:
    """BIC improvement of a model with ``k`` more parameters (Schwarz 1978, Gaussian residuals
    with unknown variance): ``N·ln(RSS_before/RSS_after) − k·ln N``; infinite when the new model
    fits exactly."""
    if rss_after <= 0:
        return math.inf
    return n * math.log(rss_before / rss_after) - k * math.log(n)


#: One parameter :func:`polish` moves: (where, effect index or None, name, start value, log).
_Slot = tuple[str, int | None, str, float, bool]


def _polish_slots(
    work: ModelSpec, effects: list[int], actuator: bool
) -> tuple[list[_Slot], dict[tuple[int, str], float | None]]:
    """The parameters :func:`polish` moves and the effects' finite-difference steps."""
    a = work.actuator
    slots: list[_Slot] = []
    if actuator and "time_varying_delay" not in [e.kind for e in a.effects]:
        slots.append(("actuator", None, "delay", a.delay, False))
    if actuator:
        slots.append(("actuator", None, "gain", a.gain, False))
    steps: dict[tuple[int, str], float | None] = {}
    for i in effects:
        e = a.effects[i]
        for prm in EFFECTS[e.kind].PARAMS:
            if not prm.polish:
                continue
            v = float(e.params[prm.name])
            slots.append(("effect", i, prm.name, v, prm.log_scale and v > 0))
            steps[i, prm.name] = prm.step
    return slots, steps


def _polish_scales(slots: list[_Slot], steps: dict[tuple[int, str], float | None]) -> list[float]:
    """The scale of each slot: 1 for a logarithm, else its step or its start value."""
    scales = []
    for _, idx, name, v, lg in slots:
        if idx is None:  # the actuator's delay or gain
            step: float | None = {"delay": 1e-3, "gain": 1e-2}[name]
        else:
            step = steps.get((idx, name))
        if lg:
            scales.append(1.0)
        elif step is not None:
            scales.append(step)
        else:
            scales.append(max(abs(v), 1e-9))
    return scales


def polish(
    spec: ModelSpec,
    data: Data,
    effects: list[int],
    actuator: bool,
    max_nfev: int = 30,
) -> tuple[ModelSpec, np.ndarray, float]:
    """Re-fit jointly the parameters of ``spec``'s effects at indices ``effects`` and, when
    ``actuator``, its delay and gain: :func:`scipy.optimize.least_squares` (trust-region
    reflective, bounded, finite-difference Jacobian) on the residual vector, parameters scaled
    (logarithm of the positive scale parameters, the others about their start value).

    Used once an effect is named: its parameters were fitted with the others fixed, and a base
    fitted to the record (delay + gain) absorbed part of the then-unmodelled effect.

    Returns
    -------
    (spec, prediction, rss)
        The polished model, never worse than the input (the input itself when polishing does
        not lower the RSS); ``rss`` is the exact (not projected) sum of squares.
    """
    exact = Data(data.command, data.measured, data.fs, data.force)
    work = copy.deepcopy(spec)
    a = work.actuator
    slots, steps = _polish_slots(work, effects, actuator)
    pred_in = Model(spec, exact).pred
    rss_in = _rss(exact, pred_in)
    if not slots or rss_in == 0:
        return spec, pred_in, rss_in
    scales = _polish_scales(slots, steps)
    lower = np.array([-math.log(10.0) if sl[4] else -10.0 for sl in slots])
    upper = np.array([math.log(10.0) if sl[4] else 10.0 for sl in slots])
    for j, sl in enumerate(slots):  # the delay may move by up to 50 ms (not below 0)
        if sl[0] == "actuator" and sl[2] == "delay":
            lower[j], upper[j] = -min(sl[3], 0.05) / scales[j], 0.05 / scales[j]

    def apply(u: np.ndarray) -> ModelSpec:
        for (where, i, name, v0, lg), ui, sc in zip(slots, u, scales, strict=True):
            v = float(v0 * math.exp(ui) if lg else v0 + ui * sc)
            if where == "actuator":
                setattr(a, name, max(v, 0.0) if name == "delay" else v)
            else:
                a.effects[i].params[name] = v  # type: ignore[index]
        for e in a.effects:  # keep the effects valid (continuously: clamp, don't reject)
            EFFECTS[e.kind].clamp(e.params)
        return work

    norm = math.sqrt(rss_in)

    def residual(u: np.ndarray) -> np.ndarray:
        try:
            return (data.measured - Model(apply(u), exact).pred) / norm
        except InputError:  # a parameter outside its effect's bounds
            return np.full(data.n, 1e3 / math.sqrt(data.n))

    res = optimize.least_squares(
        residual,
        np.zeros(len(slots)),
        bounds=(lower, upper),
        method="trf",
        diff_step=1e-4,
        x_scale=1.0,
        max_nfev=max_nfev,
    )
    out = copy.deepcopy(apply(res.x))
    pred = Model(out, exact).pred
    rss = _rss(exact, pred)
    if not rss < rss_in:
        return spec, pred_in, rss_in
    return out, pred, rss

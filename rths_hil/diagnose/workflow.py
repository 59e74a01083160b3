"""The discrepancy workflow: localise, name the missing effect, add it, repeat, show the gap.

Loop (``rths-hil diagnose``, :func:`diagnose`):

1. simulate the current model with the record's command (noiseless); the residual is
   ``measured − predicted``;
2. localise it (:func:`rths_hil.diagnose.localise.localise`: when, at which frequencies, in
   which regime; reported for the final model built up step by step);
3. fit every candidate (:mod:`rths_hil.diagnose.candidates`) and score it by the Bayesian
   information criterion of Schwarz (1978) for Gaussian residuals with unknown variance,
   ``BIC = N·ln(RSS/N) + k·ln N``; a candidate is *significant* when it lowers the BIC of the
   current model by more than ``threshold`` (default 10, "very strong" evidence in Kass &
   Raftery, JASA 90:773, 1995). The most significant one is named; candidates within
   ``tie_margin`` (default 2, "not worth more than a bare mention") of it are reported as
   indistinguishable alternatives, and the first of them in :data:`CANDIDATES` order is named
   (a re-fit of the actuator's delay or gain before a new effect; simpler effects first);
4. add it to the model and repeat until no candidate is significant (the answer is then
   ``none`` if nothing was added) or ``max_effects`` have been added;
5. safeguards for several effects (:class:`_Search`): once effects are named, the three best
   candidates of a screening are verified by a joint re-fit with them; with two or more named,
   the selection is rerun from the next best first choices and the path of lowest total BIC
   kept; then each named effect is re-examined with the others in the model (replaced by a
   better candidate, dropped when no longer significant);
6. the gap before and after each step: J2 (NRMS, %) and J3 (peak, %) of the prediction against
   the measurement (:mod:`rths_hil.metrics`, normalised by the measurement), and the FEI
   A and d of measured against predicted (the FEI paper's Eq. 2.1-2.5).

The BIC assumes independent residuals: white sensor noise once the model is right. A residual
that stays coloured (model error the catalogue cannot express) makes the criterion liberal;
raise ``threshold`` for such records.
"""

from __future__ import annotations

import copy
import logging
import math
import time as _time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rths_hil.sim_backends.modelfile import ModelSpec

from ..errors import InputError
from ..estimation import calibrate
from ..fei import fei
from ..metrics import j2_nrms, j3_peak
from .candidates import (
    CANDIDATES,
    Candidate,
    Data,
    Fit,
    Model,
    _rss,
    delta_bic,
    fit_candidate,
    polish,
    specimen_from_record,
)
from .localise import Localisation, _intervals, localise, moving_ms

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_THRESHOLD",
    "MIN_CYCLES",
    "MIN_DURATION_S",
    "Diagnosis",
    "Gap",
    "Step",
    "check_record",
    "diagnose",
]

#: Default significance threshold on the BIC improvement.
DEFAULT_THRESHOLD = 10.0
#: Default margin within which two candidates are reported as indistinguishable.
DEFAULT_TIE_MARGIN = 2.0
#: Shortest record the workflow decides on (s) …
MIN_DURATION_S = 5.0
#: … and the fewest cycles of the command's equivalent frequency (the FEI paper's Eq. 2.4) it must
#: hold.
MIN_CYCLES = 5.0
_MIN_SAMPLES = 256


@dataclass
class Gap:
    """Discrepancy between a prediction and the measurement.

    Attributes
    ----------
    j2 : float
        NRMS error, % of the measurement's RMS (Silva et al. 2020, J2).
    j3 : float
        Peak error, % of the measurement's peak (J3).
    fei_amplitude, fei_delay : float
        FEI A and d (s) of measured against predicted (the FEI paper's Eq. 2.1-2.5): 1 and 0 when
        they agree.
    rms : float
        RMS of the residual (m).
    """

    j2: float
    j3: float
    fei_amplitude: float
    fei_delay: float
    rms: float

    @classmethod
    def of(cls, measured: np.ndarray, pred: np.ndarray, fs: float) -> Gap:
        """Gap of ``pred`` against ``measured``."""
        f = fei(pred, measured, fs)
        r = measured - pred
        return cls(
            j2=j2_nrms(measured, pred),
            j3=j3_peak(measured, pred),
            fei_amplitude=float(f.amplitude),
            fei_delay=float(f.delay),
            rms=float(np.sqrt(np.mean(r * r))),
        )

    def to_json(self) -> dict[str, float]:
        """Plain dict."""
        return {
            "j2_percent": self.j2,
            "j3_percent": self.j3,
            "fei_amplitude": self.fei_amplitude,
            "fei_delay_s": self.fei_delay,
            "rms_m": self.rms,
        }


def _gaps(before: Gap, after: Gap) -> dict[str, Any]:
    """The twin-vs-measurement gap before and after (J2, J3 and the FEI) for ``report.json``."""
    return {
        "gap_before": before.j2,
        "gap_after": after.j2,
        "j3_before": before.j3,
        "j3_after": after.j3,
        "fei_before": {"amplitude": before.fei_amplitude, "delay_s": before.fei_delay},
        "fei_after": {"amplitude": after.fei_amplitude, "delay_s": after.fei_delay},
    }


@dataclass
class Step:
    """One named effect (or re-fit) and what it changed.

    Attributes
    ----------
    name : str
        Catalogue kind, ``delay`` or ``gain``.
    params : dict
        Fitted parameters (SI).
    delta_bic : float
        BIC improvement over the model before the step.
    alternatives : list of str
        Candidates within the tie margin (indistinguishable on this record).
    candidates : list of dict
        Every candidate's fit at this step: name, ΔBIC, parameters, note.
    where : dict
        Localisation of the residual before the step, plus ``acts``: where the added effect
        changes the prediction by more than the noise.
    before, after : Gap
        Gap before and after the step.
    spec : ModelSpec
        The model after the step.
    pred : ndarray
        Its prediction (m).
    localisation : Localisation
        Full localisation before the step (arrays for the plots).
    """

    name: str
    params: dict[str, float]
    delta_bic: float
    alternatives: list[str]
    candidates: list[dict[str, Any]]
    where: dict[str, Any]
    before: Gap
    after: Gap
    spec: ModelSpec = field(repr=False)
    pred: np.ndarray = field(repr=False)
    localisation: Localisation = field(repr=False)

    def to_json(self) -> dict[str, Any]:
        """Entry of ``report.json``'s ``effects``."""
        return {
            "name": self.name,
            "parameters": self.params,
            "delta_bic": self.delta_bic,
            "alternatives": self.alternatives,
            "where": self.where,
            **_gaps(self.before, self.after),
            "candidates": self.candidates,
        }


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes
    ----------
    base, model : ModelSpec
        The starting model and the augmented one.
    base_source : str
        Where the base model came from (file, or ``fitted to the record``).
    steps : list of Step
        Named effects in order (empty: the answer is ``none``).
    stop : dict
        Why the loop stopped (reason, best remaining candidate and its ΔBIC).
    before, after : Gap
        Gap of the base and of the augmented model.
    base_pred, pred : ndarray
        Their predictions (m).
    final : Localisation
        Localisation of what is left.
    time, command, measured, force : ndarray
        The record.
    fs : float
    threshold, tie_margin : float
    runtime_s : float
    notes : list of str
    """

    base: ModelSpec
    model: ModelSpec
    base_source: str
    steps: list[Step]
    stop: dict[str, Any]
    before: Gap
    after: Gap
    base_pred: np.ndarray = field(repr=False)
    pred: np.ndarray = field(repr=False)
    base_localisation: Localisation = field(repr=False)
    final: Localisation = field(repr=False)
    time: np.ndarray = field(repr=False)
    command: np.ndarray = field(repr=False)
    measured: np.ndarray = field(repr=False)
    force: np.ndarray | None = field(repr=False)
    fs: float = 0.0
    threshold: float = DEFAULT_THRESHOLD
    tie_margin: float = DEFAULT_TIE_MARGIN
    runtime_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        """Names of the steps (empty list = ``none``)."""
        return [s.name for s in self.steps]

    @property
    def answer(self) -> str:
        """``none`` or the named effects joined by ``+``."""
        return " + ".join(self.names) if self.steps else "none"

    def report(self, model_path: str | None = None) -> dict[str, Any]:
        """The ``report.json`` content (gaps as J2 in %)."""
        return {
            "answer": self.answer,
            "effects": [s.to_json() for s in self.steps],
            **_gaps(self.before, self.after),
            "model": model_path,
            "base_model": self.base_source,
            "criterion": {
                "name": "BIC = N ln(RSS/N) + k ln N (Schwarz 1978)",
                "threshold": self.threshold,
                "tie_margin": self.tie_margin,
                "samples": len(self.measured),
            },
            "stop": self.stop,
            "history": self.history,
            "noise_m": self.final.noise,
            "remaining": self.final.to_json(),
            "record": {
                "samples": len(self.measured),
                "fs_hz": self.fs,
                "duration_s": len(self.measured) / self.fs,
                "force": self.force is not None,
            },
            "notes": self.notes,
            "runtime_s": self.runtime_s,
        }


def _as_array(name: str, values: Any) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if a.ndim != 1:
        raise InputError(f"{name}: must be a 1-D array, got shape {a.shape}")
    return a


def check_record(
    time: Any, command: Any, measured: Any, force: Any | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, float]:
    """Validate a record for the diagnosis; return ``(t, command, measured, force, fs)``.

    Raises
    ------
    InputError
        Unequal lengths, non-finite values, non-uniform time, a constant command, or a record
        too short to decide (under :data:`MIN_DURATION_S` or :data:`MIN_CYCLES` cycles of the
        command's equivalent frequency).
    """
    t = _as_array("time", time)
    u = _as_array("command", command)
    y = _as_array("measured", measured)
    f = None if force is None else _as_array("force", force)
    lengths = {"time": len(t), "command": len(u), "measured": len(y)}
    if f is not None:
        lengths["force"] = len(f)
    if len(set(lengths.values())) != 1:
        desc = ", ".join(f"{k} {v}" for k, v in lengths.items())
        raise InputError(f"record columns have different lengths ({desc})")
    for name, a in (("time", t), ("command", u), ("measured", y), ("force", f)):
        if a is None:
            continue
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise InputError(f"{name}: non-finite value at sample {int(bad[0])} ({a[bad[0]]!r})")
    if len(t) < _MIN_SAMPLES:
        raise InputError(
            f"record too short to decide: {len(t)} samples, need at least {_MIN_SAMPLES}"
        )
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise InputError(f"time: not strictly increasing at sample {int(np.argmax(dt <= 0)) + 1}")
    mean_dt = float((t[-1] - t[0]) / (len(t) - 1))
    if np.max(np.abs(dt - mean_dt)) > 1e-3 * mean_dt:
        raise InputError("time: non-uniform sampling")
    fs = 1.0 / mean_dt
    if np.ptp(u) == 0:
        raise InputError("command: constant, nothing to compare the measurement against")
    duration = len(t) / fs
    whole = fei(u, u, fs)
    feq = whole.f_eq if whole.valid else float("nan")
    need = max(MIN_DURATION_S, MIN_CYCLES / feq if feq > 0 else MIN_DURATION_S)
    if duration < need:
        raise InputError(
            f"record too short to decide: {duration:.3g} s, need at least {need:.3g} s "
            f"({MIN_DURATION_S:g} s and {MIN_CYCLES:g} cycles of the command's equivalent "
            f"frequency {feq:.3g} Hz)"
        )
    return t, u, y, f, fs


def _acts(delta: np.ndarray, fs: float, sigma: float, window_s: float) -> dict[str, Any]:
    """Where an effect's contribution ``delta`` exceeds the noise (window RMS > σ)."""
    m = max(round(window_s * fs), 8)
    m = min(m, len(delta))
    ends, ms = moving_ms(delta, m, max(m // 4, 1))
    t_end = ends / fs
    flag = np.sqrt(ms) > sigma
    return {
        "intervals_s": _intervals(t_end - (m - 1) / fs, t_end, flag),
        "fraction": float(flag.mean()) if flag.size else 0.0,
        "window_s": m / fs,
        "rms_m": float(np.sqrt(np.mean(delta * delta))),
        "samples_changed_fraction": float(np.mean(np.abs(delta) > sigma)),
    }


def _step_params(name: str, spec: ModelSpec) -> dict[str, float]:
    """Parameters of step ``name`` as they stand in ``spec``."""
    a = spec.actuator
    if name == "delay":
        return {"delay": float(a.delay)}
    if name == "gain":
        return {"gain": float(a.gain)}
    for e in a.effects:
        if e.kind == name:
            return {k: float(v) for k, v in e.params.items()}
    return {}


@dataclass
class _Item:
    """A named effect or re-fit while the search runs."""

    name: str
    k: int
    delta_bic: float
    alternatives: list[str]
    table: list[dict[str, Any]]


def _without(spec: ModelSpec, base: ModelSpec, name: str) -> ModelSpec:
    """``spec`` without the named effect (or with the re-fitted delay/gain set back to base)."""
    out = copy.deepcopy(spec)
    a = out.actuator
    if name == "delay":
        a.delay = base.actuator.delay
    elif name == "gain":
        a.gain = base.actuator.gain
    else:
        if name == "time_varying_delay":  # give its mean delay back to the actuator
            for e in a.effects:
                if e.kind == name:
                    a.delay += e.params["delay"]
        a.effects = [e for e in a.effects if e.kind != name]
    return out


@dataclass(eq=False)
class _Search:
    """Forward selection with BIC, its first choice revisited, then a swap/drop pass."""

    #: Candidates verified by an exact joint re-fit (fitted base, or effects already named).
    VERIFY = 3
    #: Alternative first choices explored when two or more effects are named.
    BEAM = 3

    base: ModelSpec
    data: Data
    exact: Data
    candidates: tuple[str, ...]
    threshold: float
    tie_margin: float
    max_effects: int
    fitted_base: bool
    history: list[dict[str, Any]] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self.n = self.data.n

    # -- pieces -----------------------------------------------------------------------------
    def polish(self, spec: ModelSpec, items: list[_Item]) -> tuple[ModelSpec, np.ndarray, float]:
        """Joint re-fit of the named effects (and of delay/gain for a fitted base), exact RSS."""
        added = {it.name for it in items}
        idx = [i for i, e in enumerate(spec.actuator.effects) if e.kind in added]
        if self.fitted_base or len(idx) >= 2:
            return polish(spec, self.exact, idx, actuator=self.fitted_base)
        pred = Model(spec, self.exact).pred
        return spec, pred, _rss(self.exact, pred)

    def rss(self, spec: ModelSpec) -> float:
        """Exact RSS of ``spec``."""
        return _rss(self.exact, Model(spec, self.exact).pred)

    def total_bic(self, spec: ModelSpec, items: list[_Item]) -> float:
        """``N ln(RSS/N) + Σk ln N`` of a path."""
        rss = max(self.rss(spec), 1e-300)
        return self.n * math.log(rss / self.n) + sum(it.k for it in items) * math.log(self.n)

    def screen(
        self, spec: ModelSpec, items: list[_Item]
    ) -> tuple[list[tuple[float, Fit]], list[dict[str, Any]], Fit | None, float, list[str]]:
        """Fit every candidate on ``spec``; return (fits with ΔBIC, table, pick, its ΔBIC,
        indistinguishable alternatives). With a fitted base, or once effects are named, the
        best few are verified by an exact joint re-fit (with the named effects, and the delay
        and gain of a fitted base), and only those can be picked."""
        current = Model(spec, self.data)
        rss0 = _rss(self.data, current.pred)
        fits: list[tuple[float, Fit]] = []
        entries: dict[int, dict[str, Any]] = {}
        table: list[dict[str, Any]] = []
        for name in self.candidates:
            res = fit_candidate(name, current, self.data)
            if isinstance(res, Candidate):
                table.append({"name": name, "skipped": res.reason})
                continue
            db = delta_bic(self.n, rss0, res.rss, res.k)
            fits.append((db, res))
            entry: dict[str, Any] = {
                "name": name,
                "delta_bic": db,
                "k": res.k,
                "parameters": res.params,
            }
            if res.note:
                entry["note"] = res.note
            entries[id(res)] = entry
            table.append(entry)
        if not fits:
            return fits, table, None, -math.inf, []
        pool = fits
        if self.data.project or items:
            rss_exact = self.rss(spec)
            top = sorted(fits, key=lambda p: -p[0])[: self.VERIFY]
            pool = []
            for _, ft in top:
                new_item = _Item(ft.name, ft.k, 0.0, [], [])
                sp, pred, rss = self.polish(ft.spec, [*items, new_item])
                ft.spec, ft.pred, ft.rss = sp, pred, rss
                ft.params = _step_params(ft.name, sp)
                db = delta_bic(self.n, rss_exact, rss, ft.k)
                entries[id(ft)].update(delta_bic=db, parameters=ft.params, verified=True)
                pool.append((db, ft))
            fits = [(entries[id(ft)]["delta_bic"], ft) for _, ft in fits]
        table.sort(key=lambda e: -e.get("delta_bic", -math.inf))
        best_db = max(db for db, _ in pool)
        tied = [ft for db, ft in pool if db >= best_db - self.tie_margin]
        order = {c: i for i, c in enumerate(CANDIDATES)}
        pick = min(tied, key=lambda ft: order[ft.name])
        pick_db = next(db for db, ft in pool if ft is pick)
        return pool, table, pick, pick_db, [ft.name for ft in tied if ft is not pick]

    # -- searches ---------------------------------------------------------------------------
    def forward(
        self, spec: ModelSpec, items: list[_Item], record: bool = True
    ) -> tuple[ModelSpec, list[_Item], dict[str, Any], list[tuple[float, Fit]]]:
        """Greedy forward selection from ``spec``; returns (spec, items, stop, first fits)."""
        items = list(items)
        first: list[tuple[float, Fit]] = []
        while True:
            if len(items) >= self.max_effects:
                return spec, items, {"reason": f"max_effects ({self.max_effects}) reached"}, first
            fits, table, pick, pick_db, alternatives = self.screen(spec, items)
            if not first:
                first = fits
            if pick is None:
                return spec, items, {"reason": "no candidate could be fitted"}, first
            if not pick_db > self.threshold:
                best_db, best = max(fits, key=lambda p: p[0])
                stop = {
                    "reason": "no significant candidate",
                    "best": best.name,
                    "delta_bic": best_db,
                    "threshold": self.threshold,
                }
                return spec, items, stop, first
            items.append(_Item(pick.name, pick.k, pick_db, alternatives, table))
            if record:
                self.history.append(
                    {
                        "action": "named",
                        "name": pick.name,
                        "delta_bic": pick_db,
                        "alternatives": alternatives,
                        "parameters": pick.params,
                    }
                )
            log.info("named %s %s (ΔBIC %.1f)", pick.name, pick.params, pick_db)
            spec, _, _ = self.polish(pick.spec, items)

    def run(self, refine: bool) -> tuple[ModelSpec, list[_Item], dict[str, Any]]:
        """The whole search."""
        spec, items, stop, first = self.forward(self.base, [])
        if not refine or len(items) < 2:
            return spec, items, stop
        # revisit the first choice: rerun the forward selection from the next best first
        # candidates and keep the path with the lowest total BIC
        best = self.total_bic(spec, items)
        ranked = sorted(first, key=lambda p: -p[0])
        # an alternative first choice is worth a path only if its deficit at the first step is
        # smaller than what the later steps of the chosen path explained
        room = sum(it.delta_bic for it in items[1:])
        for db, ft in ranked[1 : self.BEAM]:
            if not db > self.threshold or ft.name == items[0].name:
                continue
            if items[0].delta_bic - db >= room:
                continue
            it0 = _Item(ft.name, ft.k, db, [], [])
            s0, _, _ = self.polish(ft.spec, [it0])
            s1, items1, stop1, _ = self.forward(s0, [it0], record=False)
            total = self.total_bic(s1, items1)
            if total < best - self.tie_margin:
                self.history.append(
                    {
                        "action": "revisited first choice",
                        "from": [it.name for it in items],
                        "to": [it.name for it in items1],
                        "bic_gain": best - total,
                    }
                )
                it0.table = items[0].table
                spec, items, stop, best = s1, items1, stop1, total
        names = [it.name for it in items]
        spec = self.swap_drop(spec, items)
        if [it.name for it in items] != names:  # something changed: anything left to name?
            spec, items, stop, _ = self.forward(spec, items)
        return spec, items, stop

    def swap_drop(self, spec: ModelSpec, items: list[_Item]) -> ModelSpec:
        """Re-examine each named item with the others in the model (in place on ``items``)."""
        for _ in range(2):
            changed = False
            for it in list(items):
                if it not in items:
                    continue
                others = [x for x in items if x is not it]
                minus = _without(spec, self.base, it.name)
                fits, table, pick, pick_db, alternatives = self.screen(minus, others)
                orig = next((db for db, ft in fits if ft.name == it.name), -math.inf)
                if pick is None or not pick_db > self.threshold:
                    items.remove(it)
                    spec, _, _ = self.polish(minus, others)
                    self.history.append({"action": "dropped", "name": it.name, "delta_bic": orig})
                    changed = True
                elif pick.name != it.name and pick_db > orig + self.tie_margin:
                    new = _Item(pick.name, pick.k, pick_db, alternatives, table)
                    items[items.index(it)] = new
                    spec, _, _ = self.polish(pick.spec, [*others, new])
                    self.history.append(
                        {
                            "action": "replaced",
                            "name": it.name,
                            "by": pick.name,
                            "delta_bic": pick_db,
                            "delta_bic_replaced": orig,
                        }
                    )
                    changed = True
                else:
                    refit = next((ft for _, ft in fits if ft.name == it.name), None)
                    it.table, it.alternatives = table, alternatives
                    if refit is not None and self.rss(refit.spec) < self.rss(spec):
                        spec, _, _ = self.polish(refit.spec, items)
            if not changed:
                break
        return spec


def _progressive(
    final: ModelSpec, base: ModelSpec, names: list[str], k: int, fitted_base: bool
) -> ModelSpec:
    """The final model restricted to the base and the first ``k`` named items."""
    inc = set(names[:k])
    out = copy.deepcopy(final)
    a, b = out.actuator, base.actuator
    base_kinds = {e.kind for e in b.effects}
    a.effects = [e for e in a.effects if e.kind in base_kinds or e.kind in inc]
    if not (fitted_base and k >= 1):
        if not ({"delay", "time_varying_delay"} & inc):
            a.delay = b.delay
        if "gain" not in inc:
            a.gain = b.gain
    return out


def diagnose(
    time: Any,
    command: Any,
    measured: Any,
    force: Any | None = None,
    model: ModelSpec | None = None,
    max_effects: int = 3,
    threshold: float = DEFAULT_THRESHOLD,
    tie_margin: float = DEFAULT_TIE_MARGIN,
    candidates: tuple[str, ...] = CANDIDATES,
    refine: bool = True,
) -> Diagnosis:
    """Find where the model and the measurement disagree, name the missing effects, add them.

    Parameters
    ----------
    time, command, measured : array_like
        The record: sample times (s, uniform), command sent to the actuator (m), measured
        displacement (m).
    force : array_like, optional
        Measured specimen force (N): localisation by force and the ``force_feedback``
        candidate's specimen.
    model : ModelSpec, optional
        The base model (a model file, :func:`rths_hil.sim_backends.modelfile.load_model`).
        Default: a delay + gain model fitted to the record (:func:`rths_hil.estimation.calibrate`,
        no offset, so that an offset stays a candidate); its delay and gain are then nuisance
        parameters, re-fitted with every candidate.
    max_effects : int
        Stop after this many named effects.
    threshold : float
        Significance threshold on the BIC improvement.
    tie_margin : float
        Candidates within this BIC margin of the best are reported as indistinguishable.
    candidates : tuple of str
        Candidates to try (default: all of :data:`CANDIDATES`).
    refine : bool
        With two or more named effects, re-examine each with the others in the model (swap it
        for a better candidate, or drop it when no longer significant).

    Returns
    -------
    Diagnosis
    """
    t_start = _time.perf_counter()
    t, u, y, f, fs = check_record(time, command, measured, force)
    if isinstance(max_effects, bool) or int(max_effects) != max_effects or max_effects < 0:
        raise InputError(f"max_effects: must be an integer ≥ 0, got {max_effects!r}")
    if not (math.isfinite(threshold) and threshold >= 0):
        raise InputError(f"threshold: must be a finite number ≥ 0, got {threshold!r}")
    if not (math.isfinite(tie_margin) and tie_margin >= 0):
        raise InputError(f"tie_margin: must be a finite number ≥ 0, got {tie_margin!r}")
    unknown = [c for c in candidates if c not in CANDIDATES]
    if unknown:
        raise InputError(f"unknown candidate {unknown[0]!r} (known: {', '.join(CANDIDATES)})")
    candidates = tuple(candidates)
    notes: list[str] = []
    fitted_base = model is None
    if model is None:
        base = calibrate(t, u, y, fit_offset=False)
        base.source = "fitted to the record (delay + gain)"
    else:
        base = model
    source = base.source
    data = Data(u, y, fs, f, project=fitted_base)
    base_model = Model(base, data)
    data.specimen = specimen_from_record(data, base)
    if data.specimen is None:
        notes.append("force_feedback not tried: needs a force column or a [specimen] table")
    else:
        k_s, c_s, src = data.specimen
        notes.append(f"specimen for force_feedback: k = {k_s:.4g} N/m, c = {c_s:.4g} N·s/m ({src})")
    exact = Data(u, y, fs, f)
    search = _Search(base, data, exact, candidates, threshold, tie_margin, max_effects, fitted_base)
    spec, items, stop = search.run(refine)
    history = search.history
    # the final model and each step's gap, localisation and significance in it
    data_exact = exact
    final = Model(spec, data_exact)
    names = [it.name for it in items]
    specs = [_progressive(spec, base, names, k, fitted_base) for k in range(len(items))]
    if fitted_base:  # the delay and gain that suit each intermediate model
        specs[1:] = [polish(sp, exact, [], actuator=True)[0] for sp in specs[1:]]
    preds = [Model(sp, data_exact).pred for sp in specs] + [final.pred]
    preds[0] = base_model.pred
    before = Gap.of(y, preds[0], fs)
    base_loc = localise(u, y, preds[0], fs, f)
    sigma0 = base_loc.noise
    n = data.n
    steps: list[Step] = []
    loc = base_loc
    for k, it in enumerate(items):
        if k:
            loc = localise(u, y, preds[k], fs, f, noise=None)
        r0 = y - preds[k]
        r1 = y - preds[k + 1]
        rss0, rss1 = float(r0 @ r0), float(r1 @ r1)
        db = delta_bic(n, rss0, rss1, it.k)
        where = loc.to_json()
        where["acts"] = _acts(preds[k + 1] - preds[k], fs, sigma0, loc.when["window_s"])
        spec_k = specs[k + 1] if k + 1 < len(specs) else spec
        steps.append(
            Step(
                name=it.name,
                params=_step_params(it.name, spec),
                delta_bic=db,
                alternatives=it.alternatives,
                candidates=it.table,
                where=where,
                before=Gap.of(y, preds[k], fs),
                after=Gap.of(y, preds[k + 1], fs),
                spec=spec_k,
                pred=preds[k + 1],
                localisation=loc,
            )
        )
    after = Gap.of(y, final.pred, fs)
    final_loc = localise(u, y, final.pred, fs, f) if steps else base_loc
    runtime = _time.perf_counter() - t_start
    return Diagnosis(
        base=base,
        model=spec,
        base_source=source,
        steps=steps,
        stop=stop,
        before=before,
        after=after,
        base_pred=preds[0],
        pred=final.pred,
        base_localisation=base_loc,
        final=final_loc,
        time=t,
        command=u,
        measured=y,
        force=f,
        fs=fs,
        threshold=threshold,
        tie_margin=tie_margin,
        runtime_s=runtime,
        notes=notes,
        history=history,
    )

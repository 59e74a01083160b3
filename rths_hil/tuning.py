"""Tuning of the inverse compensation from short trial tests.

Inverse compensation (Chen & Ricles 2009; :mod:`rths_hil.compensators.inverse`) sends
``x_c[k] = a·(α·x_t[k] − (α − 1)·x_t[k−1])``. It is the backward-Euler inverse of a first-order
actuator lag ``T = (α − 1)·Δt``; for a slowly varying target it leads by ``(α − 1)·Δt``. Too
small an α leaves the actuator lagging (equivalent delay ``d > 0``, the FEI paper's Eq. 2.5), too
large makes it lead (``d < 0``).

Offline tuning (:func:`tune`)
    Run a short trial with the current ``(α, a)``, evaluate the FEI of measured vs target over
    the whole trial (the FEI paper's Eq. 2.1–2.5: amplitude ``A``, equivalent delay ``d``), then
    update::

        α ← α + d/Δt          (a residual delay d asks for d/Δt more steps of lead)
        a ← a / A             (when the amplitude factor is tuned)

    and repeat. The amplitude update also removes the change of the compensator's own gain
    ``|C(α, f_eq)|`` (:func:`compensator_response`) that the new α brings:
    ``a ← a/A · |C(α, f_eq)|/|C(α_new, f_eq)|`` (``a/A`` when α stays). The α update assumes
    the slope ``∂d/∂α = −Δt``; the true slope is ``−Δt/(1 + (ω_eq·(α − 1)·Δt)²)`` to first
    order (the compensator's phase lead is ``atan(ω(α − 1)Δt)``, see
    :func:`compensator_response`), a few % flatter at 0.77 Hz and α ≈ 30, so each iteration
    removes about 98 % of the residual delay. It stops when
    ``|d| ≤ tol_delay`` and ``|A − 1| ≤ tol_amplitude`` (*converged*), or when it stops
    improving, with the reason: the normalised error ``e = max(|d|/tol_delay, |A − 1|/tol_amp)``
    of a trial is not below :data:`IMPROVEMENT` × the best so far (*stalled*; *diverging* when it
    grew), α or ``a`` would leave its bounds (*bound*), the trial's FEI is invalid (*invalid*),
    the delay is in tolerance but ``A`` is not and ``a`` is not tuned (*amplitude*), a trial was
    stopped by a safety rule or the operator (*trip*, *operator_stop*), or the iteration budget
    ran out (*max_iterations*). The recommended parameters are those of the best *verified*
    trial (never an untested update).
Sweep (:func:`sweep`)
    Trials on a grid of α; ``d(α)`` falls through zero at the balanced α, found by linear
    interpolation between the two grid points that bracket the sign change
    (:func:`zero_crossing`); the amplitude factor recommended there is ``a / A(α₀)`` with ``A``
    interpolated the same way.
Trials (:class:`LoopTrials`)
    Each trial is a run of the real-time loop (:class:`rths_hil.hybrid.RTHSLoop`) with the
    trial's α and ``a``, adaptive compensation off, for ``duration`` seconds of the record:
    in lockstep against the configured twin (online evaluators off for speed: the trial is
    evaluated offline over its whole length, and nothing is at risk), or — only after the
    caller has obtained the operator's confirmation — paced against the real controller with
    the ground motion scaled down by ``scale`` and every safety rule of the configuration on.

Theory helpers
    :func:`compensator_response` (the FIR's frequency response), :func:`residual_delay` and
    :func:`balanced_alpha` predict ``d(α)`` and the zero crossing for an actuator of known
    phase lag, in closed form; the tests compare the sweep with them.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol, overload

import numpy as np

from .config import Config, set_compensation
from .errors import InputError
from .fei import fei
from .metrics import j1_delay, j2_nrms

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_HARDWARE_SCALE",
    "DEFAULT_TRIAL_DURATION",
    "IMPROVEMENT",
    "LoopTrials",
    "SweepResult",
    "Trial",
    "TrialRunner",
    "TuneResult",
    "balanced_alpha",
    "compensator_response",
    "evaluate_trial",
    "residual_delay",
    "sweep",
    "tune",
    "zero_crossing",
]

#: Default trial length (s): covers the strong-motion phase of the bundled records.
DEFAULT_TRIAL_DURATION = 15.0
#: Default amplitude of hardware trials, as a fraction of the configured PGA.
DEFAULT_HARDWARE_SCALE = 0.25
#: A trial must bring the normalised error below this fraction of the best one so far.
IMPROVEMENT = 0.8
#: Bounds on the amplitude factor the tuner may propose (a larger correction points at a
#: calibration problem, not at tuning).
FACTOR_BOUNDS = (0.5, 2.0)


# ----------------------------------------------------------------------------------------------
# closed forms


@overload
def compensator_response(alpha: float, f: float, dt: float) -> complex: ...
@overload
def compensator_response(alpha: float, f: np.ndarray, dt: float) -> np.ndarray: ...
def compensator_response(alpha: float, f: float | np.ndarray, dt: float) -> np.ndarray | complex:
    """Frequency response ``C = α − (α − 1)·e^{−jωΔt}`` of the inverse compensator.

    Its phase, ``atan2((α−1)·sin ωΔt, α − (α−1)·cos ωΔt) ≈ atan(ω(α−1)Δt)``, is the lead the
    compensator gives at frequency ``f`` (Hz); its magnitude ``≈ sqrt(1 + (ω(α−1)Δt)²)`` is the
    amplification that comes with it (Chen & Ricles 2009).
    """
    w = 2.0 * math.pi * np.asarray(f, dtype=float) * dt
    return alpha - (alpha - 1.0) * np.exp(-1j * w)


def residual_delay(alpha: float, f: float, dt: float, plant_lag: float) -> float:
    """Equivalent delay (s, the FEI paper's Eq. 2.5) of compensator + actuator at frequency ``f``.

    ``plant_lag`` is the actuator's phase lag (rad, > 0 for a lagging actuator) at ``f``:
    ``d = (plant_lag − angle C(α, f)) / (2π f)``.
    """
    lead = float(np.angle(compensator_response(alpha, f, dt)))
    return (plant_lag - lead) / (2.0 * math.pi * f)


def balanced_alpha(plant_lag: float, f: float, dt: float) -> float:
    """The α whose compensator lead equals the actuator's phase lag ``plant_lag`` (rad) at ``f``.

    Closed form of ``angle C(α, f) = φ``: with ``θ = 2π f Δt`` and ``β = α − 1``,
    ``tan φ·(1 + β(1 − cos θ)) = β sin θ``, so ``β = tan φ / (sin θ − tan φ·(1 − cos θ))``.
    For a pure delay τ (``φ = 2π f τ``) this is ``1 + tan(ωτ)/ω/Δt`` to first order in θ —
    slightly above the naive ``1 + τ/Δt``.
    """
    theta = 2.0 * math.pi * f * dt
    t = math.tan(plant_lag)
    den = math.sin(theta) - t * (1.0 - math.cos(theta))
    if not (0.0 <= plant_lag < math.pi / 2) or den <= 0:
        raise InputError(f"no α balances a phase lag of {plant_lag:g} rad at {f:g} Hz")
    return 1.0 + t / den


# ----------------------------------------------------------------------------------------------
# trials


@dataclass
class Trial:
    """One trial test and its evaluation.

    Attributes
    ----------
    index : int
        1-based number of the trial in its tuning run or sweep.
    alpha : float
        α used (steps).
    factor : float
        Amplitude factor ``a`` used.
    amplitude : float
        FEI amplitude A of measured vs target over the trial (the FEI paper's Eq. 2.2).
    delay : float
        FEI equivalent delay d (s, the FEI paper's Eq. 2.5), > 0 when measured lags.
    f_eq : float
        Equivalent frequency (Hz, the FEI paper's Eq. 2.4).
    valid : bool
        The FEI is valid (the target moved).
    j1 : float
        J1, cross-correlation delay (s).
    j2 : float
        J2, normalised RMS tracking error (%).
    status : str
        ``completed``, ``trip`` or ``operator_stop`` (the loop's status).
    steps : int
        Steps run.
    pga : float
        Peak ground acceleration of the trial (m/s²).
    reason : str
        Why the loop stopped early ('' when completed).
    run_dir : str
        The trial's run directory ('' for trials not run through the loop).
    """

    index: int
    alpha: float
    factor: float
    amplitude: float
    delay: float
    f_eq: float
    valid: bool
    j1: float = math.nan
    j2: float = math.nan
    status: str = "completed"
    steps: int = 0
    pga: float = math.nan
    reason: str = ""
    run_dir: str = ""

    def error(self, tol_delay: float, tol_amplitude: float, amplitude: bool = True) -> float:
        """Normalised error ``max(|d|/tol_delay, |A − 1|/tol_amplitude)`` (delay only if not
        ``amplitude``); ``inf`` for an invalid or stopped trial."""
        if not self.valid or self.status != "completed":
            return math.inf
        e = abs(self.delay) / tol_delay
        if amplitude:
            e = max(e, abs(self.amplitude - 1.0) / tol_amplitude)
        return e

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (SI units)."""
        return asdict(self)


class TrialRunner(Protocol):
    """Runs one trial with α and amplitude factor; ``index`` numbers it (1-based)."""

    def __call__(self, alpha: float, factor: float, index: int) -> Trial: ...


def evaluate_trial(
    target: np.ndarray, measured: np.ndarray, fs: float
) -> tuple[float, float, float, bool, float, float]:
    """FEI (the FEI paper's Eq. 2.1–2.5), J1 and J2 of one trial.

    Returns
    -------
    amplitude, delay, f_eq, valid, j1, j2
        A, d (s), f_eq (Hz), validity, J1 (s), J2 (%). NaN when there are fewer than 8
        samples or the target did not move.
    """
    x = np.asarray(target, dtype=float)
    y = np.asarray(measured, dtype=float)
    if x.size < 8:
        return math.nan, math.nan, math.nan, False, math.nan, math.nan
    r = fei(x, y, fs)
    if not r.valid:
        return math.nan, math.nan, math.nan, False, math.nan, math.nan
    return (
        r.amplitude,
        r.delay,
        r.f_eq,
        True,
        float(j1_delay(x, y, fs)),
        float(j2_nrms(x, y)),
    )


def _record_pga(cfg: Config) -> float:
    """PGA (m/s²) the configuration's record is run at."""
    from .hybrid import build_ground_motion

    g = cfg["ground_motion"]
    if g["pga"] > 0:
        return float(g["pga"])
    return float(build_ground_motion(cfg).pga)


class LoopTrials:
    """Trials through the real-time loop, in lockstep on the twin or paced on hardware.

    Parameters
    ----------
    cfg : Config
        The test's configuration. Its compensation α and amplitude are replaced per trial;
        adaptive compensation is switched off.
    out_dir : str or Path
        Each trial's run directory is ``out_dir/<prefix>-NN``.
    duration : float
        Seconds of the record per trial (0 = ``loop.duration``).
    scale : float
        Ground-motion scale of the trials (0 < scale ≤ 1), applied to the configured PGA.
    mode : {"lockstep", "paced"}, optional
        Default: lockstep on a twin, paced on hardware (a real actuator runs in real time).
    fast : bool, optional
        Switch the online FEI and Kalman evaluators (and their safety rules) off during trials.
        Default: on a twin yes (the trial is evaluated offline; nothing is at risk), on
        hardware no.
    plant : Plant, optional
        Plant for the twin (tests); default built from ``[twin]``.
    prefix : str
        Run directory prefix (``trial``, ``sweep``).
    on_trial : callable, optional
        Called with each finished :class:`Trial`.

    Notes
    -----
    Hardware trials (``twin.enabled = false``) drive a real actuator: the caller must have the
    operator's explicit confirmation before calling. ``rths-hil tune`` asks for it.
    """

    def __init__(
        self,
        cfg: Config,
        out_dir: str | Path,
        duration: float = DEFAULT_TRIAL_DURATION,
        scale: float = 1.0,
        mode: str | None = None,
        fast: bool | None = None,
        plant: Any = None,
        prefix: str = "trial",
        on_trial: Callable[[Trial], None] | None = None,
    ) -> None:
        if not (math.isfinite(duration) and duration >= 0):
            raise InputError(f"trial duration must be ≥ 0 s, got {duration!r}")
        if not (math.isfinite(scale) and 0 < scale <= 1):
            raise InputError(f"trial amplitude scale must be in (0, 1], got {scale!r}")
        self.cfg = cfg
        self.hardware = not cfg["twin"]["enabled"]
        self.mode = mode or ("paced" if self.hardware else "lockstep")
        if self.mode not in ("paced", "lockstep"):
            raise InputError(f"trial mode must be 'paced' or 'lockstep', got {self.mode!r}")
        self.fast = (not self.hardware) if fast is None else bool(fast)
        self.duration = float(duration) or float(cfg["loop"]["duration"])
        self.scale = float(scale)
        self.out_dir = Path(out_dir)
        self.plant = plant
        self.prefix = prefix
        self.on_trial = on_trial
        self.fs = float(cfg["loop"]["fs"])
        self.dt = 1.0 / self.fs
        self.pga = _record_pga(cfg) * self.scale

    def config_for(self, alpha: float, factor: float) -> Config:
        """The configuration of a trial with α and amplitude factor."""
        cfg = copy.deepcopy(self.cfg)
        c = cfg["compensation"]
        c["enabled"] = True
        c["method"] = "inverse"
        set_compensation(c, "alpha", alpha, cfg["loop"]["fs"])
        c["amplitude"] = float(factor)
        c["adaptive"] = False
        cfg["loop"]["console"] = 0.0
        cfg["ground_motion"]["pga"] = self.pga
        if self.fast:
            cfg["fei"]["enabled"] = False
            cfg["kalman"]["enabled"] = False
        return cfg

    def __call__(self, alpha: float, factor: float, index: int) -> Trial:
        """Run trial ``index`` with α and amplitude factor; return its evaluation."""
        from .hybrid import RTHSLoop
        from .records.recorder import read_run

        run_dir = self.out_dir / f"{self.prefix}-{index:02d}"
        if (run_dir / "record.npy").exists():
            raise InputError(f"{run_dir} already holds a run: choose a new output directory")
        cfg = self.config_for(alpha, factor)
        loop = RTHSLoop(cfg, run_dir, plant=self.plant, mode=self.mode, duration=self.duration)
        log.info(
            "trial %d: α = %.3f, a = %.4f, %s, %d steps",
            index,
            alpha,
            factor,
            self.mode,
            loop.n_steps,
        )
        res = loop.run()
        rec = read_run(run_dir).record
        a, d, f_eq, valid, j1, j2 = evaluate_trial(rec["target"], rec["measured"], self.fs)
        reason = ""
        if res.trip is not None:
            reason = f"{res.trip.rule}: {res.trip.reason}"
        trial = Trial(
            index=index,
            alpha=float(alpha),
            factor=float(factor),
            amplitude=a,
            delay=d,
            f_eq=f_eq,
            valid=valid,
            j1=j1,
            j2=j2,
            status=res.status,
            steps=res.steps,
            pga=self.pga,
            reason=reason,
            run_dir=str(run_dir),
        )
        if self.on_trial is not None:
            self.on_trial(trial)
        return trial


# ----------------------------------------------------------------------------------------------
# offline tuning


@dataclass
class TuneResult:
    """Outcome of :func:`tune`.

    Attributes
    ----------
    trials : list of Trial
        The trials, in order.
    stop : str
        ``converged``, ``stalled``, ``diverging``, ``bound``, ``invalid``, ``amplitude``,
        ``trip``, ``operator_stop`` or ``max_iterations``.
    reason : str
        One sentence saying why it stopped, with numbers.
    alpha, factor : float
        Recommended α and amplitude factor: those of the best verified trial.
    best : int
        Index (1-based) of that trial, 0 when no trial was usable.
    next_alpha, next_factor : float
        The update the last trial asked for (not verified; NaN when none).
    tol_delay, tol_amplitude : float
        Tolerances used (s, fraction).
    tune_amplitude : bool
        Whether the amplitude factor was tuned.
    """

    trials: list[Trial]
    stop: str
    reason: str
    alpha: float
    factor: float
    best: int
    next_alpha: float = math.nan
    next_factor: float = math.nan
    tol_delay: float = 1e-3
    tol_amplitude: float = 0.01
    tune_amplitude: bool = True

    @property
    def converged(self) -> bool:
        """True when the tolerances were met."""
        return self.stop == "converged"

    @property
    def iterations(self) -> int:
        """Number of trials run."""
        return len(self.trials)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        d = asdict(self)
        d["converged"] = self.converged
        return d


def _gain_ratio(alpha: float, new_alpha: float, f: float, dt: float) -> float:
    """``|C(α, f)| / |C(α', f)|``: how much of A's change the new α itself will cause."""
    if not (math.isfinite(f) and f > 0):
        return 1.0
    return float(
        abs(compensator_response(alpha, f, dt)) / abs(compensator_response(new_alpha, f, dt))
    )


def _ms(x: float) -> str:
    return f"{1e3 * x:+.2f} ms"


def _check_tune_inputs(
    alpha0: float,
    dt: float,
    factor0: float,
    tol_delay: float,
    tol_amplitude: float,
    max_iterations: int,
    alpha_bounds: tuple[float, float],
    factor_bounds: tuple[float, float],
) -> None:
    """Raise InputError for a :func:`tune` argument out of its range."""
    if not (dt > 0 and math.isfinite(dt)):
        raise InputError(f"time step must be > 0 s, got {dt!r}")
    if not (tol_delay > 0 and tol_amplitude > 0):
        raise InputError("tolerances must be > 0")
    if int(max_iterations) < 1:
        raise InputError(f"max iterations must be ≥ 1, got {max_iterations!r}")
    lo, hi = alpha_bounds
    if not (1.0 <= lo <= alpha0 <= hi):
        raise InputError(f"starting α = {alpha0:g} is outside its bounds [{lo:g}, {hi:g}]")
    flo, fhi = factor_bounds
    if not (flo <= factor0 <= fhi):
        raise InputError(
            f"starting amplitude factor {factor0:g} is outside its bounds [{flo:g}, {fhi:g}]"
        )


def tune(
    run_trial: TrialRunner,
    alpha0: float,
    dt: float,
    factor0: float = 1.0,
    tol_delay: float = 1e-3,
    tol_amplitude: float = 0.01,
    max_iterations: int = 6,
    tune_amplitude: bool = True,
    alpha_bounds: tuple[float, float] = (1.0, 100.0),
    factor_bounds: tuple[float, float] = FACTOR_BOUNDS,
) -> TuneResult:
    """Tune α (and the amplitude factor) from trial tests (see the module docstring).

    Parameters
    ----------
    run_trial : TrialRunner
        Runs one trial (e.g. :class:`LoopTrials`).
    alpha0 : float
        Starting α (steps, ≥ 1).
    dt : float
        Loop step Δt (s) of the compensator.
    factor0 : float
        Starting amplitude factor.
    tol_delay : float
        Tolerance on |d| (s).
    tol_amplitude : float
        Tolerance on |A − 1|.
    max_iterations : int
        Largest number of trials.
    tune_amplitude : bool
        Update the amplitude factor (``a ← a/A``) as well as α.
    alpha_bounds, factor_bounds : (float, float)
        Allowed ranges; an update outside is clipped, and a clipped update that would repeat
        the trial stops the tuning (*bound*).

    Returns
    -------
    TuneResult
    """
    _check_tune_inputs(
        alpha0, dt, factor0, tol_delay, tol_amplitude, max_iterations, alpha_bounds, factor_bounds
    )
    lo, hi = alpha_bounds
    flo, fhi = factor_bounds
    trials: list[Trial] = []
    errors: list[float] = []
    alpha, factor = float(alpha0), float(factor0)
    stop, reason = "max_iterations", ""
    next_alpha = next_factor = math.nan
    for i in range(1, int(max_iterations) + 1):
        tr = run_trial(alpha, factor, i)
        trials.append(tr)
        e = tr.error(tol_delay, tol_amplitude, tune_amplitude)
        errors.append(e)
        if tr.status != "completed":
            stop = "operator_stop" if tr.status == "operator_stop" else "trip"
            reason = f"trial {i} (α = {alpha:.2f}) was stopped: {tr.reason or tr.status}"
            break
        if not tr.valid:
            stop = "invalid"
            reason = (
                f"trial {i} (α = {alpha:.2f}): the FEI is invalid (the target hardly moved); "
                "lengthen the trial or raise its amplitude"
            )
            break
        d_ok = abs(tr.delay) <= tol_delay
        a_ok = abs(tr.amplitude - 1.0) <= tol_amplitude
        if d_ok and a_ok:
            stop = "converged"
            reason = (
                f"converged at trial {i}: d = {_ms(tr.delay)} (|d| ≤ {1e3 * tol_delay:g} ms), "
                f"A = {tr.amplitude:.4f} (|A − 1| ≤ {100 * tol_amplitude:g} %)"
            )
            break
        if d_ok and not tune_amplitude:
            stop = "amplitude"
            reason = (
                f"trial {i}: d = {_ms(tr.delay)} is within tolerance but A = {tr.amplitude:.4f} "
                "is not, and the amplitude factor is not tuned (α does not fix A)"
            )
            break
        if i > 1:
            before = min(errors[:-1])
            if e > IMPROVEMENT * before:
                grew = e > errors[-2]
                stop = "diverging" if grew else "stalled"
                reason = (
                    f"{'diverging' if grew else 'stopped improving'} at trial {i}: error "
                    f"{e:.2f}× the tolerance (d = {_ms(tr.delay)}, A = {tr.amplitude:.4f}) vs "
                    f"{before:.2f}× before; the residual is not one the update removes "
                    "(noise, nonlinearity, or an actuator far from a delay or lag)"
                )
                break
        # the update: α ← α + d/Δt, a ← a/A
        na = alpha + tr.delay / dt
        nf = factor
        if tune_amplitude:
            nf = factor / tr.amplitude * _gain_ratio(alpha, min(max(na, lo), hi), tr.f_eq, dt)
        next_alpha, next_factor = na, nf
        ca = min(max(na, lo), hi)
        cf = min(max(nf, flo), fhi)
        if (ca != na and ca == alpha) or (cf != nf and cf == factor):
            stop = "bound"
            which = (
                f"α = {na:.2f} outside [{lo:g}, {hi:g}]"
                if ca != na
                else f"an amplitude factor of {nf:.4f}, outside [{flo:g}, {fhi:g}]"
            )
            reason = f"trial {i} asks for {which}, and the trial was already at the bound"
            break
        alpha, factor = ca, cf
        if i == int(max_iterations):
            reason = (
                f"not converged after {i} trials: last d = {_ms(tr.delay)}, "
                f"A = {tr.amplitude:.4f}; next α would be {na:.2f}"
            )
    usable = [k for k, e in enumerate(errors) if math.isfinite(e)]
    if usable:
        b = trials[min(usable, key=lambda k: errors[k])]
        rec_alpha, rec_factor, best = b.alpha, b.factor, b.index
    else:
        rec_alpha, rec_factor, best = float(alpha0), float(factor0), 0
    return TuneResult(
        trials=trials,
        stop=stop,
        reason=reason,
        alpha=rec_alpha,
        factor=rec_factor,
        best=best,
        next_alpha=next_alpha,
        next_factor=next_factor,
        tol_delay=tol_delay,
        tol_amplitude=tol_amplitude,
        tune_amplitude=tune_amplitude,
    )


# ----------------------------------------------------------------------------------------------
# sweep


@dataclass
class SweepResult:
    """Outcome of :func:`sweep`.

    Attributes
    ----------
    trials : list of Trial
        One per grid point, in grid order.
    alpha : float
        Zero crossing of d(α), the recommended α (NaN when d does not change sign).
    amplitude : float
        A interpolated at that α (NaN when none).
    factor : float
        Recommended amplitude factor ``a / A(α₀)`` (the sweep's factor when no crossing).
    reason : str
        How the recommendation was found, or why there is none.
    """

    trials: list[Trial]
    alpha: float
    amplitude: float
    factor: float
    reason: str

    @property
    def found(self) -> bool:
        """True when d(α) crosses zero on the grid."""
        return math.isfinite(self.alpha)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        d = asdict(self)
        d["found"] = self.found
        return d


def zero_crossing(alphas: Sequence[float], delays: Sequence[float]) -> float | None:
    """α where d(α) falls through zero, by linear interpolation between grid points.

    Points with a non-finite delay are skipped. The first crossing from d ≥ 0 to d < 0 in
    increasing α is returned (d decreases with α for an inverse compensator); a grid point with
    d = 0 exactly is returned as is. ``None`` when d does not fall through zero.
    """
    a = np.asarray(alphas, dtype=float)
    d = np.asarray(delays, dtype=float)
    if a.shape != d.shape:
        raise InputError("alphas and delays must have the same length")
    ok = np.isfinite(a) & np.isfinite(d)
    a, d = a[ok], d[ok]
    order = np.argsort(a, kind="stable")
    a, d = a[order], d[order]
    for k in range(a.size):
        if d[k] == 0.0:
            return float(a[k])
        if k + 1 < a.size and d[k] > 0.0 > d[k + 1]:
            return float(a[k] + d[k] * (a[k + 1] - a[k]) / (d[k] - d[k + 1]))
    return None


def sweep(
    run_trial: TrialRunner,
    alphas: Sequence[float],
    factor: float = 1.0,
    stop_on_trip: bool = False,
) -> SweepResult:
    """Trials on a grid of α; the zero crossing of d(α) is the recommended α.

    Parameters
    ----------
    run_trial : TrialRunner
        Runs one trial.
    alphas : sequence of float
        The grid (each ≥ 1).
    factor : float
        Amplitude factor of every trial.
    stop_on_trip : bool
        Stop the sweep at the first trial a safety rule stopped (hardware); otherwise the
        trial is left out of the interpolation and the sweep goes on.

    Returns
    -------
    SweepResult
    """
    grid = [float(a) for a in alphas]
    if not grid:
        raise InputError("the sweep grid is empty")
    bad = [a for a in grid if not (math.isfinite(a) and a >= 1.0)]
    if bad:
        raise InputError(f"sweep: α must be ≥ 1, got {bad[0]:g}")
    trials: list[Trial] = []
    note = ""
    for i, a in enumerate(grid, 1):
        tr = run_trial(a, factor, i)
        trials.append(tr)
        if tr.status != "completed":
            note = f"; trial {i} (α = {a:g}) was stopped: {tr.reason or tr.status}"
            if stop_on_trip or tr.status == "operator_stop":
                note += ", sweep ended there"
                break
    use = [t for t in trials if t.valid and t.status == "completed"]
    al = [t.alpha for t in use]
    dl = [t.delay for t in use]
    a0 = zero_crossing(al, dl)
    if a0 is None:
        if not use:
            reason = "no usable trial"
        elif all(d > 0 for d in dl):
            reason = (
                f"d > 0 at every α up to {max(al):g} (smallest {_ms(min(dl))}): the balanced α "
                "is above the grid; extend it"
            )
        elif all(d < 0 for d in dl):
            reason = (
                f"d < 0 at every α from {min(al):g} (largest {_ms(max(dl))}): the balanced α "
                "is below the grid; extend it"
            )
        else:
            reason = "d(α) does not fall through zero on the grid"
        return SweepResult(trials, math.nan, math.nan, float(factor), reason + note)
    amp = float(np.interp(a0, al, [t.amplitude for t in use]))
    reason = (
        f"d(α) crosses zero at α = {a0:.2f} (linear interpolation between grid points); "
        f"A there ≈ {amp:.4f}"
    )
    return SweepResult(trials, a0, amp, float(factor) / amp, reason + note)

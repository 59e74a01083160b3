"""The parts every catalogue effect is made of: :class:`Param` and :class:`ParamRange` (a
parameter, its unit, bounds and realistic range), :class:`Fitting` (how the diagnosis fits it),
the :class:`Effect` base class, and :func:`validate_params` against the catalogue
:data:`EFFECTS` (filled by :mod:`rths_hil.sim_backends.effects`)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rths_hil.config.coerce import check_table
from rths_hil.errors import InputError
from rths_hil.keys import REQUIRED, Key

__all__ = ["EFFECTS", "Effect", "Fitting", "Param", "ParamRange", "validate_params"]


@dataclass(frozen=True)
class ParamRange:
    """Realistic range of a parameter's magnitude, for random draws and fitting bounds.

    ``low``/``high`` bound the magnitude; ``signed`` means either sign is realistic;
    ``log`` means draw log-uniformly (ranges spanning a decade or more).
    """

    low: float
    high: float
    signed: bool = False
    log: bool = False
    note: str = ""


@dataclass(frozen=True)
class Param:
    """One parameter of an effect.

    Attributes
    ----------
    name, unit, doc : str
        Name (as in a model file), SI unit, meaning.
    default : float or None
        Default value; ``None`` = required.
    minimum, maximum : float or None
        Bounds checked by :func:`validate_params` (through :meth:`key`); ``exclusive_minimum``
        makes the minimum strict.
    typical : ParamRange or None
        Realistic range (random hidden effects of the diagnosis benchmarks and tests,
        :func:`draw_effect_params`); ``None`` for parameters that are not drawn.
    polish : bool
        Re-fitted by the diagnosis' joint re-fit (:func:`rths_hil.diagnose.candidates.polish`);
        ``False`` for parameters that come from elsewhere (the specimen of ``force_feedback``).
    step : float or None
        Scale of the joint re-fit's steps for a parameter that is not on a log scale (SI);
        ``None``: the magnitude of its start value.
    """

    name: str
    unit: str
    doc: str
    default: float | None = None
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    typical: ParamRange | None = None
    polish: bool = True
    step: float | None = None

    @property
    def log_scale(self) -> bool:
        """A positive scale parameter spanning decades (its realistic range is drawn
        log-uniformly and has one sign): the joint re-fit moves its logarithm."""
        t = self.typical
        return t is not None and t.log and not t.signed

    def key(self, unit: str | None = None) -> Key:
        """The parameter as a configuration :class:`~rths_hil.config.Key`: a float in ``unit``
        (default :attr:`unit`), required without a default, range checked
        (:func:`~rths_hil.config.check_table`)."""
        return Key(
            "float",
            REQUIRED if self.default is None else self.default,
            unit=self.unit if unit is None else unit,
            doc=self.doc,
            lo=self.minimum,
            hi=self.maximum,
            lo_open=self.exclusive_minimum,
        )


@dataclass(frozen=True)
class Fitting:
    """How the discrepancy diagnosis fits an effect as a candidate explanation.

    The fitting methods themselves are in :mod:`rths_hil.diagnose.candidates`; an effect only
    says which one suits it and over what range.

    Attributes
    ----------
    method : {"linear", "scalar", "stops", "modulated_delay"}
        ``linear``: ``y = x + v·regressor(t)``, least squares in closed form; ``scalar``: one
        parameter by a log-spaced grid and bounded Brent between ``low`` and ``high`` (see
        :meth:`Effect.fit_bounds`); ``stops``: one grid + Brent per stop of a saturation;
        ``modulated_delay``: linearised search over the period, then exact least squares.
    param : str
        The parameter fitted (``linear`` and ``scalar``).
    low, high : float
        Default search range of ``param`` (``scalar``; SI).
    needs_specimen : bool
        The fit needs the specimen's stiffness and damping (from the record's force column or
        the model's ``[specimen]``); skipped without them.
    """

    method: str
    param: str = ""
    low: float = 0.0
    high: float = 0.0
    needs_specimen: bool = False


def _positive(
    name: str, unit: str, doc: str, typical: ParamRange, default: float | None = None
) -> Param:
    """A parameter that must be > 0."""
    return Param(
        name, unit, doc, default=default, minimum=0.0, exclusive_minimum=True, typical=typical
    )


class Effect(ABC):
    """Base of every catalogue effect: construct with ``dt`` and parameters, then step/simulate.

    Everything the twin and the diagnosis know about an effect is on its class: ``kind`` (its
    name in model files and reports), ``PARAMS`` (units, bounds, realistic ranges, how the joint
    re-fit treats each), ``CHAIN`` (its place in the physical chain), ``PREFERENCE`` (which
    candidate is named when two explain a record equally well) and ``FIT`` (how the diagnosis
    fits it), plus the hooks below. Register a new effect in :data:`EFFECTS`.
    """

    kind: ClassVar[str]
    PARAMS: ClassVar[tuple[Param, ...]]
    #: Place in the physical chain from the actuator to the transducer (lower = nearer the
    #: actuator): a twin applies its effects, and the diagnosis inserts a new one, in this order.
    CHAIN: ClassVar[int]
    #: Preference between candidates within the tie margin (lower = named first; simpler
    #: effects first).
    PREFERENCE: ClassVar[int]
    #: How the diagnosis fits this effect.
    FIT: ClassVar[Fitting]

    def __init__(self, dt: float, **params: float) -> None:
        if not math.isfinite(float(dt)) or float(dt) <= 0:
            raise InputError(f"dt: must be > 0 s, got {dt!r}")
        self.dt = float(dt)
        self.params = validate_params(self.kind, params)
        self._setup()
        self.reset()

    def _setup(self) -> None:
        """Derive coefficients from :attr:`params` (called once by ``__init__``)."""
        return None

    @classmethod
    def check(cls, params: dict[str, float], where: str) -> None:
        """Cross-parameter checks after each parameter passed its own bounds (none by default)."""
        return None

    # -- what the diagnosis asks (rths_hil.diagnose.candidates) -------------------------------
    @classmethod
    def regressor(cls, t: np.ndarray) -> np.ndarray:
        """``FIT.method == "linear"``: the change of the output per unit of ``FIT.param`` at
        times ``t`` (s)."""
        raise NotImplementedError(f"effect {cls.kind!r} is not linear in a parameter")

    @classmethod
    def fit_bounds(
        cls, x: np.ndarray, fs: float, specimen: tuple[float, float] | None
    ) -> tuple[float, float]:
        """``FIT.method == "scalar"``: search range of ``FIT.param`` for the input ``x`` (m,
        sampled at ``fs`` Hz) of the effect, given the specimen ``(k_s, c_s)`` when known."""
        return cls.FIT.low, cls.FIT.high

    @classmethod
    def fit_fixed(cls, specimen: tuple[float, float] | None) -> dict[str, float]:
        """Parameters held fixed while ``FIT.param`` is fitted (none by default)."""
        return {}

    @classmethod
    def low_frequency(cls, params: dict[str, float]) -> tuple[float, float] | None:
        """Low-frequency equivalent ``(delay in s, gain)`` the effect adds, or ``None`` when it
        adds neither. When the actuator's delay and gain are fitted to the record, the actuator
        gives them back while this effect is fitted."""
        return None

    @classmethod
    def fit_note(cls, params: dict[str, float], x: np.ndarray, fs: float) -> str:
        """Anything worth reporting about a fit with ``params`` on input ``x`` (m, at ``fs``)."""
        return ""

    @classmethod
    def clamp(cls, params: dict[str, float]) -> None:
        """Bring ``params`` back into validity in place, continuously (the joint re-fit moves
        them freely)."""
        return None

    @abstractmethod
    def reset(self) -> None:
        """Return to rest (time zero, zero state)."""

    @abstractmethod
    def step(self, x: float) -> float:
        """Transform one displacement sample (m)."""

    @abstractmethod
    def simulate(self, x: np.ndarray) -> np.ndarray:
        """Transform a whole displacement history from rest (vectorised, equal to stepping)."""

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{type(self).__name__}({args})"


#: The catalogue, by the names the model file and the diagnosis workflow use: kind → class
#: (filled by :mod:`rths_hil.sim_backends.effects`, which defines the effects).
EFFECTS: dict[str, type[Effect]] = {}


def validate_params(
    kind: str,
    params: Mapping[str, Any],
    where: str = "",
    path: str = "",
    *,
    units: Mapping[str, str] | None = None,
) -> dict[str, float]:
    """Check ``params`` against effect ``kind``'s :attr:`Effect.PARAMS`; fill defaults.

    Each parameter is read as its :meth:`Param.key` by :func:`~rths_hil.config.check_table`
    (a number, or a string with a unit; range checked; an unknown name gets the closest known
    one), then the effect's cross-parameter :meth:`Effect.check` runs.

    Parameters
    ----------
    kind : str
        The effect (a key of :data:`EFFECTS`).
    params : mapping
        Parameter name → value (SI, or a string with a unit).
    where : str
        The source, first in every message (``twin.toml``); empty for none.
    path : str
        The parameters' table (``actuator.effects[1]``); empty for none.
    units : mapping of str to str, optional
        A parameter's unit where it differs from :attr:`Param.unit` (the force-controlled
        twin's ``offset`` in N).

    Returns
    -------
    dict of str to float
        Every parameter of the effect, in SI units.

    Raises
    ------
    InputError
        ``where: path.name: what is wrong`` (an unknown effect, an unknown, missing or out of
        range parameter).
    """
    pre = f"{where}: " if where else ""
    dot = f"{path}." if path else ""
    if kind not in EFFECTS:
        raise InputError(f"{pre}{dot}kind: unknown effect {kind!r} (known: {', '.join(EFFECTS)})")
    units = units or {}
    keys = {p.name: p.key(units.get(p.name)) for p in EFFECTS[kind].PARAMS}
    given = {k: v.item() if isinstance(v, np.generic) else v for k, v in params.items()}
    out = check_table(given, keys, where, path, missing=f"required by effect {kind!r}")
    EFFECTS[kind].check(out, f"{pre}{dot}")
    return out

"""The real-time hybrid simulation loop: plan (config → stages), channels, runner, record.

``from rths_hil.hybrid import RTHSLoop, run`` is the loop's entry point (the documented one for
scripts is :func:`rths_hil.run`, ``docs/api.md``). Where to look:

``rthsloop.py``
    :class:`RTHSLoop` (a configured test, ready to run) and :func:`run`; the step order and
    the modes in its docstring.
``plan.py``
    configuration → :class:`~rths_hil.hybrid.plan.TestPlan`: structure, one channel per
    actuator, record columns; every validation and "which model / which driver" decision.
``substructure.py``
    the numerical side of the plan: the ground motion, a channel's twin plant, the MDOF model
    and the structure stage (the stages themselves are :mod:`rths_hil.structures`).
``setup.py``
    the experimental setup (OpenFresco's ``ExperimentalSetup``): DOFs ↔ actuators, one
    transformation ``T`` both ways, for the channels and the OpenSees site.
``channel.py``
    one actuator: driver ⇄ twin, compensator, evaluators, safety rules, and its state named
    after the record's columns (``target``, ``command``, ``measured``, ``force`` …).
``runner.py``
    a run: open the channels, arm, the start phase, the loop, the end phase, the result;
    e-stop of all.
``step.py``
    the loop's step in named phases: wait and send → replies → structure → compensate →
    evaluators → safety (one call per phase) → record (by column name) → accounting.
``stepio.py``
    one step's exchange with the controllers (send, collect within the budget, hold what is
    missing), for the loop, the start/end phases and commissioning.
``pacer.py``
    the paced wait (one grid of deadlines, sleep then spin, stall detection) and the reply
    budget.
``phases.py``
    from where the actuators are to step 0 (start ramp), and back to rest at the end.
``evaluators.py``
    streaming and exact online FEI on the step path.
``timing.py``
    the machine's floor and overrun attribution.
``result.py``
    :class:`~rths_hil.hybrid.result.RunResult`, what a run did.

The record's columns, the recorder and the safety rules are :mod:`rths_hil.records` and
:mod:`rths_hil.safety`.

The names below are imported on first use (the submodules import the recorder and the drivers).
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> submodule that defines it
_EXPORTS = {
    "RTHSLoop": "rthsloop",
    "run": "rthsloop",
    "RunResult": "result",
    "Runner": "runner",
    "TestPlan": "plan",
    "build_plan": "plan",
    "build_ground_motion": "substructure",
    "choose_plant": "substructure",
    "new_run_dir": "plan",
    "CAUSES": "timing",
    "MACHINE": "timing",
    "MACHINE_BACKLOG": "timing",
    "MACHINE_IN_WORK": "timing",
    "ON_TIME": "timing",
    "WORK": "timing",
    "WORK_BACKLOG": "timing",
    "attribute_overruns": "timing",
    "count_causes": "timing",
    "paced_floor": "timing",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))

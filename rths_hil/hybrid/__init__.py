"""The hybrid test as stages: plan (config → stages), channels, runner, timing.

Where to look:

``plan.py``
    configuration → :class:`~rths_hil.hybrid.plan.TestPlan`: structure, one channel per
    actuator, record columns; every validation and "which model / which driver" decision.
``structures.py``
    the structure stage interface (SDOF CR stepper, MDOF models, an external site's client).
``channel.py``
    one actuator: driver ⇄ twin, compensator, evaluators, safety rules, its state.
``runner.py``
    the step: send every channel → receive every channel → structure → compensate →
    evaluators → safety (one call per phase) → record (by column name); e-stop of all.
``evaluators.py``
    streaming and exact online FEI on the step path.
``timing.py``
    pacing, the machine's floor and overrun attribution.
"""

"""Studies: the FEI paper's computational study and robustness studies on perturbed twins.

* :mod:`rths_hil.studies.paper` — the FEI paper's Section 4: the window size that holds the
  delay error within tolerance (Fig. 4.2) and the accuracy of A and d (Table 4.1, Fig. 4.6).
* :mod:`rths_hil.studies.robustness` — perturbed twins (:class:`Perturbation`,
  :func:`parse_vary`, :func:`default_perturbations`) run in lockstep through the full chain and
  scored with J1–J9, the whole-record FEI and the MWO extremes (``docs/studies.md``).
* :mod:`rths_hil.studies.executors` — where the cases run: in process, a process pool or a
  Dask cluster (:func:`open_executor`).

:mod:`rths_hil.studies.compensators` runs every compensator on the robustness study's draws.
"""

from .executors import SerialExecutor, make_executor, open_executor, run_cases
from .paper import (
    ACCURACY_COLUMNS,
    AccuracyResult,
    WindowCriterion,
    WindowSizeResult,
    accuracy_case,
    accuracy_study,
    auto_decimation,
    format_value,
    plot_accuracy,
    plot_window_size,
    window_size_for,
    window_size_study,
    write_accuracy_csv,
    write_window_size_csv,
)
from .perturbations import (
    Perturbation,
    channel_suffixes,
    default_perturbations,
    inline_twin,
    parse_vary,
)
from .robustness import (
    BENCHMARK_MIN_STEPS,
    SUMMARY_METRICS,
    TRIAL_COLUMNS,
    RobustnessResult,
    TrialSpec,
    exact_text,
    metric_summary,
    plan_trials,
    plot_robustness,
    preflight,
    reference_by_loop,
    reference_response,
    robustness_study,
    robustness_trial,
    trial_columns,
    write_summary,
    write_trials_csv,
)

__all__ = [
    "ACCURACY_COLUMNS",
    "BENCHMARK_MIN_STEPS",
    "SUMMARY_METRICS",
    "TRIAL_COLUMNS",
    "AccuracyResult",
    "Perturbation",
    "RobustnessResult",
    "SerialExecutor",
    "TrialSpec",
    "WindowCriterion",
    "WindowSizeResult",
    "accuracy_case",
    "accuracy_study",
    "auto_decimation",
    "channel_suffixes",
    "default_perturbations",
    "exact_text",
    "format_value",
    "inline_twin",
    "make_executor",
    "metric_summary",
    "open_executor",
    "parse_vary",
    "plan_trials",
    "plot_accuracy",
    "plot_robustness",
    "plot_window_size",
    "preflight",
    "reference_by_loop",
    "reference_response",
    "robustness_study",
    "robustness_trial",
    "run_cases",
    "trial_columns",
    "window_size_for",
    "window_size_study",
    "write_accuracy_csv",
    "write_summary",
    "write_trials_csv",
    "write_window_size_csv",
]

"""The paper's large-scale experiment (Puphal et al. 2022, Sec. V), reproduced.

:func:`run_experiment` draws ``situations`` single-frame synthetic intersection situations
with the paper's ranges (:func:`converters.synthetic.generate_situation`: 30-100 agents,
5-100 m gaps, 0-25 m/s), replays each through all nine models and the default cascade
with the replay engine (in worker processes, one per CPU by default), computes the
dataset statistics (:mod:`replay.analysis.stats`) and plots (:mod:`replay.analysis.stats.plots`), and writes
``report.md`` comparing the measured AUC and robustness with the paper's findings.

It also measures what the paper only proposed (Sec. VI): the cascade's false negatives
against the baseline and its compute against survival analysis on all agents, for

- the **default cascade** (``risk/survival_cascade.toml``), calibrated on other synthetic
  scenes (a held-out check: the situation seeds here never equal its calibration seeds);
- a cascade **calibrated on the first half** of the situations (``replay calibrate``'s
  maths, no false negative allowed) and run on the second half.

One module per concern:

- :mod:`replay.analysis.experiment.run`: drawing and replaying the situations (on the process pool
  of :mod:`replay.core.pool`), the half-calibration, the statistics: :func:`run_experiment`;
- :mod:`replay.analysis.experiment.findings`: the paper's findings checked one by one;
- :mod:`replay.analysis.experiment.report`: the tables, plots and ``report.md``
  (:func:`write_experiment`); its fixed prose is in ``templates/``.

Choices (documented here and in the report):

- Situation ``i`` uses seed ``SeedSequence(seed, spawn_key=(i,))``: independent streams,
  reproducible, and far from the small integer seeds used elsewhere.
- Every model is a function of the ego and one agent, so calibrating on the agents table
  (risks on all agents) reproduces what the cascade does on sub-frames exactly; the
  calibrated cascade is nevertheless *run* (with its own timing) on the second half.
"""

from replay.analysis.experiment.findings import (
    CE_FAMILY,
    ORDER_POINT,
    PAPER_SIGMA,
    SIGMA_REL_TOLERANCE,
    Finding,
    findings,
    median_ratio,
)
from replay.analysis.experiment.report import relink, report_markdown, write_experiment
from replay.analysis.experiment.run import (
    PAPER_RANGES,
    ChunkResult,
    ExperimentResult,
    ExperimentSettings,
    HalfCalibration,
    SituationTask,
    calibrate_on,
    calibration_seeds,
    lane_width,
    merge,
    model_times_ms,
    run_experiment,
    run_situations,
    situation_name,
    situation_seed,
)

# Re-exported while other branches move over (they live in replay.core.pool now).
from replay.core.pool import chunks, default_workers, parallel_map

__all__ = [
    "CE_FAMILY",
    "ORDER_POINT",
    "PAPER_RANGES",
    "PAPER_SIGMA",
    "SIGMA_REL_TOLERANCE",
    "ChunkResult",
    "ExperimentResult",
    "ExperimentSettings",
    "Finding",
    "HalfCalibration",
    "SituationTask",
    "calibrate_on",
    "calibration_seeds",
    "chunks",
    "default_workers",
    "findings",
    "lane_width",
    "median_ratio",
    "merge",
    "model_times_ms",
    "parallel_map",
    "relink",
    "report_markdown",
    "run_experiment",
    "run_situations",
    "situation_name",
    "situation_seed",
    "write_experiment",
]

"""Dataset statistics: how well each risk model filters against the survival baseline.

One module per concern (see ``docs/statistics.md`` for the tables and the choices):

- :mod:`replay.core.stats_sink`: :class:`StatsSink`, which collects the agents and frames
  tables while a scene replays, and the tables' schema;
- :mod:`replay.analysis.stats.compute`: ROC curves (with :func:`risk.metrics.exact_sweep`),
  operating points, FN/FP over the threshold, the cascade funnel: :func:`compute_stats`;
- :mod:`replay.analysis.stats.files`: agents tables read back from ``replay run --table`` and
  :func:`write_stats`;
- :mod:`replay.analysis.stats.plots`: the PNG figures (matplotlib; not imported here, so that
  workers that only collect tables do not load it);
- :mod:`replay.analysis.stats.run`: compute + write + plot, the tail ``replay stats`` and
  ``replay batch`` share.

The names below are the package's API: ``from replay.analysis.stats import compute_stats``.
"""

from replay.analysis.stats.compute import (
    DEFAULT_ERRORS_MODEL,
    HIGH_TPR_RANGE,
    TPR_TARGETS,
    TPR_TOLERANCE,
    DatasetStats,
    ModelStats,
    OperatingPoint,
    Situations,
    bootstrap_std_difference,
    cascade_summary,
    compute_stats,
    errors_over_threshold,
    funnel_table,
    model_stats,
    per_situation_rates,
    situations_of,
    sort_agents,
)
from replay.analysis.stats.files import (
    concat_agents,
    frames_from_agents,
    read_agents_table,
    write_stats,
)
from replay.core.stats_sink import (
    SITUATION_KEY,
    StatsSink,
    cascade_frame_row,
    frame_columns,
    frames_table,
    model_names_of,
    stage_names_of,
    tier_names_of,
)
from replay.errors import StatsError

__all__ = [
    "DEFAULT_ERRORS_MODEL",
    "HIGH_TPR_RANGE",
    "SITUATION_KEY",
    "TPR_TARGETS",
    "TPR_TOLERANCE",
    "DatasetStats",
    "ModelStats",
    "OperatingPoint",
    "Situations",
    "StatsError",
    "StatsSink",
    "bootstrap_std_difference",
    "cascade_frame_row",
    "cascade_summary",
    "compute_stats",
    "concat_agents",
    "errors_over_threshold",
    "frame_columns",
    "frames_from_agents",
    "frames_table",
    "funnel_table",
    "model_names_of",
    "model_stats",
    "per_situation_rates",
    "read_agents_table",
    "situations_of",
    "sort_agents",
    "stage_names_of",
    "tier_names_of",
    "write_stats",
]

"""The agents table as numpy columns, the form the table sink (:mod:`replay.core.tables`)
collects and the table's writer (:mod:`replay.core.table_file`, polars) turns into the
file. numpy only: both import it, and neither imports the other for its types.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

TRUTH_COLUMNS = ("truth_gap_m", "truth_pet_s", "truth_label")
#: With a planner beside the replay (``replay run --planner NAME --table T``): whether
#: removing the agent alone changes the plan (true / false, null when unknown) and by how
#: much (m); see :mod:`replay.planning.truth`.
PLANNER_COLUMNS = ("planner_label", "planner_shift_m")


@dataclass(frozen=True, eq=False)
class TableColumns:
    """The table as numpy columns: what :mod:`replay.core.table_file` turns into the file."""

    keys: tuple[str, ...]  # the collected columns, in order (codes for kind, stage, tier)
    data: dict[str, Any]  # name -> (rows,) array ([] when there are no rows)
    stage_names: tuple[str, ...]
    tier_names: tuple[str, ...]
    truth_gap_m: np.ndarray  # NaN: unknown
    truth_pet_s: np.ndarray  # NaN: the footprints do not meet, or unknown
    truth_label: np.ndarray  # int8 risk.hindsight labels

"""A planner beside a replay: every frame planned with all agents and with the cascade's.

``replay run --planner NAME`` (and ``replay evaluate --planner NAME``) give the engine a
:class:`PlannerAnnotator`. For each replayed frame it plans once with every valid other
agent and once with the agents the frame's cascade kept, and, with ``truth``, once more
without each agent that may matter (:func:`replay.planning.truth.planner_truth`). The
engine adds what it returns to the frame's :attr:`outputs.sinks.FrameResult.extras`:

- ``plan_all``, ``plan_filtered``: :class:`~replay.planning.types.Plan` (the recording
  draws both and plots their planning times);
- ``plan_changed``: :class:`~replay.planning.compare.PlanChange` of the filtered plan;
- with ``truth``: ``planner_label`` and ``planner_shift_m``, ``(N,)`` over the frame's
  agents (NaN for the ego, invalid agents and unknown labels), which the agents table
  writes as columns.

Car planners plan for vehicle egos only (``ego_kinds="vehicles"``, the default): a frame
whose ego is a pedestrian, a cyclist or another agent gets no plan (a failed plan naming
why) and unknown labels, and is counted in ``skipped`` and the summary line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from outputs.sinks import FrameResult, SceneInfo
from replay.planning.compare import DEFAULT_TOLERANCE_M, compare_plans
from replay.planning.errors import NoReferencePath
from replay.planning.inputs import ego_kind, plan_request, plans_for
from replay.planning.truth import planner_truth, target_speed
from replay.planning.types import Plan, Planner, PlanRequest, cold
from risk.filtering import cascade_answer
from risk.frame import Frame
from risk.hindsight import Tracks


@dataclass
class PlannerAnnotator:
    """See the module docstring. ``planner``: any :class:`Planner`."""

    planner: Planner
    truth: bool = False
    #: Also plan with the cascade's agents and compare (``plan_filtered``,
    #: ``plan_changed``); planner truth alone (``replay evaluate``) does not need it.
    filtered: bool = True
    tolerance_m: float = DEFAULT_TOLERANCE_M
    horizon_s: float = 5.0
    dt_s: float = 0.1
    #: ``vehicles`` (plan for vehicle egos only) or ``all`` (replay.planning.inputs).
    ego_kinds: str = "vehicles"

    def __post_init__(self) -> None:
        self.info: SceneInfo | None = None
        self._tracks: Tracks | None = None
        self._columns: dict[int, int] = {}
        #: Per annotated frame: (all-agents plan ms, filtered plan ms, changed or None).
        self.records: list[tuple[float, float, bool | None]] = []
        #: Frames not planned for the ego's kind, by kind name.
        self.skipped: dict[str, int] = {}

    @property
    def name(self) -> str:
        return self.planner.name

    def summary(self) -> str:
        """One line for the end of a run: how often the cascade changed the plan, and
        the median planning times with all agents and with the cascade's."""
        skipped = (
            f"; skipped {sum(self.skipped.values())} frames whose ego is not a vehicle ("
            + ", ".join(f"{k}: {n}" for k, n in sorted(self.skipped.items()))
            + ")"
            if self.skipped
            else ""
        )
        if not self.records:
            return f"Planner {self.name}: no frame planned{skipped}"
        all_ms = np.array([r[0] for r in self.records])
        filtered_ms = np.array([r[1] for r in self.records])
        changed = [r[2] for r in self.records if r[2] is not None]
        failed = len(self.records) - len(changed)
        ok = np.isfinite(all_ms) & np.isfinite(filtered_ms)
        times = (
            f"plan {np.median(all_ms[ok]):.2f} ms median with all agents, "
            f"{np.median(filtered_ms[ok]):.2f} ms with the cascade's"
            if ok.any()
            else "no plan timed"
        )
        return (
            f"Planner {self.name}: the cascade's agents changed the plan in "
            f"{sum(changed)} of {len(changed)} comparable frames"
            + (f" ({failed} frames without a plan either way)" if failed else "")
            + f"; {times}{skipped}"
        )

    def begin(self, info: SceneInfo) -> None:
        self.info = info
        self._tracks = None
        self._columns = {}

    def _tracks_now(self) -> Tracks | None:
        assert self.info is not None
        if self._tracks is None and self.info.tracks is not None:
            get: Callable[[], Tracks] = self.info.tracks
            self._tracks = get()
            self._columns = {int(i): c for c, i in enumerate(self._tracks.ids)}
        return self._tracks

    def annotate(self, result: FrameResult) -> dict[str, Any]:
        """The frame's plans (and labels); see the module docstring."""
        assert self.info is not None, "begin() first"
        frame = result.frame
        if not plans_for(frame, self.ego_kinds):
            kind = ego_kind(frame)
            self.skipped[kind] = self.skipped.get(kind, 0) + 1
            skipped = Plan.failed(f"the ego is a {kind}: car planners plan for vehicles")
            out: dict[str, Any] = {"plan_all": skipped}
            if self.filtered:
                out.update(plan_filtered=skipped, plan_changed=None)
            if self.truth:
                n = frame.n_agents
                out.update(planner_label=np.full(n, np.nan), planner_shift_m=np.full(n, np.nan))
            return out
        speed_now = float(frame.speed[frame.ego])
        target = speed_now
        tracks = self._tracks_now()
        if tracks is not None and frame.ego_id in self._columns:
            row = round((frame.t - tracks.t0_s) / tracks.dt_s)
            column = self._columns[frame.ego_id]
            target = target_speed(tracks, row, column, self.horizon_s, speed_now)
        n = frame.n_agents
        out = {}
        try:
            request = plan_request(
                frame, self.info.map, target_speed_mps=target, horizon_s=self.horizon_s,
                dt_s=self.dt_s,
            )  # fmt: skip
        except NoReferencePath as exc:
            failed = Plan.failed(str(exc))
            out.update(plan_all=failed, plan_filtered=failed, plan_changed=None)
            self.records.append((float("nan"), float("nan"), None))
            if self.truth:
                out.update(planner_label=np.full(n, np.nan), planner_shift_m=np.full(n, np.nan))
            return out
        everyone = cold(self.planner).plan(request)
        if not self.filtered:
            out.update(plan_all=everyone)
            self.records.append((everyone.plan_ms, float("nan"), None))
            if self.truth:
                out.update(self._labels(frame, request, everyone))
            return out
        kept = cascade_answer(frame, result.cascade, self.info.cascade).kept_ids
        keep = np.isin(request.agents.ids, kept)
        filtered = cold(self.planner).plan(request.with_agents(request.agents.subset(keep)))
        change = compare_plans(everyone, filtered, tolerance_m=self.tolerance_m)
        out.update(plan_all=everyone, plan_filtered=filtered, plan_changed=change)
        self.records.append((everyone.plan_ms, filtered.plan_ms, change.changed))
        if self.truth:
            out.update(self._labels(frame, request, everyone))
        return out

    def _labels(self, frame: Frame, request: PlanRequest, everyone: Plan) -> dict[str, Any]:
        """``planner_label`` and ``planner_shift_m`` ``(N,)`` over the frame's agents."""
        n = frame.n_agents
        labels = planner_truth(self.planner, request, everyone, tolerance_m=self.tolerance_m)
        label = np.full(n, np.nan)
        shift = np.full(n, np.nan)
        index = np.searchsorted(frame.ids, labels.ids, sorter=np.argsort(frame.ids))
        rows = np.argsort(frame.ids)[index]
        label[rows] = labels.label
        shift[rows] = labels.shift_m
        return {"planner_label": label, "planner_shift_m": shift}

"""The filter cascade of Puphal et al. (ICRAE 2022), Sec. VI, Fig. 6.

Filter stages run in order (default: path distance, trajectory distance, 2D Gaussians);
each evaluates *its own* model only on the agents that survived the previous stages (a
sub-frame built with :meth:`risk.Frame.select`, so the compute saving is real) and keeps
an agent when its risk reaches the stage's threshold. The survivors are then sorted by
survival risk into nested planner tiers (behavior ⊇ interactive ⊇ cooperative).

Every frame's report compares the cascade with the survival-analysis baseline computed on
*all* agents: which baseline-important agents each stage dropped (false negatives) and
what each stage cost beside what survival analysis on all agents costs.

Two implementations of the same job, one the oracle of the other:

- **Fused** (the default, whenever ``run_cascade`` is given no ``evaluate`` or
  ``risk.evaluate`` itself): no sub-frames. A reachability bound
  (:func:`risk.kernel.reachable`, maximum speeds :data:`MAX_SPEED_MPS`) first drops, in
  O(1) each, the agents whose survival risk cannot reach the baseline threshold even at
  their kind's maximum speed; zero false negatives by construction. When every stage is a
  path distance, trajectory distance or Gaussian stage (the default) the bound, the
  stages and survival analysis of the survivors run in one compiled pass per agent
  (:func:`risk.kernel.cascade_agents`): the path is extended and predicted once, an agent
  leaves at the first stage that drops it, distance stages are keep/drop tests that stop
  as soon as the decision is certain, and the Gaussian stage stops at the first step
  that reaches its threshold. Each part's time is the call's wall time shared out by the
  CPU cycles the kernel counted in it. Stages of other models run as one compiled call
  each over the index list of the remaining agents.
- **Staged** (when a custom ``evaluate`` is injected, e.g. a stand-in in tests): each stage
  is one ``evaluate`` call on a sub-frame of its survivors. The fused cascade keeps and
  drops exactly the same agents, except those the reachability bound drops first.

Choices the spec leaves open (documented here, see also ``docs/cascade.md``):

- Each stage's time includes its own share of the prediction (in the one-pass kernel,
  an agent's extension counts to the first stage that needs it, its prediction to the
  Gaussian stage); the survival-on-all reference likewise includes its own prediction on
  all agents. Times are wall-clock ``time.perf_counter``.
- A stage with no agent left to judge is not run; its time is 0.
- Tiers are nested: an agent reaches tier ``k`` when it reached tier ``k - 1``, its
  survival risk is ``>= tiers[k].min_survival_risk`` and it is among the ``max_agents``
  riskiest of tier ``k - 1`` (ties broken by agent order). A survivor below the first
  tier's minimum gets tier -1 although it was kept.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from risk.cascade_config import (
    DEFAULT_CASCADE_NAME,
    DEFAULT_CASCADE_PATH,
    NAMED_CASCADES,
    CascadeConfig,
    CascadeConfigError,
    CorridorSettings,
    Stage,
    Tier,
)
from risk.frame import KIND_NAMES, Frame
from risk.kernel_shared import BEHIND, CROSSING, LEADER
from risk.registry import (
    BASELINE_MODEL,
    BASELINE_THRESHOLD,
    MODELS,
    kernel,
    kernel_inputs,
    kernel_settings,
    resolve_prediction,
)
from risk.registry import evaluate as risk_evaluate

__all__ = [
    "DEFAULT_CASCADE_NAME",
    "DEFAULT_CASCADE_PATH",
    "MAX_SPEED_MPS",
    "NAMED_CASCADES",
    "SURVIVAL_MODEL",
    "CascadeConfig",
    "CascadeConfigError",
    "CascadeResult",
    "CorridorSettings",
    "Stage",
    "Tier",
    "assign_tiers",
    "keep_bounds",
    "reachable_mask",
    "run_cascade",
]

#: The model of the sorting step and of the baseline (survival analysis).
SURVIVAL_MODEL = BASELINE_MODEL

#: The reachability bound's maximum speed per kind, m/s: an agent is dropped ahead of the
#: stages only when it cannot become important even at ``max(its speed, this)``.
MAX_SPEED_MPS: dict[str, float] = {
    "vehicle": 40.0,  # 144 km/h
    "pedestrian": 7.0,  # a running adult
    "cyclist": 15.0,  # 54 km/h
    "other": 40.0,  # as a vehicle
}

#: Signature of ``risk.evaluate``: frame, model names, parameters -> name -> (N,) risks.
Evaluator = Callable[..., dict[str, np.ndarray]]


# ---------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class CascadeResult:
    """The cascade on one frame. ``N = frame.n_agents``; ``S = len(stages)``."""

    stage_names: tuple[str, ...]
    kept: np.ndarray  # (S, N) bool, kept after stage s (False for ego/invalid)
    dropped_at: np.ndarray  # (N,) int8, stage that dropped the agent; -1 survived or not judged
    tier: np.ndarray  # (N,) int8, deepest tier reached (0 = first), -1 if none
    # (N,) float64, survival risk of the survivors, NaN otherwise (and for every agent
    # when the cascade has no tiers: then survival of the survivors is skipped)
    survival: np.ndarray
    baseline: np.ndarray  # (N,) bool, survival baseline on all agents (R_S >= threshold)
    false_negatives: np.ndarray  # (S,) int64, baseline agents dropped up to and incl. stage s
    stage_time_s: np.ndarray  # (S,) float64, s, each stage's compute time on its input set
    sort_time_s: float  # s, survival on the survivors + tier sorting
    survival_all_time_s: float  # s, survival on all agents (what the cascade saves)
    others: np.ndarray  # (N,) bool, valid and not the ego
    survival_all: np.ndarray = field(repr=False)  # (N,) float64 R_S on all agents (NaN: ego)
    # (N,) bool, dropped by the reachability bound ahead of stage 0 (their dropped_at is
    # 0); None when the bound did not run (the staged cascade)
    unreachable: np.ndarray | None = field(default=None, repr=False)
    reach_time_s: float = 0.0  # s, the reachability bound
    # (N,) bool, kept by the corridor stage ahead of the others (kept after every stage);
    # None when the cascade has no corridor stage
    protected: np.ndarray | None = field(default=None, repr=False)
    corridor_time_s: float = 0.0  # s, the corridor stage
    # (N,) bool, dropped by the corridor stage as followers that cannot reach the ego
    # (their dropped_at is 0); None when the cascade has no corridor stage
    behind: np.ndarray | None = field(default=None, repr=False)
    # False when run with ``baseline=False``: survival on all agents was not computed, so
    # ``survival_all`` is NaN, ``baseline`` False and ``false_negatives`` 0 (not measured)
    baseline_computed: bool = True

    @property
    def n_kept(self) -> np.ndarray:
        """(S,) number of agents kept after each stage."""
        return self.kept.sum(axis=1)

    @classmethod
    def _make(cls, **values: Any) -> CascadeResult:
        """The result from a value for every field (all of them: not checked here, see
        ``tests/test_cascade.py``), without the frozen ``__init__``'s
        ``object.__setattr__`` per field: several microseconds a frame, right after the
        kernel has cooled Python's caches."""
        result = object.__new__(cls)
        result.__dict__.update(values)
        return result

    def tier_counts(self, n_tiers: int) -> np.ndarray:
        """(n_tiers,) number of agents that reached each tier (nested counts)."""
        return np.array([(self.tier >= k).sum() for k in range(n_tiers)], dtype=np.int64)


# ---------------------------------------------------------------------- running
def run_cascade(
    frame: Frame,
    config: CascadeConfig,
    *,
    params: Mapping[str, Any] | None = None,
    prediction: Any = None,
    evaluate: Evaluator | None = None,
    reachability: bool = True,
    baseline: bool = True,
) -> CascadeResult:
    """Run the cascade on one frame.

    Stage ``s`` judges ``config.stages[s].model`` on the agents kept by stage ``s - 1``
    (all valid others for the first stage). ``params`` (model name -> parameters) and
    ``prediction`` (a ``risk.PredictionSettings``) apply to every model.

    With ``evaluate`` None or ``risk.evaluate`` (also a ``functools.partial`` of it that
    sets only ``prediction``) the fused cascade runs, led by the reachability bound when
    ``reachability`` is True; with any other ``evaluate`` the staged cascade calls it on
    sub-frames.

    ``baseline``: also run survival analysis on every agent, for the baseline and the
    false negatives (what the replay engine reports). A planner stack needs only the
    kept agents and their tiers: with False the fused cascade skips it, which takes about
    a third off a call on a frame of 20 agents, and the result says so
    (``baseline_computed``). The staged cascade always computes it.
    """
    fused, prediction = _fused_prediction(evaluate, prediction)
    if fused:
        return _run_fused(frame, config, params, prediction, reachability, baseline)
    assert evaluate is not None
    if prediction is not None:
        evaluate = functools.partial(evaluate, prediction=prediction)
    return _run_staged(frame, config, params, evaluate)


def _fused_prediction(evaluate: Evaluator | None, prediction: Any) -> tuple[bool, Any]:
    """Whether ``evaluate`` is the production ``risk.evaluate`` (so the fused cascade
    gives the same result), and the prediction settings it implies."""
    if evaluate is None or evaluate is risk_evaluate:
        return True, prediction
    if (
        isinstance(evaluate, functools.partial)
        and evaluate.func is risk_evaluate
        and not evaluate.args
        and set(evaluate.keywords) <= {"prediction"}
    ):
        return True, prediction if prediction is not None else evaluate.keywords.get("prediction")
    return False, prediction


def keep_bounds(threshold: float, epsilon_m: float) -> tuple[float, float]:
    """Squared distances ``(stop2, cut2)`` of a distance stage ``eps / (eps + d) >= t``.

    Any ``d`` with ``d^2 <= stop2`` certainly keeps and any ``d`` with ``d^2 > cut2``
    certainly drops, in floating point (the risk is monotone in ``d`` and both ends are
    stepped past the float where the comparison turns), so the kernel can stop early
    and prune without changing one decision."""
    if not threshold > 0:
        return math.inf, math.inf  # everything is kept
    if threshold > 1:
        return -1.0, -1.0  # nothing reaches a risk above 1
    d_cut = max(epsilon_m / threshold - epsilon_m, 0.0)
    step = max(d_cut * 1e-15, 1e-300)
    lo = d_cut
    while lo > 0 and epsilon_m / (epsilon_m + lo) < threshold:
        lo = max(lo - step, 0.0)
        step *= 2.0
    step = max(d_cut * 1e-15, 1e-300)
    hi = d_cut
    while epsilon_m / (epsilon_m + hi) >= threshold:
        hi += step
        step *= 2.0
    stop = lo * (1 - 1e-12)
    cut = hi * (1 + 1e-12)
    return (stop * stop if epsilon_m / (epsilon_m + lo) >= threshold else -1.0), cut * cut


def _kind_speeds() -> np.ndarray:
    a = np.array([MAX_SPEED_MPS[k] for k in KIND_NAMES], dtype=np.float64)
    a.flags.writeable = False
    return a


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.int64)
    a.flags.writeable = False
    return a


def _run_fused(
    frame: Frame,
    config: CascadeConfig,
    params: Mapping[str, Any] | None,
    prediction: Any,
    reachability: bool,
    with_baseline: bool = True,
) -> CascadeResult:
    chosen, settings, steps, unc, fp, ip = kernel_inputs(params, prediction)
    plan = _plan(config, chosen)
    others = frame.others

    start = time.perf_counter()
    if with_baseline:
        survival_all = kernel.run(frame, _WANT[(_SURV_SLOT,)], fp, ip, steps, unc)[_SURV_SLOT]
    else:  # NaN compares False: nobody is baseline-important, no false negative counted
        survival_all = np.full(frame.n_agents, np.nan)
    survival_all_time_s = time.perf_counter() - start

    protected, behind, corridor_time_s = corridor_masks(frame, config.corridor)
    shielded = kernel.NOT_PROTECTED if protected is None else protected
    parts = None
    judged = kernel.ALL_AGENTS
    if behind is not None and behind.any():
        judged = _ro(np.flatnonzero(others & ~behind))
    if plan.one_pass and (judged is kernel.ALL_AGENTS or judged.size > 0):
        parts = _one_pass(
            frame, plan, steps, unc, fp, ip, reachability, survival_all, shielded, judged
        )
    if parts is None:
        parts = _pass_per_stage(
            frame, config, chosen, settings, steps, unc, fp, ip, reachability, survival_all,
            shielded, behind,
        )  # fmt: skip
    elif judged is not kernel.ALL_AGENTS:
        parts = _with_behind(parts, behind, others, survival_all, config.baseline_threshold)
    kept, dropped_at, unreachable, survival, tier, baseline, false_negatives, times = parts
    return CascadeResult._make(
        stage_names=plan.stage_names,
        kept=kept,
        dropped_at=dropped_at,
        tier=tier,
        survival=survival,
        baseline=baseline,
        false_negatives=false_negatives,
        stage_time_s=times[1],
        sort_time_s=times[2],
        survival_all_time_s=survival_all_time_s,
        others=others,
        survival_all=survival_all,
        unreachable=unreachable,
        reach_time_s=times[0],
        protected=protected,
        corridor_time_s=corridor_time_s,
        behind=behind,
        baseline_computed=with_baseline,
    )


def _with_behind(
    parts: _Parts,
    behind: Any,
    others: np.ndarray,
    survival_all: np.ndarray,
    baseline_threshold: float,
) -> _Parts:
    """The one-pass kernel's result, which judged every agent but the corridor stage's
    followers, completed for them: dropped ahead of stage 0, counted in the baseline and
    its false negatives."""
    kept, dropped_at, unreachable, survival, tier, baseline, false_neg, times = parts
    dropped_at[behind] = 0
    important = behind & others & (survival_all >= baseline_threshold)
    baseline = baseline | important
    false_neg = false_neg + int(important.sum())
    return kept, dropped_at, unreachable, survival, tier, baseline, false_neg, times


def corridor_masks(
    frame: Frame, corridor: CorridorSettings | None
) -> tuple[np.ndarray | None, np.ndarray | None, float]:
    """``(N,)`` bool, read-only: the agents the corridor stage keeps and those it drops
    (:func:`risk.kernel.corridor_keep`), and its time (s); None, None and 0 without one."""
    if corridor is None:
        return None, None, 0.0
    start = time.perf_counter()
    fa = kernel.frame_arrays(frame)
    codes = kernel.corridor_keep(
        *fa[:5], fa[6], fa[7], fa[8], fa[9], int(frame.ego), corridor_vector(corridor)
    )
    protected = (codes == LEADER) | (codes == CROSSING)
    behind = codes == BEHIND
    protected.flags.writeable = False
    behind.flags.writeable = False
    return protected, behind, time.perf_counter() - start


def corridor_mask(
    frame: Frame, corridor: CorridorSettings | None
) -> tuple[np.ndarray | None, float]:
    """``(N,)`` bool, read-only: the agents the corridor stage keeps, and its time (s);
    None and 0 without one (:func:`corridor_masks`)."""
    protected, _, elapsed = corridor_masks(frame, corridor)
    return protected, elapsed


#: The corridor settings in the order of the kernel's vector (risk.kernel_corridor).
CORRIDOR_FIELDS = (
    "leaders", "headway_s", "brake_mps2", "accel_mps2", "margin_m", "lateral_margin_m",
    "crossing", "crossing_slack_s", "horizon_s",
)  # fmt: skip


@functools.lru_cache(maxsize=16)
def corridor_vector(corridor: CorridorSettings) -> np.ndarray:
    """The kernel's read-only parameter vector of a corridor stage."""
    vector = np.array([float(getattr(corridor, name)) for name in CORRIDOR_FIELDS])
    vector.flags.writeable = False
    return vector


#: Stage models that the one-pass kernel (:func:`risk.kernel.cascade_agents`) runs.
_FUSED_MODELS = ("path_distance", "trajectory_distance", "gaussian")

#: kept (S, N), dropped_at, unreachable, survival, tier, baseline, false negatives (S,),
#: (reach, stage, sort times).
_Parts = tuple[
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    tuple[float, np.ndarray, float],
]


@dataclass(frozen=True)
class _Plan:
    """A cascade's kernel arguments for one choice of the stage models' parameters."""

    params: tuple[Any, ...]  # the stage models' parameter objects (compared by identity)
    stage_names: tuple[str, ...]
    one_pass: bool  # every stage is one the one-pass kernel runs (and it can run here)
    slots: np.ndarray
    thr: np.ndarray
    stop2: np.ndarray
    cut2: np.ndarray
    tier_min: np.ndarray
    tier_cap: np.ndarray
    baseline_threshold: float


def _plan(config: CascadeConfig, chosen: Mapping[str, Any]) -> _Plan:
    """The kernel arguments of ``config``, cached on the (immutable) configuration while
    the stage models' parameter objects stay the same."""
    plan = config.__dict__.get("_plan")
    # (a tuple compares its items by identity first; equal objects give equal vectors)
    if plan is not None and tuple(map(chosen.__getitem__, plan.stage_names)) == plan.params:
        return plan
    objects = tuple(chosen[st.model] for st in config.stages)
    slots, thr, stop2, cut2 = _stage_vectors(config.stages, chosen)
    tier_min, tier_cap = _tier_vectors(config.tiers)
    plan = _Plan(
        params=objects,
        stage_names=config.stage_names,
        one_pass=kernel.HAVE_CYCLE_COUNTER
        and all(st.model in _FUSED_MODELS for st in config.stages),
        slots=slots,
        thr=thr,
        stop2=stop2,
        cut2=cut2,
        tier_min=tier_min,
        tier_cap=tier_cap,
        baseline_threshold=float(config.baseline_threshold),
    )
    object.__setattr__(config, "_plan", plan)
    return plan


def _tier_vectors(tiers: Sequence[Tier]) -> tuple[np.ndarray, np.ndarray]:
    """Read-only minimum risks and caps (-1: none) of the tiers, for :func:`kernel.tiers`."""
    tier_min = np.array([t.min_survival_risk for t in tiers], dtype=np.float64)
    tier_cap = np.array([-1 if t.max_agents is None else t.max_agents for t in tiers])
    tier_cap = tier_cap.astype(np.int64)
    tier_min.flags.writeable = False
    tier_cap.flags.writeable = False
    return tier_min, tier_cap


def _one_pass(
    frame: Frame,
    plan: _Plan,
    steps: np.ndarray,
    unc: np.ndarray,
    fp: np.ndarray,
    ip: np.ndarray,
    reachability: bool,
    survival_all: np.ndarray,
    protected: np.ndarray,
    agents: np.ndarray,
) -> _Parts | None:
    """The bound, every stage, survival of the survivors and their tiers in one kernel
    call for ``agents`` (empty: every valid other); None when this CPU has no cycle
    counter (then run a pass per stage).

    Each stage's time (and the bound's, and survival's with the tiers in the sort time)
    is the call's measured wall time shared out in proportion to the CPU cycles the
    kernel counted in that part (its set-up, the ego's prediction, and the call overhead
    are so shared in the same proportion)."""
    n_stages = plan.slots.shape[0]
    start = time.perf_counter()
    kept, dropped_at, unreachable, _, survival, cyc, tier, baseline, false_neg = (
        kernel.cascade_agents(
            *kernel.frame_arrays(frame), int(frame.ego), agents, steps, unc, fp,
            ip, plan.slots, plan.thr, plan.stop2, plan.cut2, bool(reachability), _MAX_SPEEDS,
            plan.baseline_threshold, survival_all, plan.tier_min, plan.tier_cap, protected,
        )
    )  # fmt: skip
    wall = time.perf_counter() - start
    parts = cyc.tolist()
    total = sum(parts) - parts[0]
    if total <= 0 and frame.others.any():
        return None  # no cycle counter on this CPU: time each stage
    scale = wall / total if total > 0 else 0.0
    stage_times = cyc[2 : 2 + n_stages] * scale
    return (
        kept,
        dropped_at,
        unreachable,
        survival,
        tier,
        baseline,
        false_neg,
        (parts[1] * scale, stage_times, parts[2 + n_stages] * scale),
    )


@functools.lru_cache(maxsize=64)
def _stage_vectors_cached(
    stages: tuple[Any, ...], eps: tuple[float, ...]
) -> tuple[np.ndarray, ...]:
    slots = np.array([kernel.SLOTS.index(st.model) for st in stages], dtype=np.int64)
    thr = np.array([st.threshold for st in stages], dtype=np.float64)
    stop2 = np.full(len(stages), -1.0)
    cut2 = np.full(len(stages), np.inf)
    for s, (stage, e) in enumerate(zip(stages, eps, strict=True)):
        if stage.model in ("path_distance", "trajectory_distance"):
            stop2[s], cut2[s] = keep_bounds(stage.threshold, e)
    for a in (slots, thr, stop2, cut2):
        a.flags.writeable = False
    return slots, thr, stop2, cut2


def _stage_vectors(stages: tuple[Any, ...], chosen: Mapping[str, Any]) -> tuple[np.ndarray, ...]:
    """Slots, thresholds and keep/drop bounds of the stages, as read-only arrays."""
    eps = tuple(
        float(chosen[st.model].epsilon_m) if hasattr(chosen[st.model], "epsilon_m") else 0.0
        for st in stages
    )
    return _stage_vectors_cached(tuple(stages), eps)


def _pass_per_stage(
    frame: Frame,
    config: CascadeConfig,
    chosen: Mapping[str, Any],
    settings: Any,
    steps: np.ndarray,
    unc: np.ndarray,
    fp: np.ndarray,
    ip: np.ndarray,
    reachability: bool,
    survival_all: np.ndarray,
    protected: np.ndarray,
    behind: np.ndarray | None = None,
) -> _Parts:
    """One kernel call for the bound, one per stage and one for survival, each timed
    (stages of any model). ``protected``: the corridor stage's agents (or empty), kept
    after every stage without being judged; ``behind``: those it drops (or None)."""
    n, n_stages = frame.n_agents, len(config.stages)
    surv_slot = _SURV_SLOT
    start = time.perf_counter()
    shielded = protected if protected.shape[0] == n else np.zeros(n, dtype=bool)
    dropped_early = np.zeros(n, dtype=bool) if behind is None else behind
    current = np.flatnonzero(frame.others & ~shielded & ~dropped_early)
    unreachable = np.zeros(n, dtype=bool)
    if reachability and current.size:
        reach = _reachable(frame, current, settings, unc, _MAX_SPEEDS, config.baseline_threshold)
        unreachable[current[~reach]] = True
        current = current[reach]
    reach_time_s = time.perf_counter() - start

    kept = np.zeros((n_stages, n), dtype=bool)
    dropped_at = np.full(n, -1, dtype=np.int8)
    dropped_at[unreachable | dropped_early] = 0
    stage_time_s = np.zeros(n_stages)
    survival_known: np.ndarray | None = None  # computed in the Gaussian stage's loop
    for s, stage in enumerate(config.stages):
        if not current.size:
            continue
        start = time.perf_counter()
        slot = kernel.SLOTS.index(stage.model)
        stop2, cut2 = kernel.NO_STOP, kernel.NO_CUT
        if stage.model in ("path_distance", "trajectory_distance"):
            stop2, cut2 = _stage_bounds(slot, stage.threshold, chosen[stage.model].epsilon_m)
        slots = (slot, surv_slot) if stage.model == "gaussian" else (slot,)
        agents = _ro(current)
        out = kernel.run(frame, _WANT[slots], fp, ip, steps, unc, agents, stop2, cut2)
        keep = np.nan_to_num(out[slot, current], nan=-np.inf) >= stage.threshold
        kept[s, current[keep]] = True
        dropped_at[current[~keep]] = s
        if len(slots) == 2:
            survival_known = out[surv_slot]
        current = current[keep]
        stage_time_s[s] = time.perf_counter() - start
    kept[:, shielded] = True
    if shielded.any():
        current = np.union1d(current, np.flatnonzero(shielded))
        survival_known = None  # (the Gaussian stage did not see the corridor's agents)
    survival = np.full(n, np.nan)
    tier = np.full(n, -1, dtype=np.int8)
    sort_time_s = 0.0
    if current.size and config.tiers:  # no tiers: no survival of the survivors (the kernel's)
        start = time.perf_counter()
        if survival_known is None:
            out = kernel.run(frame, _WANT[(surv_slot,)], fp, ip, steps, unc, _ro(current))
            survival_known = out[surv_slot]
        survival[current] = survival_known[current]
        tier[current] = assign_tiers(survival[current], config.tiers)
        sort_time_s = time.perf_counter() - start
    baseline = frame.others & (survival_all >= config.baseline_threshold)  # NaN: False
    false_negatives = (baseline[None, :] & ~kept).sum(axis=1).astype(np.int64)
    return (
        kept,
        dropped_at,
        unreachable,
        survival,
        tier,
        baseline,
        false_negatives,
        (reach_time_s, stage_time_s, sort_time_s),
    )


def reachable_mask(
    frame: Frame,
    threshold: float = BASELINE_THRESHOLD,
    *,
    prediction: Any = None,
    max_speed_mps: Mapping[str, float] | None = None,
) -> np.ndarray:
    """``(N,)`` bool: False for the agents that the reachability bound drops (their
    survival risk is certainly below ``threshold``), True for every other valid agent;
    False for the ego and invalid agents. ``max_speed_mps``: per kind name (default
    :data:`MAX_SPEED_MPS`)."""
    settings = resolve_prediction(prediction)
    _, unc = kernel_settings(settings)
    speeds = _MAX_SPEEDS
    if max_speed_mps is not None:
        speeds = np.array([float(max_speed_mps[k]) for k in KIND_NAMES])
        speeds.flags.writeable = False
    out = np.zeros(frame.n_agents, dtype=bool)
    agents = np.flatnonzero(frame.others)
    if agents.size:
        out[agents] = _reachable(frame, agents, settings, unc, speeds, threshold)
    return out


def _reachable(
    frame: Frame,
    agents: np.ndarray,
    settings: Any,
    unc: np.ndarray,
    speeds: np.ndarray,
    threshold: float,
) -> np.ndarray:
    fa = kernel.frame_arrays(frame)
    return kernel.reachable(
        fa[7], fa[9], fa[2], fa[5], int(frame.ego), _ro(agents), float(settings.horizon_s),
        int(settings.n_steps), unc, speeds, float(threshold),
    )  # fmt: skip


class _Wants(dict):
    """Read-only ``want`` flag vectors by tuple of model slots, made on first use."""

    def __missing__(self, slots: tuple[int, ...]) -> np.ndarray:
        want = np.zeros(kernel.N_MODELS, dtype=np.bool_)
        want[list(slots)] = True
        want.flags.writeable = False
        self[slots] = want
        return want


_WANT = _Wants()
_SURV_SLOT = list(MODELS).index(SURVIVAL_MODEL)  # (registry order = the kernel's slots)
_MAX_SPEEDS = _kind_speeds()


@functools.lru_cache(maxsize=256)
def _stage_bounds(slot: int, threshold: float, epsilon_m: float) -> tuple[np.ndarray, np.ndarray]:
    stop, cut = keep_bounds(threshold, epsilon_m)
    stop2 = np.array(kernel.NO_STOP)
    cut2 = np.array(kernel.NO_CUT)
    stop2[slot], cut2[slot] = stop, cut
    stop2.flags.writeable = False
    cut2.flags.writeable = False
    return stop2, cut2


def _run_staged(
    frame: Frame,
    config: CascadeConfig,
    params: Mapping[str, Any] | None,
    evaluate: Evaluator,
) -> CascadeResult:
    """The cascade on sub-frames through ``evaluate`` (the oracle of the fused one)."""
    n, n_stages = frame.n_agents, len(config.stages)
    others = frame.others

    start = time.perf_counter()
    survival_all = np.asarray(
        evaluate(frame, models=[SURVIVAL_MODEL], params=params)[SURVIVAL_MODEL], dtype=np.float64
    )
    survival_all_time_s = time.perf_counter() - start
    # NaN (ego, invalid) compares False, so they are never baseline-important.
    baseline = others & (np.nan_to_num(survival_all, nan=-np.inf) >= config.baseline_threshold)

    protected, behind, corridor_time_s = corridor_masks(frame, config.corridor)
    shielded = np.zeros(n, dtype=bool) if protected is None else protected
    kept = np.zeros((n_stages, n), dtype=bool)
    dropped_at = np.full(n, -1, dtype=np.int8)
    stage_time_s = np.zeros(n_stages)
    current = others & ~shielded
    if behind is not None:
        current &= ~behind
        dropped_at[behind] = 0
    for s, stage in enumerate(config.stages):
        candidates = np.flatnonzero(current)
        if candidates.size:
            risk_s, stage_time_s[s] = _timed_on_subset(
                frame, candidates, stage.model, params, evaluate
            )
            keep = np.nan_to_num(risk_s, nan=-np.inf) >= stage.threshold
            kept[s, candidates[keep]] = True
            dropped_at[candidates[~keep]] = s
        current = kept[s]
    kept[:, shielded] = True
    current = current | shielded
    false_negatives = (baseline[None, :] & ~kept).sum(axis=1).astype(np.int64)

    survivors = np.flatnonzero(current)
    survival = np.full(n, np.nan)
    tier = np.full(n, -1, dtype=np.int8)
    sort_time_s = 0.0
    if survivors.size and config.tiers:  # as the fused cascade: no tiers, no survival
        start = time.perf_counter()
        risk_surv, _ = _timed_on_subset(frame, survivors, SURVIVAL_MODEL, params, evaluate)
        survival[survivors] = risk_surv
        tier[survivors] = assign_tiers(risk_surv, config.tiers)
        sort_time_s = time.perf_counter() - start

    return CascadeResult(
        stage_names=config.stage_names,
        kept=kept,
        dropped_at=dropped_at,
        tier=tier,
        survival=survival,
        baseline=baseline,
        false_negatives=false_negatives,
        stage_time_s=stage_time_s,
        sort_time_s=sort_time_s,
        survival_all_time_s=survival_all_time_s,
        others=others,
        survival_all=survival_all,
        protected=protected,
        corridor_time_s=corridor_time_s,
        behind=behind,
    )


def _timed_on_subset(
    frame: Frame,
    agents: np.ndarray,
    model: str,
    params: Mapping[str, Any] | None,
    evaluate: Evaluator,
) -> tuple[np.ndarray, float]:
    """``model``'s risk ``(len(agents),)`` on a sub-frame of the ego plus ``agents``, and
    the wall time (s) of building the sub-frame and evaluating it."""
    start = time.perf_counter()
    sub = frame.select(np.concatenate(([frame.ego], agents)))
    risk_sub = np.asarray(evaluate(sub, models=[model], params=params)[model], dtype=np.float64)
    elapsed = time.perf_counter() - start
    # The ego is row 0 of the sub-frame; the others follow in the order of ``agents``.
    return risk_sub[1:], elapsed


def assign_tiers(survival: np.ndarray, tiers: Sequence[Tier]) -> np.ndarray:
    """Deepest tier of each agent, ``(K,)`` int8 from survival risks ``(K,)``; -1: none.

    Tier ``k`` holds the agents of tier ``k - 1`` whose risk is ``>= min_survival_risk``,
    capped to the ``max_agents`` riskiest (ties: the lower index first). Computed by
    :func:`risk.kernel.tiers` (which the one-pass cascade calls too).
    """
    # A writable copy: the one-pass cascade calls the kernel with a writable array, so
    # both calls share one compiled specialisation.
    risk = np.array(survival, dtype=np.float64, order="C")
    if risk.ndim != 1:
        raise ValueError("survival must be one-dimensional")
    return kernel.tiers(risk, *_tier_vectors(tiers))

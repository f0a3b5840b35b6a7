"""Budgets: the share of a reference's positives a planner keeps when it takes at most K
agents per frame (or every agent within a radius), with scene-bootstrap intervals.

Pure numpy. A *situation* is one frame seen by one ego. The **top-K rule** of a score
keeps, in every situation, the K agents with the highest scores (a planner's budget,
"give me the 16 agents that matter most"); ties are broken by the row order (stable), so
exactly ``min(K, agents)`` are kept. **Nearest-K** is the top-K rule of minus the centre
distance; a **radius** rule keeps every agent within R m (its budget varies per
situation, so it is reported at its mean kept count). The recall of a rule against a
reference is ``kept positives / positives`` pooled over all situations, the positives
being the reference's (label codes 1, 0, -1 unknown or booleans: unknown rows are left
out, as in :mod:`risk.evaluation`).

Intervals: the scene bootstrap of :func:`risk.evaluation.bootstrap_weights` (counts per
scene, weighed by each replicate's draws).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from risk.evaluation import percentile_interval, reference_mask

#: The budgets reported (agents per situation).
BUDGETS: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
#: The radius rules reported (m).
RADII_M: tuple[float, ...] = (10.0, 20.0, 30.0, 50.0, 75.0, 100.0)


def ranks_in_situation(scores: np.ndarray, situations: np.ndarray) -> np.ndarray:
    """``(A,)`` int64: each row's rank (0 = highest score) among the rows of its
    situation; NaN scores rank last; ties in row order."""
    s = np.asarray(scores, dtype=np.float64)
    sit = np.asarray(situations)
    key = np.where(np.isnan(s), np.inf, -s)  # highest first, NaN last
    order = np.lexsort((np.arange(s.size), key, sit))
    sorted_sit = sit[order]
    start = np.r_[0, np.flatnonzero(sorted_sit[1:] != sorted_sit[:-1]) + 1]
    group_start = np.repeat(start, np.diff(np.r_[start, s.size]))
    ranks = np.empty(s.size, dtype=np.int64)
    ranks[order] = np.arange(s.size) - group_start
    return ranks


def _recall(
    kept: np.ndarray, positive: np.ndarray, codes: np.ndarray, draws: np.ndarray | None,
    level: float,
) -> dict[str, Any]:  # fmt: skip
    """Pooled recall of the ``kept (A,)`` rows among ``positive (A,)``, with the
    interval over scene draws ``(B, S)`` (codes ``(A,)`` scene indices)."""
    n_pos = int(positive.sum())
    out: dict[str, Any] = {
        "positives": n_pos,
        "kept_positives": int((kept & positive).sum()),
        "value": float((kept & positive).sum() / n_pos) if n_pos else math.nan,
    }
    if draws is not None:
        n_s = draws.shape[1]
        pos_c = np.bincount(codes[positive], minlength=n_s).astype(np.float64)
        kept_c = np.bincount(codes[positive & kept], minlength=n_s).astype(np.float64)
        d = draws.astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            reps = (d @ kept_c) / (d @ pos_c)
        lo, hi = percentile_interval(reps, level=level)
        out["ci"] = [lo, hi]
    return out


def budget_recall(
    scores: dict[str, np.ndarray],
    reference: np.ndarray,
    *,
    situations: np.ndarray,
    codes: np.ndarray,
    distance_m: np.ndarray | None = None,
    kept_sets: dict[str, np.ndarray] | None = None,
    budgets: Sequence[int] = BUDGETS,
    radii_m: Sequence[float] = RADII_M,
    draws: np.ndarray | None = None,
    level: float = 0.95,
) -> list[dict[str, Any]]:
    """The recall of every rule against one reference, as rows.

    ``scores``: rule name -> ``(A,)`` score (top-K rules); ``distance_m (A,)``: centre
    distances for ``nearest`` (top-K) and ``radius`` rules; ``kept_sets``: name -> ``(A,)``
    bool of a fixed rule (the cascade), reported at its mean kept count; ``situations
    (A,)`` situation codes; ``codes (A,)`` scene indices ``0 .. S-1`` of ``draws (B, S)``.
    Each row: ``rule``, ``kind`` (``top_k``, ``radius``, ``fixed``), ``k`` (the budget,
    or None), ``radius_m`` (or None), ``mean_kept`` (agents per situation), ``positives``,
    ``kept_positives``, ``value`` (recall; NaN without positives), ``ci``.
    """
    include, positive = reference_mask(reference)
    positive = include & positive
    codes = np.asarray(codes, dtype=np.int64)
    sit = np.asarray(situations)
    n_sit = max(1, np.unique(sit).size)
    rows: list[dict[str, Any]] = []
    top = dict(scores)
    if distance_m is not None:
        top["nearest"] = -np.asarray(distance_m, dtype=np.float64)
    for rule, s in top.items():
        rank = ranks_in_situation(s, sit)
        counts = np.bincount(np.unique(sit, return_inverse=True)[1])
        for k in budgets:
            kept = rank < k
            rows.append(
                {
                    "rule": rule, "kind": "top_k", "k": int(k), "radius_m": None,
                    "mean_kept": float(np.minimum(counts, k).mean()) if counts.size else 0.0,
                    **_recall(kept, positive, codes, draws, level),
                }
            )  # fmt: skip
    if distance_m is not None:
        d = np.asarray(distance_m, dtype=np.float64)
        for r in radii_m:
            kept = np.nan_to_num(d, nan=np.inf) <= r
            rows.append(
                {
                    "rule": "radius", "kind": "radius", "k": None, "radius_m": float(r),
                    "mean_kept": float(kept.sum() / n_sit),
                    **_recall(kept, positive, codes, draws, level),
                }
            )  # fmt: skip
    for name, kept_set in (kept_sets or {}).items():
        kept = np.asarray(kept_set, dtype=bool)
        rows.append(
            {
                "rule": name, "kind": "fixed", "k": None, "radius_m": None,
                "mean_kept": float(kept.sum() / n_sit),
                **_recall(kept, positive, codes, draws, level),
            }
        )  # fmt: skip
    return rows

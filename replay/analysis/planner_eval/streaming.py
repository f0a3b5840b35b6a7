"""``replay plan``'s summaries, merged tables and plot points from the per-scene part
files, one part at a time (issue 38): the driver holds per-scene sums, value counts and
a capped sample of plot points, never the corpus's rows.

A summary is two passes over the parts (:class:`Tally`), each reading one part at a
time and only the columns it needs, through the same per-part code:

1. per scene: the counts and sums of every share and mean (the bootstrap's clusters),
   totals, the values' counts on :mod:`risk.order_statistics`' grid;
2. the values in the grid bins where each median and p95 falls, and the plot points.

The scene bootstrap draws :func:`risk.evaluation.scene_draws` for the scenes in name
order (as :func:`risk.evaluation.bootstrap_weights` numbers them), so it depends on the
scene list and the seed only, never on the engine or on the order in which scenes
finished. A scene's sum adds its values in row order, as ``np.bincount`` does over the
key-ordered table (a scene whose closed-loop egos ran in several tasks continues its sum
over their parts), so the replicates are those of the full table.

**Exact** against the full-table summary (``tests/test_plan_streaming.py`` keeps it as
the oracle): every count, share and its interval, every median and p95, every interval
of a mean. **Up to float rounding** (the full table's ``np.mean`` and polars' sums add
pairwise, here scene by scene): the point estimates of means of non-integer values (the
closed loop's ``score`` and the paired ``score`` and ``progress_ratio`` differences),
its ``mean_agents`` and ``time_headway_below_1s_s``.

Distinct egos (``distinct_egos``, ``changed_egos``) are counted per part: the jobs write
all rows of an ego into one part (a scene's open loop is one task; a closed-loop ego
runs in one task).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import pathlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import polars as pl

from outputs.atomic import atomic_write
from replay.analysis.planner_eval import metrics
from replay.analysis.planner_eval.open_loop import ALL_AGENTS
from risk.evaluation import percentile_interval, scene_draws
from risk.order_statistics import OrderStatistics, median_ranks, quantile_ranks

Key = tuple[Any, ...]
#: One pass over a table: the columns wanted (None: all) -> its pieces (each holds
#: whole egos).
Frames = Callable[[Sequence[str] | None], Iterable[pl.DataFrame]]

#: Agent-count bins of the timing table (others in the frame).
COUNT_BINS = (0, 10, 25, 50, 100, 10**9)
#: The changed share is also reported at these tolerances (m) ...
SHIFT_TOLERANCES_M = (0.5, 1.0, 2.0)
#: ... and at a speed-scaled one: the distance the ego travels in this time (one
#: re-planning period at 10 Hz), at least the run's tolerance. A plan shifted by less is
#: the same plan executed a re-planning period earlier or later.
SPEED_SCALED_S = 0.1
#: At most this many points per planner and filter in the planning-time scatter: with
#: more, every k-th row (key order; k the smallest that keeps at most this many). A
#: deterministic subsample, the same on any engine and in any finishing order.
PLOT_POINTS = 20_000

#: Rows per row group of a merged table: what its writer holds at once (polars' default,
#: 512**2 rows, would hold a corpus of that many rows whole).
MERGED_ROW_GROUP_ROWS = 20_000
#: At most this many grid bins per summarised quantity (medians and p95: about 35 per
#: planner and filter): ~320 kB of counts each; a bin is then at least 2**-10 of its
#: value wide over eight powers of two, and the second pass keeps the values of the bins
#: that hold the medians and p95s only.
VALUE_BINS = 1 << 13
#: The plans table's columns a summary reads.
PLAN_SUMMARY_COLUMNS = (
    "scene", "dataset", "planner", "ego_id", "frame", "filter", "n_others", "n_agents",
    "filter_ms", "plan_ms", "plan_ok", "changed", "max_shift_m", "why", "blocking_dropped",
    "ego_speed_mps", "changed_1s", "unsafe",
)  # fmt: skip


# ---------------------------------------------------------------------- the parts
@dataclasses.dataclass(frozen=True)
class TableParts:
    """A table written as part files (scenes in key order; several planners one after
    the other): read lazily, written by streaming."""

    files: tuple[pathlib.Path, ...] = ()

    def is_empty(self) -> bool:
        return not self.files

    def schema(self) -> pl.Schema:
        """The columns and types of :meth:`scan` (from the files' schemas only)."""
        return self.scan().collect_schema()

    def scan(self) -> pl.LazyFrame:
        """The parts as one lazy table (columns a part lacks are null; types widened), as
        a diagonal concatenation of the parts."""
        if not self.files:
            return pl.DataFrame().lazy()
        return pl.concat([pl.scan_parquet(f) for f in self.files], how="diagonal_relaxed")

    def collect(self) -> pl.DataFrame:
        """The whole table (small tables, tests)."""
        return self.scan().collect()

    def frames(self, columns: Sequence[str] | None) -> Iterator[pl.DataFrame]:
        """One part at a time, ``columns`` only (None: all; those no part has are left
        out), with :meth:`scan`'s types: a part without a column that others have reads
        it as nulls, as the concatenation does."""
        union = self.schema()
        wanted = list(union) if columns is None else [c for c in columns if c in union]
        for path in self.files:
            own = pl.read_parquet_schema(path)
            df = pl.read_parquet(path, columns=[c for c in wanted if c in own])
            yield df.select(
                pl.col(c).cast(union[c]) if c in own else pl.lit(None, dtype=union[c]).alias(c)
                for c in wanted
            )

    def write(self, path: pathlib.Path) -> pathlib.Path:
        """The table into ``path`` (:meth:`scan`'s rows), streamed (never collected),
        atomically: a temporary file beside it, renamed into place when complete. The
        writer holds one row group (:data:`MERGED_ROW_GROUP_ROWS` rows) at a time."""
        if not self.files:
            return atomic_write(path, pl.DataFrame().write_parquet)
        lazy = self.scan()
        return atomic_write(
            path, lambda tmp: lazy.sink_parquet(tmp, row_group_size=MERGED_ROW_GROUP_ROWS)
        )


def frames_of(df: pl.DataFrame) -> Frames:
    """A table in memory as one piece (library callers with rows at hand)."""
    return lambda columns: [df if columns is None else df.select(c for c in columns if c in df)]


# ---------------------------------------------------------------------- per-scene sums
@functools.lru_cache(maxsize=2)  # most shares resample the same scenes; (B, S) each
def _draws(n_scenes: int, n_boot: int, seed: int) -> np.ndarray:
    draws = scene_draws(n_scenes, n_boot=n_boot, seed=seed)
    draws.setflags(write=False)
    return draws


@dataclasses.dataclass
class SceneSums:
    """Per scene (by name): the sum of values in row order and the number of rows."""

    total: dict[str, float] = dataclasses.field(default_factory=dict)
    rows: dict[str, int] = dataclasses.field(default_factory=dict)

    def add(self, scenes: np.ndarray, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64)
        if v.size == 0:
            return
        names, codes = np.unique(np.asarray(scenes), return_inverse=True)
        codes = codes.reshape(-1)
        sums = np.bincount(codes, weights=v, minlength=names.size)  # in row order per scene
        rows = np.bincount(codes, minlength=names.size)
        for code, name in enumerate(names.tolist()):
            if name in self.total:  # a scene seen before goes on adding, in row order
                own = np.concatenate(([self.total[name]], v[codes == code]))
                self.total[name] = float(np.cumsum(own)[-1])
            else:
                self.total[name] = float(sums[code])
            self.rows[name] = self.rows.get(name, 0) + int(rows[code])

    @property
    def n(self) -> int:
        return sum(self.rows.values())

    def replicates(self, *, n_boot: int, seed: int) -> np.ndarray:
        """The scene bootstrap's replicates of the mean (scenes in name order)."""
        names = sorted(self.rows)
        sums = np.array([self.total[k] for k in names], dtype=np.float64)
        rows = np.array([self.rows[k] for k in names], dtype=np.float64)
        draws = _draws(len(names), n_boot, seed)
        with np.errstate(invalid="ignore", divide="ignore"):
            return (draws @ sums) / (draws @ rows)

    def share(self, *, n_boot: int, seed: int) -> dict[str, Any]:
        """Share of True (the values are 0 or 1) with a 95 % scene-bootstrap interval."""
        n = self.n
        if n == 0:
            return {"share": None, "ci95": None, "n": 0, "count": 0}
        lo, hi = percentile_interval(self.replicates(n_boot=n_boot, seed=seed))
        count = round(sum(self.total.values()))
        return {"share": count / n, "ci95": [lo, hi], "n": n, "count": count}

    def mean(self, *, n_boot: int, seed: int) -> dict[str, Any]:
        """Mean with a 95 % scene-bootstrap interval (scenes resampled whole)."""
        n = self.n
        if n == 0:
            return {"mean": None, "ci95": None, "n": 0}
        lo, hi = percentile_interval(self.replicates(n_boot=n_boot, seed=seed))
        total = float(np.sum([self.total[k] for k in sorted(self.total)]))
        return {"mean": total / n, "ci95": [lo, hi], "n": n}


def share_with_interval(
    hits: np.ndarray, scenes: np.ndarray, *, n_boot: int, seed: int
) -> dict[str, Any]:
    """Share of True in ``hits`` with a 95 % scene-bootstrap interval."""
    sums = SceneSums()
    sums.add(scenes, np.asarray(hits, dtype=bool))
    return sums.share(n_boot=n_boot, seed=seed)


# ---------------------------------------------------------------------- two passes
class Tally:
    """What the passes over a table add up, keyed by tuples: totals, per-scene sums,
    values (their medians and p95), names in order of first appearance and first
    values. In the second pass (:meth:`second_pass`) only values and plot points are
    taken: the per-part code runs unchanged in both."""

    def __init__(self) -> None:
        self.second = False
        self.totals: dict[Key, float] = {}
        self.sums: dict[Key, SceneSums] = {}
        self.stats: dict[Key, OrderStatistics] = {}
        self.names: dict[Key, list[Any]] = {}
        self.firsts: dict[Key, Any] = {}
        self.points: dict[Key, list[list[np.ndarray]]] = {}  # per column, its pieces
        self._seen: dict[Key, int] = {}

    def add(self, key: Key, n: float) -> None:
        if not self.second:
            self.totals[key] = self.totals.get(key, 0) + n

    def total(self, key: Key) -> Any:
        return self.totals.get(key, 0)

    def scenes(self, key: Key, scenes: np.ndarray, values: np.ndarray) -> None:
        if not self.second:
            self.sums.setdefault(key, SceneSums()).add(scenes, values)

    def values(self, key: Key, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64)
        v = v[np.isfinite(v)]  # as the full table's quantiles
        if not self.second:
            self.stats.setdefault(key, OrderStatistics(VALUE_BINS)).count(v)
        elif key in self.stats:
            self.stats[key].keep(v)

    def seen(self, key: Key, names: Iterable[Any]) -> None:
        if not self.second:
            known = self.names.setdefault(key, [])
            known.extend(n for n in names if n not in known)

    def first(self, key: Key, value: Any) -> None:
        if not self.second:
            self.firsts.setdefault(key, value)

    def sample(self, key: Key, *columns: np.ndarray) -> None:
        """Plot points: pass 1 counts them, pass 2 keeps every k-th (at most
        :data:`PLOT_POINTS`)."""
        n = int(columns[0].size)
        if not self.second:
            self.add(("points", *key), n)
            return
        step = max(1, math.ceil(self.total(("points", *key)) / PLOT_POINTS))
        start = self._seen.get(key, 0)
        self._seen[key] = start + n
        take = np.arange((-start) % step, n, step)
        kept = self.points.setdefault(key, [[] for _ in columns])
        for pieces, column in zip(kept, columns, strict=True):
            pieces.append(column[take])

    def sampled(self, key: Key, columns: int) -> list[np.ndarray]:
        """The plot points of ``key``: one array per column."""
        return [
            np.concatenate(p) if p else np.empty(0) for p in self.points.get(key, [[]] * columns)
        ]

    def second_pass(self) -> None:
        self.second = True
        for s in self.stats.values():
            s.want([*median_ranks(s.n), *quantile_ranks(s.n, 0.95)[:2]] if s.n else [])

    def quantiles(self, key: Key) -> dict[str, float | None]:
        s = self.stats.get(key)
        if s is None or s.n == 0:
            return {"median": None, "p95": None}
        return {"median": s.median(), "p95": s.quantile(0.95)}

    def median(self, key: Key) -> float | None:
        s = self.stats.get(key)
        return None if s is None else s.median()

    def share(self, key: Key, *, n_boot: int, seed: int) -> dict[str, Any]:
        return self.sums.get(key, SceneSums()).share(n_boot=n_boot, seed=seed)

    def mean_ci(self, key: Key, *, n_boot: int, seed: int) -> dict[str, Any]:
        return self.sums.get(key, SceneSums()).mean(n_boot=n_boot, seed=seed)

    def mean(self, key: Key) -> float:
        """Mean of the non-null values added as ``key + ("sum",)`` and ``("n",)``;
        0.0 when there is none (``x.mean() or 0.0``)."""
        n = self.total((*key, "n"))
        return float(self.total((*key, "sum")) / n) if n else 0.0


def two_passes(
    frames: Frames, columns: Sequence[str] | None, part: Callable[[pl.DataFrame, Tally], None]
) -> Tally:
    """Run ``part`` over every piece twice (see :class:`Tally`)."""
    tally = Tally()
    for df in frames(columns):
        part(df, tally)
    tally.second_pass()
    for df in frames(columns):
        part(df, tally)
    return tally


def _np(series: pl.Series) -> np.ndarray:
    return series.to_numpy()


def _count(series: pl.Series) -> int:
    """True values of a boolean column (nulls not counted)."""
    return int(series.sum() or 0)


# ---------------------------------------------------------------------- open loop
_KEY = ["scene", "ego_id", "frame"]


def _open_loop_part(df: pl.DataFrame, t: Tally) -> None:
    """One piece of one planner's plans table."""
    if df.is_empty():
        return
    t.first(("planner",), str(df["planner"][0]))
    t.add(("distinct_egos",), df.select(["scene", "ego_id"]).unique().height)
    reference = df.filter(pl.col("filter") == ALL_AGENTS).select(
        [*_KEY, pl.col("plan_ms").alias("all_plan_ms"), pl.col("plan_ok").alias("all_ok"),
         pl.col("n_agents").alias("all_agents")]
    )  # fmt: skip
    t.add(("all", "ok", "sum"), _count(reference["all_ok"]))
    t.add(("all", "ok", "n"), reference["all_ok"].count())
    t.add(("all", "agents", "sum"), int(reference["all_agents"].sum() or 0))
    t.add(("all", "agents", "n"), reference["all_agents"].count())
    t.values(("all", "plan_ms"), _np(reference.filter(pl.col("all_ok"))["all_plan_ms"]))
    names = df["filter"].unique(maintain_order=True).to_list()
    t.seen(("filters",), names)
    for name in names:
        if name != ALL_AGENTS:
            _filter_part(name, df.filter(pl.col("filter") == name).join(reference, on=_KEY,
                         how="left"), t)  # fmt: skip
    ok = df.filter(pl.col("plan_ok"))
    for name in ok["filter"].unique(maintain_order=True).to_list():
        rows = ok.filter(pl.col("filter") == name)
        t.seen(("plotted",), [name])
        t.sample((name,), _np(rows["n_others"]), _np(rows["filter_ms"] + rows["plan_ms"]))


def _filter_part(name: str, rows: pl.DataFrame, t: Tally) -> None:
    """One filter's rows of a piece, each with its all-agents plan's columns."""
    f = (name,)
    comparable = rows.filter(pl.col("changed").is_not_null())
    both_ok = rows.filter(pl.col("plan_ok") & pl.col("all_ok"))
    blocking = rows.filter(pl.col("blocking_dropped").is_not_null())
    changed = comparable.filter(pl.col("changed"))
    t.add((*f, "rows"), rows.height)
    t.add((*f, "kept", "sum"), int(rows["n_agents"].sum() or 0))
    t.add((*f, "kept", "n"), rows["n_agents"].count())
    t.add((*f, "ok", "sum"), _count(rows["plan_ok"]))
    t.add((*f, "ok", "n"), rows["plan_ok"].count())
    t.add((*f, "comparable"), comparable.height)
    t.scenes((*f, "changed"), _np(comparable["scene"]), _np(comparable["changed"]).astype(bool))
    if "unsafe" in rows.columns:
        _safety_part(f, rows, comparable, t)
    kinds = changed["why"].str.split(" ").list.first().str.strip_chars(":")
    for kind, n in kinds.value_counts().iter_rows():
        t.add((*f, "why", str(kind)), int(n))
    shifted = changed.filter(pl.col("why").str.starts_with("shift"))
    t.values((*f, "changed_shift_m"), _np(shifted["max_shift_m"]))
    t.add((*f, "changed_egos"), changed.select(["scene", "ego_id"]).unique().height)
    t.scenes((*f, "blocking"), _np(blocking["scene"]),
             _np(blocking["blocking_dropped"]).astype(bool))  # fmt: skip
    t.values((*f, "filter_ms"), _np(rows["filter_ms"]))
    t.values((*f, "filtered_plan_ms"), _np(both_ok["plan_ms"]))
    t.values((*f, "filter_plus_plan_ms"), _np(both_ok["filter_ms"] + both_ok["plan_ms"]))
    t.values((*f, "all_agents_plan_ms"), _np(both_ok["all_plan_ms"]))
    counts = _np(both_ok["n_others"])
    for lo, hi in itertools.pairwise(COUNT_BINS):
        inside = (counts >= lo) & (counts < hi)
        if not inside.any():
            continue
        part = both_ok.filter(pl.Series(inside))
        b = (*f, "bin", lo)
        t.add((*b, "rows"), int(inside.sum()))
        t.values((*b, "all"), _np(part["all_plan_ms"]))
        t.values((*b, "total"), _np(part["filter_ms"] + part["plan_ms"]))
        t.add((*b, "changed", "sum"), _count(part["changed"]))
        t.add((*b, "changed", "n"), part["changed"].count())
    for (dataset,), d in rows.group_by(["dataset"]):
        k = (*f, "dataset", str(dataset))
        t.seen((*f, "datasets"), [str(dataset)])
        t.add((*k, "rows"), d.height)
        t.add((*k, "changed", "sum"), _count(d["changed"]))
        t.add((*k, "changed", "n"), d["changed"].count())
        t.add((*k, "kept", "sum"), int(d["n_agents"].sum() or 0))
        t.add((*k, "kept", "n"), d["n_agents"].count())
        t.add((*k, "others", "sum"), int(d["n_others"].sum() or 0))
        t.add((*k, "others", "n"), d["n_others"].count())


def _safety_part(f: Key, rows: pl.DataFrame, comparable: pl.DataFrame, t: Tally) -> None:
    """The changed share at other tolerances, ``changed_1s`` and ``unsafe``: per scene."""
    scenes = _np(comparable["scene"])
    changed = _np(comparable["changed"]).astype(bool)
    decision = ~_np(comparable["why"].fill_null("").str.starts_with("shift"))
    shift = np.nan_to_num(_np(comparable["max_shift_m"]).astype(np.float64), nan=np.inf)
    tolerance = SHIFT_TOLERANCES_M[0]
    speed = _np(comparable["ego_speed_mps"]).astype(np.float64)
    scaled = np.maximum(tolerance, SPEED_SCALED_S * np.nan_to_num(speed))
    for tol in SHIFT_TOLERANCES_M:
        t.scenes((*f, "at", f"{tol:g}"), scenes, changed & (decision | (shift > tol)))
    t.scenes((*f, "at", "speed_scaled"), scenes, changed & (decision | (shift > scaled)))
    first = rows.filter(pl.col("changed_1s").is_not_null())
    judged = rows.filter(pl.col("unsafe").is_not_null())
    t.scenes((*f, "changed_1s"), _np(first["scene"]), _np(first["changed_1s"]).astype(bool))
    t.scenes((*f, "unsafe"), _np(judged["scene"]), _np(judged["unsafe"]).astype(bool))


@dataclasses.dataclass(frozen=True)
class PlotPoints:
    """The planning-time scatter of one planner: per filter (in order), the others in
    the frame and the filter's plus the plan's time of at most :data:`PLOT_POINTS`
    rows where the plan exists."""

    planner: str
    filters: tuple[tuple[str, np.ndarray, np.ndarray], ...]


def summarize_plans(
    frames: Frames, base: dict[str, Any], *, n_boot: int = 1000, seed: int = 0
) -> tuple[dict[str, Any], PlotPoints | None]:
    """One planner's open-loop summary (``replay plan``'s ``summary.json``) from its
    plans table's pieces, and its plot points; ``base``: what the jobs' partials add up
    to (scenes, ego-frames, skipped egos ...), the summary's first keys."""
    t = two_passes(frames, PLAN_SUMMARY_COLUMNS, _open_loop_part)
    out: dict[str, Any] = {**base, "distinct_egos": 0, "filters": {}, "by_agent_count": {}}
    if ("planner",) not in t.firsts:
        return out, None
    out["planner"] = t.firsts[("planner",)]
    out["distinct_egos"] = int(t.total(("distinct_egos",)))
    out["all_agents"] = {
        "plan_ok_share": t.mean(("all", "ok")),
        "mean_agents": t.mean(("all", "agents")),
        "plan_ms": t.quantiles(("all", "plan_ms")),
    }
    boot = {"n_boot": n_boot, "seed": seed}
    for name in t.names.get(("filters",), []):
        if name == ALL_AGENTS:
            continue
        f = (name,)
        total, every = (
            t.quantiles((*f, "filter_plus_plan_ms")),
            t.quantiles((*f, "all_agents_plan_ms")),
        )
        ratio = None
        if total["median"] is not None and every["median"] is not None and every["median"] > 0:
            ratio = float(total["median"] / every["median"])
        changed = t.sums.get((*f, "changed"), SceneSums())
        out["filters"][name] = {
            "ego_frames": int(t.total((*f, "rows"))),
            "mean_kept": t.mean((*f, "kept")),
            "plan_ok_share": t.mean((*f, "ok")),
            "not_comparable": int(t.total((*f, "rows")) - t.total((*f, "comparable"))),
            "changed": changed.share(**boot),
            **_safety(t, f, boot),
            "changed_scenes": sum(1 for v in changed.total.values() if v > 0),
            "changed_why": _why(t, f),
            "changed_shift_m": t.quantiles((*f, "changed_shift_m")),
            "changed_egos": int(t.total((*f, "changed_egos"))),
            "blocking_agent_dropped": t.share((*f, "blocking"), **boot),
            "filter_ms": t.quantiles((*f, "filter_ms")),
            "filtered_plan_ms": t.quantiles((*f, "filtered_plan_ms")),
            "filter_plus_plan_ms": total,
            "all_agents_plan_ms": every,
            "median_time_ratio": ratio,
        }
        out["by_agent_count"][name] = [
            {
                "agents": f"{lo}-{hi - 1}" if hi < 10**9 else f"{lo}+",
                "ego_frames": int(t.total((*f, "bin", lo, "rows"))),
                "all_agents_plan_ms": t.quantiles((*f, "bin", lo, "all")),
                "filter_plus_plan_ms": t.quantiles((*f, "bin", lo, "total")),
                "changed_share": t.mean((*f, "bin", lo, "changed")),
            }
            for lo, hi in itertools.pairwise(COUNT_BINS)
            if t.total((*f, "bin", lo, "rows"))
        ]
        out.setdefault("by_dataset", {})[name] = {
            d: {
                "ego_frames": int(t.total((*f, "dataset", d, "rows"))),
                "changed_share": (
                    t.mean((*f, "dataset", d, "changed"))
                    if t.total((*f, "dataset", d, "changed", "n"))
                    else None
                ),
                "mean_kept": t.mean((*f, "dataset", d, "kept")),
                "mean_others": t.mean((*f, "dataset", d, "others")),
            }
            for d in sorted(t.names.get((*f, "datasets"), []))
        }
    points = PlotPoints(
        planner=out["planner"],
        filters=tuple((name, *t.sampled((name,), 2)) for name in t.names.get(("plotted",), [])),
    )
    return out, points


def _safety(t: Tally, f: Key, boot: dict[str, int]) -> dict[str, Any]:
    """Empty for tables without the safety columns (runs before issue 37) or without a
    comparable frame, as the full-table summary."""
    if (*f, "unsafe") not in t.sums or not t.total((*f, "comparable")):
        return {}
    at = {f"{tol:g}": t.share((*f, "at", f"{tol:g}"), **boot) for tol in SHIFT_TOLERANCES_M}
    at["speed_scaled"] = t.share((*f, "at", "speed_scaled"), **boot)
    return {
        "changed_at": at,
        "changed_1s": t.share((*f, "changed_1s"), **boot),
        "unsafe": t.share((*f, "unsafe"), **boot),
    }


def _why(t: Tally, f: Key) -> dict[str, int]:
    """How many changed frames each rule caught first, most first (ties by name)."""
    counts = {k[-1]: int(n) for k, n in t.totals.items() if k[: len(f) + 1] == (*f, "why")}
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


# ---------------------------------------------------------------------- closed loop
_CLASSES = ("stopped_ego", "stopped_track", "front", "rear_end", "lateral")
_PAIRED = ("at_fault_collisions", "score", "progress_ratio")


def _closed_loop_part(df: pl.DataFrame, t: Tally) -> None:
    """One piece of one planner's closed-loop table."""
    if df.is_empty():
        return
    key = ["scene", "ego_id"]
    reference = df.filter(pl.col("filter") == ALL_AGENTS)
    t.first(("agents",), str(df["agents"][0]) if "agents" in df.columns else "log")
    t.first(("tracker",), str(df["tracker"][0]) if "tracker" in df.columns else "perfect")
    t.add(("runs",), reference.height)
    t.add(("distinct_egos",), reference.select(key).unique().height)
    t.scenes(("scenes",), _np(reference["scene"]), np.zeros(reference.height))
    for dataset, n in reference["dataset"].value_counts().iter_rows():
        t.seen(("datasets",), [str(dataset)])
        t.add(("dataset", str(dataset)), int(n))
    names = df["filter"].unique(maintain_order=True).to_list()
    t.seen(("filters",), names)
    for name in names:
        rows = df.filter(pl.col("filter") == name)
        f = (name,)
        scenes = _np(rows["scene"])
        t.add((*f, "runs"), rows.height)
        for column in ("collisions", "at_fault_collisions", "plan_failures",
                       *(f"{c}_collisions" for c in _CLASSES)):  # fmt: skip
            t.add((*f, column), int(rows[column].sum() or 0))
        t.add((*f, "runs_with_collision"), int((rows["collisions"] > 0).sum()))
        t.scenes((*f, "runs_at_fault"), scenes, _np(rows["at_fault_collisions"] > 0))
        t.scenes((*f, "score"), scenes, _np(rows["score"]))
        t.add((*f, "drivable_area_fails"), int((rows["drivable_area_ok"] == False).sum()))  # noqa: E712
        t.add((*f, "ttc_below_bound"), int((rows["min_ttc_s"] < metrics.LEAST_TTC_S).sum()))
        t.add((*f, "uncomfortable"), int((~rows["comfortable"]).sum()))
        t.add((*f, "headway"), float(rows["time_headway_below_1s_s"].sum()))
        agents = rows["mean_agents"].drop_nulls()
        t.add((*f, "agents", "sum"), float(agents.sum()))
        t.add((*f, "agents", "n"), agents.len())
        for column in ("progress_ratio", "min_gap_m", "progress_m", "plan_ms_median",
                       "plan_ms_p95"):  # fmt: skip
            t.values((*f, column), _np(rows[column]))
        if name == ALL_AGENTS:
            continue
        paired = rows.join(reference, on=key, suffix="_all", maintain_order="left")
        pair_scenes = _np(paired["scene"])
        t.add((*f, "pairs"), paired.height)
        for column in _PAIRED:
            difference = (paired[column] - paired[f"{column}_all"]).cast(pl.Float64)
            t.scenes((*f, "difference", column), pair_scenes, _np(difference))
        for column, label in (("collisions", "collisions"), ("at_fault_collisions", "at_fault")):
            t.add((*f, "more", label), int((paired[column] > paired[f"{column}_all"]).sum()))
            t.add((*f, "fewer", label), int((paired[column] < paired[f"{column}_all"]).sum()))
        t.values((*f, "progress_change_m"), _np(paired["progress_m"] - paired["progress_m_all"]))
        t.values((*f, "min_gap_change_m"), _np(paired["min_gap_m"] - paired["min_gap_m_all"]))


def summarize_closed_loop(frames: Frames, *, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
    """Per filter: collisions by class, at-fault collisions (runs with one, with a 95 %
    scene-bootstrap interval), score, progress, TTC, comfort, planning time; and the
    paired differences against the all-agents run of the same ego (at-fault collisions,
    score, progress ratio) with 95 % scene-bootstrap intervals. From the closed-loop
    table's pieces."""
    t = two_passes(frames, None, _closed_loop_part)
    if ("agents",) not in t.firsts:
        return {"runs": 0, "filters": {}}
    boot = {"n_boot": n_boot, "seed": seed}
    datasets = {d: int(t.total(("dataset", d))) for d in t.names.get(("datasets",), [])}
    out: dict[str, Any] = {
        "runs": int(t.total(("runs",))),
        "distinct_egos": int(t.total(("distinct_egos",))),
        "scenes": len(t.sums.get(("scenes",), SceneSums()).rows),
        "datasets": dict(sorted(datasets.items(), key=lambda kv: (-kv[1], kv[0]))),
        "agents": t.firsts[("agents",)],
        "tracker": t.firsts[("tracker",)],
        "filters": {},
    }
    for name in t.names.get(("filters",), []):
        f = (name,)
        entry: dict[str, Any] = {
            "runs": int(t.total((*f, "runs"))),
            "collisions": int(t.total((*f, "collisions"))),
            "rear_end_collisions": int(t.total((*f, "rear_end_collisions"))),
            "collisions_by_class": {c: int(t.total((*f, f"{c}_collisions"))) for c in _CLASSES},
            "at_fault_collisions": int(t.total((*f, "at_fault_collisions"))),
            "runs_with_collision": int(t.total((*f, "runs_with_collision"))),
            "runs_at_fault": t.share((*f, "runs_at_fault"), **boot),
            "score": t.mean_ci((*f, "score"), **boot),
            "progress_ratio": t.quantiles((*f, "progress_ratio")),
            "drivable_area_fails": int(t.total((*f, "drivable_area_fails"))),
            "ttc_below_bound": int(t.total((*f, "ttc_below_bound"))),
            "uncomfortable": int(t.total((*f, "uncomfortable"))),
            "min_gap_m": t.quantiles((*f, "min_gap_m")),
            "time_headway_below_1s_s": float(t.total((*f, "headway"))),
            "progress_m": t.quantiles((*f, "progress_m")),
            "plan_ms_median": t.median((*f, "plan_ms_median")),
            "plan_ms_p95": t.median((*f, "plan_ms_p95")),
            "mean_agents": t.mean((*f, "agents")),
            "plan_failures": int(t.total((*f, "plan_failures"))),
        }
        if name != ALL_AGENTS:
            entry["paired"] = {
                "runs": int(t.total((*f, "pairs"))),
                "more_collisions": int(t.total((*f, "more", "collisions"))),
                "fewer_collisions": int(t.total((*f, "fewer", "collisions"))),
                "more_at_fault": int(t.total((*f, "more", "at_fault"))),
                "fewer_at_fault": int(t.total((*f, "fewer", "at_fault"))),
                "at_fault_difference": t.mean_ci((*f, "difference", "at_fault_collisions"), **boot),
                "score_difference": t.mean_ci((*f, "difference", "score"), **boot),
                "progress_ratio_difference": t.mean_ci(
                    (*f, "difference", "progress_ratio"), **boot
                ),
                "progress_change_m": t.quantiles((*f, "progress_change_m")),
                "min_gap_change_m": t.quantiles((*f, "min_gap_change_m")),
            }
        out["filters"][name] = entry
    return out

"""What a guarantee-calibrated stage keeps in dense frames, for several candidate scores.

Usage::

    .venv/bin/python benchmarks/stage_tail.py CACHE --report calibration.json [--no-learned]

``CACHE`` is the ``--scores-cache`` folder of a ``replay calibrate --reference planner``
run and ``calibration.json`` its ``--report`` (for the held-out sites). Every candidate
runs after the corridor stage (its agents kept, those it puts behind dropped) and behind
the reachability bound, and gets the threshold of the shipped rule at ``k = 0``: the
least score of a planner-important agent over every calibration scene (the order
statistic that A = 0.02 at C = 0.95 takes with 183 scene units; path distance also with
one and three scenes below, what 236 and 386 units would allow). Reported on the held-out
sites: agents kept per ego-frame, in all ego-frames and in dense ones (``--dense`` or
more others), and the planner-important agents dropped.

Candidates:

- ``path distance``, ``trajectory distance``: the shipped stage and the runner-up;
- ``path and trajectory``: both at their own thresholds. Not a valid guarantee at A:
  two thresholds chosen apart need A/2 each (Bonferroni), 299 units at 1 %;
- ``learned``, ``learned, monotone`` (needs scikit-learn, not a project dependency):
  gradient-boosted trees (depth 3) on the log of the nine risk scores, the centre
  distance, the agent's kind and the corridor's behind flag; the calibration scores are
  cross-fitted (each site scored by trees fitted on the other sites), which approximates
  but does not give the finite-sample guarantee; the monotone variant constrains the
  score to grow with every risk and to fall with distance;
- ``oracle``: the corridor's agents and exactly the planner-important ones (what no
  stage after the corridor can beat).

Writes ``benchmarks/results/stage_tail.md``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import platform
import sys
from collections.abc import Callable

import numpy as np
import polars as pl

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from replay.analysis.planner_calibration import ScorePart  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "stage_tail.md"
PLANNER_LABELS = ("label_idm", "label_fiss_plus", "label_pdm", "label_fop")
FRAME_KEYS = ["scene", "ego_id", "frame"]


def read_cache(cache: pathlib.Path) -> pl.DataFrame:
    """Every scene's scores with its corridor columns, the union label ``important``,
    and ``n_others`` per ego-frame."""
    frames = []
    for scores in sorted((cache / "parts" / "scores").rglob("*.parquet")):
        corridor = cache / "parts" / "corridor" / scores.relative_to(cache / "parts" / "scores")
        frames.append(
            ScorePart(scores.stem, scores, corridor if corridor.exists() else None).read()
        )
    if not frames:
        raise SystemExit(f"Error: {cache} holds no scores parts; pass a --scores-cache folder")
    df = pl.concat(frames, how="vertical_relaxed")
    labels = [c for c in PLANNER_LABELS if c in df.columns]
    important = pl.any_horizontal([pl.col(c).fill_null(False) for c in labels])
    df = df.with_columns(important.alias("important"))
    return df.join(df.group_by(FRAME_KEYS).agg(pl.len().alias("n_others")), on=FRAME_KEYS)


def features(df: pl.DataFrame) -> np.ndarray:
    risks = [c for c in df.columns if c.startswith("risk_")]
    logs = [np.log(np.clip(df[c].to_numpy(), 1e-300, None)) for c in risks]
    extra = [df["distance_m"].to_numpy(), df["kind"].to_numpy(), df["behind"].to_numpy()]
    x = np.column_stack([*logs, *[np.asarray(e, dtype=np.float64) for e in extra]])
    return np.nan_to_num(x, nan=-700.0, neginf=-700.0, posinf=700.0)


def learned_scores(df: pl.DataFrame, held: np.ndarray, monotone: bool) -> np.ndarray:
    """Cross-fitted scores on the calibration sites, and the scores of trees fitted on
    every calibration site for the held-out ones."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    x, y = features(df), df["important"].to_numpy().astype(bool)
    n_risks = sum(c.startswith("risk_") for c in df.columns)
    cst = [1] * n_risks + [-1, 0, -1] if monotone else None

    def fit(rows: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        model = HistGradientBoostingClassifier(
            max_depth=3, max_iter=200 if monotone else 100,
            learning_rate=0.05 if monotone else 0.1, monotonic_cst=cst, random_state=0,
        )  # fmt: skip
        model.fit(x[rows], y[rows])
        return lambda r: np.log(model.predict_proba(x[r])[:, 1] + 1e-300)

    site = df["site"].to_numpy()
    train = ~held & ~df["corridor"].to_numpy().astype(bool)
    out = np.full(df.height, np.nan)
    for s in np.unique(site[~held]):
        out[site == s] = fit(train & (site != s))(site == s)
    out[held] = fit(train)(held)
    return out


def evaluate(
    df: pl.DataFrame, held: np.ndarray, score: np.ndarray, dense: int, below: int = 0
) -> dict:
    """The threshold of ``score`` that leaves ``below`` calibration scenes with an
    important agent under it (the order statistic's ``k``), and what it keeps and drops
    on the held-out scenes."""
    corridor = df["corridor"].to_numpy().astype(bool)
    behind = df["behind"].to_numpy().astype(bool)
    reach = df["reachable"].to_numpy().astype(bool)
    important = df["important"].to_numpy().astype(bool)
    judged = important & reach & ~behind & ~corridor & ~held
    worst = (
        pl.DataFrame({"scene": df["scene"].to_numpy()[judged], "s": score[judged]})
        .group_by("scene")
        .agg(pl.col("s").min())
        .sort("s")["s"]
        .to_numpy()
    )
    threshold = float(worst[below]) if worst.size > below else np.inf
    keep = reach & ~behind & (corridor | (np.nan_to_num(score, nan=-np.inf) >= threshold))
    d = df.select([*FRAME_KEYS, "n_others"]).with_columns(
        pl.Series("keep", keep), pl.Series("miss", important & ~keep), pl.Series("held", held)
    )
    per_frame = (
        d.filter(pl.col("held"))
        .group_by([*FRAME_KEYS, "n_others"])
        .agg(pl.col("keep").sum(), pl.col("miss").sum())
    )
    crowd = per_frame.filter(pl.col("n_others") >= dense)
    return {
        "threshold": threshold,
        "kept": per_frame["keep"].mean(),
        "others": per_frame["n_others"].mean(),
        "dense_kept": crowd["keep"].mean() if crowd.height else float("nan"),
        "dense_others": crowd["n_others"].mean() if crowd.height else float("nan"),
        "dense_frames": crowd.height,
        "dropped": int(per_frame["miss"].sum()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cache", type=pathlib.Path)
    ap.add_argument("--report", type=pathlib.Path, required=True)
    ap.add_argument("--dense", type=int, default=50)
    ap.add_argument("--learned", action=argparse.BooleanOptionalAction, default=True)
    args = ap.parse_args()
    try:
        held_sites = json.loads(args.report.read_text())["held_out_sites"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(
            f"Error: {args.report}: not a calibration report with held-out sites ({exc!r}); "
            "pass the --report of a `replay calibrate --holdout auto` run"
        ) from None
    df = read_cache(args.cache)
    held = df["site"].is_in(held_sites).to_numpy()
    path = df["risk_path_distance"].to_numpy()
    traj = df["risk_trajectory_distance"].to_numpy()
    candidates: dict[str, np.ndarray] = {
        "path distance (shipped)": path,
        "trajectory distance": traj,
    }
    rows = {name: evaluate(df, held, s, args.dense) for name, s in candidates.items()}
    tp, tt = rows["path distance (shipped)"]["threshold"], rows["trajectory distance"]["threshold"]
    both = np.where((path >= tp) & (traj >= tt), 1.0, 0.0)  # each at its own threshold
    rows["path and trajectory (Bonferroni needed)"] = evaluate(df, held, both, args.dense)
    # What more scene units would allow: at A = 2 %, C = 95 %, k scenes may fall below
    # the threshold with n >= 236 (k = 1) or 386 (k = 3) units.
    for k, units in ((1, 236), (3, 386)):
        name = f"path distance, {k} scene(s) below ({units} units)"
        rows[name] = evaluate(df, held, path, args.dense, below=k)
    if args.learned:
        try:
            for monotone in (False, True):
                name = "learned, monotone (cross-fitted)" if monotone else "learned (cross-fitted)"
                rows[name] = evaluate(df, held, learned_scores(df, held, monotone), args.dense)
        except ImportError:
            print("scikit-learn is missing (pip install scikit-learn): learned rows left out")
    oracle = df["important"].to_numpy().astype(float)
    rows["oracle: the corridor's and the important agents"] = evaluate(df, held, oracle, args.dense)

    lines = [
        "# What a guarantee-calibrated stage keeps in dense frames",
        "",
        f"Written by `benchmarks/stage_tail.py` on {datetime.date.today().isoformat()} "
        f"({platform.machine()}, Python {platform.python_version()}). Command: "
        f"`python benchmarks/stage_tail.py {args.cache.name} --report {args.report.name}`.",
        "",
        f"Held-out sites: {', '.join(held_sites)}. Thresholds at k = 0 (unless a row says) over the "
        f"calibration scenes (after the corridor stage); kept and dropped on the held-out sites; dense: "
        f"{args.dense} or more others.",
        "",
        "| stage after the corridor | threshold | kept per ego-frame | dense: kept | "
        "dense ego-frames | important dropped |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['threshold']:.4g} | {r['kept']:.1f} of {r['others']:.1f} | "
            f"{r['dense_kept']:.1f} of {r['dense_others']:.1f} | {r['dense_frames']} | "
            f"{r['dropped']} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    RESULTS.write_text(text)
    print(f"Wrote {RESULTS}")


if __name__ == "__main__":
    main()

"""The sensitivity sweep streamed (issue 38): every variant evaluated from per-scene part
files, never from a whole table in memory; the variant parts against the in-memory
replacement (the oracle); the defaults' parts reused; the order of the parts."""

from __future__ import annotations

import math

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal
from test_sensitivity import FAST, paths, same, scene, sweep_aucs

from converters.scene.writer import write_scene
from replay.analysis.evaluation import sensitivity
from replay.analysis.evaluation.collect import collect_agents
from replay.analysis.evaluation.corpus import EvaluationError
from replay.analysis.evaluation.sensitivity import (
    Variant,
    replace_risks,
    run_sweep,
    variant_parts,
)
from replay.analysis.evaluation.streaming import evaluate_frame
from replay.analysis.stats.collect import TablesSettings, tables_job
from replay.jobs import resolve_inputs, run_jobs, scene_refs
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """test_sensitivity's three scenes in two folders."""
    root = tmp_path_factory.mktemp("sweep_streamed")
    for folder, name, crossing in (
        ("setA", "S_A-1_1", True), ("setA", "S_A-1_2", False), ("setB", "S_B-1_1", True),
    ):  # fmt: skip
        (root / folder).mkdir(exist_ok=True)
        write_scene(root / folder / f"{name}.mcap", scene(crossing=crossing))
    return root


def parts_of(keys_rows: dict[str, pl.DataFrame], folder) -> dict[str, object]:
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for k, (key, df) in enumerate(keys_rows.items()):
        out[key] = folder / f"{k}.parquet"
        df.write_parquet(out[key])
    return out


def hand_scene(name: str, rng: np.random.Generator) -> tuple[pl.DataFrame, pl.DataFrame]:
    n = 7
    base = pl.DataFrame({
        "scene": [name] * n, "ego_id": [0] * n, "frame": list(range(n)),
        "agent_id": [3] * n, "risk_gaussian": rng.random(n), "risk_circles": rng.random(n),
        "baseline": rng.random(n) < 0.5,
    })  # fmt: skip
    variant = base.select("scene", "ego_id", "frame", "agent_id").with_columns(
        pl.Series("risk_circles", rng.random(n))
    )
    return base, variant.sample(fraction=1.0, shuffle=True, seed=1)  # rows in another order


def test_variant_parts_equal_the_in_memory_replacement(tmp_path):
    rng = np.random.default_rng(0)
    scenes = {f"k{j}": hand_scene(f"k{j}", rng) for j in (2, 0, 1)}
    defaults = parts_of({k: b for k, (b, _) in scenes.items()}, tmp_path / "d")
    variant = parts_of({k: v for k, (_, v) in scenes.items()}, tmp_path / "v")
    merged = variant_parts(defaults, variant, ["circles"], tmp_path / "m")
    got = pl.concat([pl.read_parquet(p) for p in merged])
    whole_base = pl.concat([scenes[k][0] for k in sorted(scenes)])
    whole_new = pl.concat([scenes[k][1] for k in sorted(scenes)])
    assert_frame_equal(got, replace_risks(whole_base, whole_new, ["circles"]))
    # one scene per part file, in key order
    assert [pl.read_parquet(p)["scene"].unique().to_list() for p in merged] == [
        ["k0"],
        ["k1"],
        ["k2"],
    ]


def test_variant_parts_refuse_a_missing_scene(tmp_path):
    rng = np.random.default_rng(1)
    scenes = {f"k{j}": hand_scene(f"k{j}", rng) for j in range(2)}
    defaults = parts_of({k: b for k, (b, _) in scenes.items()}, tmp_path / "d")
    variant = parts_of({"k0": scenes["k0"][1]}, tmp_path / "v")
    with pytest.raises(EvaluationError, match="no scene k1"):
        variant_parts(defaults, variant, ["circles"], tmp_path / "m")


@pytest.fixture()
def one_scene_parts_only(monkeypatch):
    """Every evaluation of the sweep reads part files of one scene each (never a whole
    table): records the number of parts evaluated."""
    seen: list[int] = []
    real = sensitivity.evaluate_parts

    def spy(parts, *args, **kwargs):
        for p in parts:
            assert pl.read_parquet(p, columns=["scene"])["scene"].n_unique() == 1
        seen.append(len(parts))
        return real(parts, *args, **kwargs)

    monkeypatch.setattr(sensitivity, "evaluate_parts", spy)
    monkeypatch.setattr(sensitivity, "evaluate_frame", None, raising=False)
    return seen


VARIANTS = [
    Variant("baseline threshold", "1e-4", {"baseline.threshold": 1e-4}),
    Variant("tau_esc", "1.6 s", {"survival.escape_time_s": 1.6}),
    Variant("closest-encounter rule", "keep d_E",
            {"closest_encounter.encounter_time_max_s": math.inf}),
]  # fmt: skip


def test_every_variant_is_streamed_and_equals_the_in_memory_sweep(corpus, one_scene_parts_only):
    result = run_sweep(paths(corpus), settings=FAST, variants=VARIANTS)
    assert one_scene_parts_only == [3] * (1 + len(VARIANTS))  # defaults + each variant
    # the oracle: the variant's whole table in memory, evaluated at once
    base, datasets, hs = collect_agents(paths(corpus))
    for variant in VARIANTS:
        models = sensitivity.affected_models(variant.settings)
        agents = base
        if models:
            cascade = CascadeConfig.default().with_settings(variant.settings)
            new, _, _ = collect_agents(paths(corpus), cascade=cascade, models=models)
            agents = replace_risks(base, new, models)
        threshold = 1e-4 if "baseline.threshold" in variant.settings else FAST.baseline_threshold
        from dataclasses import replace

        summary = evaluate_frame(
            agents, settings=replace(FAST, baseline_threshold=threshold), datasets=datasets,
            hindsight=hs,
        )  # fmt: skip
        expected = {
            (m, ref): summary["models"][m].get(ref, {"auc": {"value": None}})["auc"]["value"]
            for m in summary["models"]
            for ref in ("survival", "hindsight")
        }
        same(sweep_aucs(result, variant.label), expected)


def test_defaults_parts_are_reused_not_replayed(corpus, tmp_path):
    found = resolve_inputs(paths(corpus))
    hs = HindsightSettings()
    job = tables_job(TablesSettings(cascade=CascadeConfig.default(), hindsight=hs))
    report = run_jobs(job, scene_refs(found), tmp_path / "run", workers=1, progress=False)
    datasets = {d.ref.key: d.ref.dataset for d in report.done}
    given_defaults = run_sweep(paths(corpus), defaults=report, datasets=datasets, settings=FAST,
                               variants=VARIANTS[:2])  # fmt: skip
    own = run_sweep(paths(corpus), settings=FAST, variants=VARIANTS[:2])
    assert_frame_equal(given_defaults.rows, own.rows)
    assert_frame_equal(given_defaults.variants, own.variants)


def test_order_of_the_defaults_parts_does_not_change_the_sweep(corpus, tmp_path):
    found = resolve_inputs(paths(corpus))
    job = tables_job(TablesSettings(cascade=CascadeConfig.default(), hindsight=HindsightSettings()))
    report = run_jobs(job, scene_refs(found), tmp_path / "run", workers=1, progress=False)
    datasets = {d.ref.key: d.ref.dataset for d in report.done}
    a = run_sweep(paths(corpus), defaults=report, datasets=datasets, settings=FAST,
                  variants=VARIANTS[1:2])  # fmt: skip
    report.done.reverse()
    b = run_sweep(paths(corpus), defaults=report, datasets=datasets, settings=FAST,
                  variants=VARIANTS[1:2])  # fmt: skip
    assert_frame_equal(a.rows, b.rows)

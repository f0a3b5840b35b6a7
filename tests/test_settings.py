"""``risk.settings``: the one parser of ``--set KEY=VALUE`` and of the cascade TOML's
``[params.<model>]`` / ``[prediction]`` tables; and the engine taking them."""

from __future__ import annotations

import math

import numpy as np
import polars as pl
import pytest

from converters.scene.writer import write_scene
from replay.core.engine import run_scene
from replay.core.tables import TableSink
from risk.cascade import CascadeConfig, CascadeConfigError
from risk.prediction import PredictionSettings
from risk.registry import BASELINE_THRESHOLD, MODELS
from risk.settings import (
    SettingsError,
    flatten_tables,
    parse_settings,
    valid_keys,
)
from tests.test_cli_evaluate import straight_scene


def test_defaults_are_the_papers():
    s = parse_settings([])
    assert s.params == {} and s.prediction == PredictionSettings()
    assert s.baseline_threshold == BASELINE_THRESHOLD == 1e-25
    assert s.params_or_none() is None and s.prediction_or_none() is None


def test_the_briefs_example():
    s = parse_settings(
        [
            "survival.escape_time_s=0.8",
            "closest_encounter.encounter_time_max_s=inf",
            "circles.radius_rule=width",
            "prediction.horizon_s=8",
            "prediction.vehicle.time_growth_lon_mps=0.2",
            "baseline.threshold=1e-4",
        ]
    )
    assert s.params["survival"].escape_time_s == 0.8
    assert s.params["closest_encounter"].encounter_time_max_s == math.inf
    assert s.params["circles"].radius_rule == "width"
    assert s.params["circles"].n_circles == 3  # untouched fields keep their defaults
    assert s.prediction.horizon_s == 8.0 and s.prediction.dt_s == 0.1
    assert s.prediction.uncertainty.vehicle.time_growth_lon_mps == 0.2
    assert s.prediction.uncertainty.pedestrian.time_growth_lon_mps == 0.0
    assert s.baseline_threshold == 1e-4
    assert set(s.params) == {"survival", "closest_encounter", "circles"}


def test_none_is_the_paper_rule_and_later_items_win():
    s = parse_settings(["headway.encounter_time_max_s=2", "headway.encounter_time_max_s=none"])
    assert s.params["headway"].encounter_time_max_s is None
    s = parse_settings(["circles.n_circles=5"])
    assert s.params["circles"].n_circles == 5 and isinstance(s.params["circles"].n_circles, int)


def test_settings_stack_on_a_base():
    base = parse_settings(["survival.escape_time_s=0.8"])
    s = parse_settings({"prediction.horizon_s": 6.0}, base=base)
    assert s.params["survival"].escape_time_s == 0.8 and s.prediction.horizon_s == 6.0
    assert s.overrides == {"survival.escape_time_s": 0.8, "prediction.horizon_s": 6.0}


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("survival.tau=1", "unknown setting 'survival.tau'; the keys of survival are: "),
        ("survival.escape_time=1", "did you mean survival.escape_time_s?"),
        ("nosuchmodel.epsilon_m=1", "unknown setting"),
        ("survival.escape_time_s", "is not KEY=VALUE"),
        ("=3", "is not KEY=VALUE"),
        ("survival.escape_time_s=fast", "survival.escape_time_s: 'fast' is not a number"),
        ("survival.escape_time_s=-1", "escape_time_s"),
        ("circles.radius_rule=huge", "radius_rule must be 'spec' or 'width'"),
        ("circles.n_circles=2.5", "is not a whole number"),
        ("prediction.horizon_s=0.55", "whole number of steps"),
        ("prediction.truck.growth_lon=1", "unknown setting"),
        ("baseline.threshold=-1", "baseline.threshold: must be a finite number >= 0"),
    ],
)
def test_bad_keys_and_values_are_one_line_errors(item, message):
    with pytest.raises(SettingsError) as err:
        parse_settings([item])
    text = str(err.value)
    assert message in text and "\n" not in text
    if "unknown setting" in message or "KEY=VALUE" in message or "did you" in message:
        # a hint, not all 55 keys (issue 31: the list hid the key the user meant)
        assert "survival.escape_time_s" in text or "did you mean" in text, text
        assert len(text) < 300, text


def test_valid_keys_cover_every_parameter():
    keys = valid_keys()
    for name, spec in MODELS.items():
        for f in spec.params_type.__dataclass_fields__:
            assert f"{name}.{f}" in keys
    assert "prediction.cyclist.time_growth_lat_mps" in keys and "baseline.threshold" in keys


def test_toml_tables_flatten_to_the_same_keys():
    data = {
        "baseline_threshold": 1e-6,
        "params": {"survival": {"escape_time_s": 1.2}, "closest_encounter": {"encounter_time_max_s": "none"}},
        "prediction": {"horizon_s": 8, "pedestrian": {"time_growth_lon_mps": 0.1}},
    }  # fmt: skip
    flat = flatten_tables(data)
    assert flat == {
        "survival.escape_time_s": 1.2,
        "closest_encounter.encounter_time_max_s": "none",
        "prediction.horizon_s": 8,
        "prediction.pedestrian.time_growth_lon_mps": 0.1,
        "baseline.threshold": 1e-6,
    }
    s = parse_settings(flat)
    assert s.params["survival"].escape_time_s == 1.2
    assert s.params["closest_encounter"].encounter_time_max_s is None
    assert s.prediction.horizon_s == 8.0 and s.baseline_threshold == 1e-6
    with pytest.raises(SettingsError, match="expected a number"):
        parse_settings({"survival.escape_time_s": True})


CASCADE = """
baseline_threshold = 1e-20
stages = [{ model = "path_distance", threshold = 0.02 }]
tiers = [{ name = "behavior", min_survival_risk = 1e-20 }]

[params.survival]
escape_time_s = 0.8

[prediction]
horizon_s = 8

[prediction.vehicle]
time_growth_lon_mps = 0.2
"""


def test_cascade_toml_tables_and_round_trip(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(CASCADE)
    c = CascadeConfig.from_toml(path)
    s = c.model_settings()
    assert s.params["survival"].escape_time_s == 0.8
    assert s.prediction.horizon_s == 8.0
    assert s.prediction.uncertainty.vehicle.time_growth_lon_mps == 0.2
    assert s.baseline_threshold == 1e-20
    again = tmp_path / "again.toml"
    again.write_text(c.to_toml_string())
    assert CascadeConfig.from_toml(again) == c
    # --set on top: the file's settings stay unless overridden
    d = c.with_settings(["survival.escape_time_s=1.6", "baseline.threshold=1e-4"])
    assert d.model_settings().params["survival"].escape_time_s == 1.6
    assert d.model_settings().prediction.horizon_s == 8.0
    assert d.baseline_threshold == 1e-4


def test_cascade_toml_bad_setting_names_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(CASCADE.replace("escape_time_s = 0.8", "escape = 0.8"))
    with pytest.raises(
        CascadeConfigError, match=r"bad.toml: params/prediction: unknown setting 'survival.escape'"
    ):
        CascadeConfig.from_toml(path)


def test_the_engine_takes_the_cascades_settings(tmp_path):
    scene = tmp_path / "s.mcap"
    write_scene(scene, straight_scene(crossing=True, duration_s=3.0))

    def risks(cascade):
        out = tmp_path / f"t{len(list(tmp_path.iterdir()))}.parquet"
        run_scene(scene, sinks=[TableSink(out)], cascade=cascade, progress=False)
        return pl.read_parquet(out)

    base = risks(CascadeConfig.default())
    changed = risks(CascadeConfig.default().with_settings(["survival.escape_time_s=1.6"]))
    np.testing.assert_array_equal(
        base["risk_gaussian"].to_numpy(), changed["risk_gaussian"].to_numpy()
    )
    assert not np.allclose(
        np.nan_to_num(base["risk_survival"].to_numpy()),
        np.nan_to_num(changed["risk_survival"].to_numpy()),
    )

"""Every baseline choice as a ``KEY=VALUE`` setting: one parser for the CLI's ``--set``
and the cascade TOML's ``[params.<model>]`` / ``[prediction]`` tables.

Keys (``valid_keys()`` lists them all):

- ``<model>.<field>``: a field of the model's parameter dataclass, e.g.
  ``survival.escape_time_s``, ``closest_encounter.encounter_time_max_s`` (``none`` = the
  paper's rule "0 while still closing at T", ``inf`` = keep d_E), ``circles.radius_rule``;
- ``prediction.horizon_s``, ``prediction.dt_s``, ``prediction.<kind>.<field>`` with kind
  ``vehicle``, ``pedestrian``, ``cyclist``, ``other`` and a field of
  :class:`risk.prediction.KindUncertainty` (e.g. ``prediction.vehicle.time_growth_lon_mps``);
- ``baseline.threshold``: the survival risk at or above which an agent is important.

Unset keys keep the paper's values. Pure: no I/O.
"""

from __future__ import annotations

import difflib
import math
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from risk.errors import RiskError
from risk.frame import Kind
from risk.prediction import KindUncertainty, PredictionSettings
from risk.registry import BASELINE_THRESHOLD, MODELS

KINDS = tuple(k.name.lower() for k in Kind)
BASELINE_KEY = "baseline.threshold"


class SettingsError(RiskError):
    """A setting key or value that is not valid (the message lists the valid keys)."""


@dataclass(frozen=True)
class ModelSettings:
    """What the settings set: per-model parameters (only the models a key touched),
    the prediction, the baseline threshold, and the ``key -> value`` overrides that made
    them (for provenance)."""

    params: Mapping[str, Any] = field(default_factory=dict)
    prediction: PredictionSettings = field(default_factory=PredictionSettings)
    baseline_threshold: float = BASELINE_THRESHOLD
    overrides: Mapping[str, Any] = field(default_factory=dict)

    @property
    def changes_prediction(self) -> bool:
        return self.prediction != PredictionSettings()

    def params_or_none(self) -> dict[str, Any] | None:
        return dict(self.params) or None

    def prediction_or_none(self) -> PredictionSettings | None:
        return self.prediction if self.changes_prediction else None


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}


def _key_types() -> dict[str, Any]:
    keys: dict[str, Any] = {}
    for name, spec in MODELS.items():
        for fname, ftype in _field_types(spec.params_type).items():
            keys[f"{name}.{fname}"] = ftype
    keys["prediction.horizon_s"] = float
    keys["prediction.dt_s"] = float
    for kind in KINDS:
        for fname, ftype in _field_types(KindUncertainty).items():
            keys[f"prediction.{kind}.{fname}"] = ftype
    keys[BASELINE_KEY] = float
    return keys


KEY_TYPES: dict[str, Any] = _key_types()


def valid_keys() -> list[str]:
    """Every key, in a stable order."""
    return list(KEY_TYPES)


def _keys_hint(wrong: str | None = None) -> str:
    """The closest one or two keys to ``wrong`` (a typo), else where the keys are listed:
    all 55 dumped on one line hid the one the user meant."""
    if wrong is not None:
        close = difflib.get_close_matches(wrong, KEY_TYPES, n=2, cutoff=0.6)
        if close:
            return "did you mean " + " or ".join(close) + "?"
        prefix = wrong.rpartition(".")[0]
        same = [k for k in KEY_TYPES if prefix and k.rpartition(".")[0] == prefix]
        if same:  # e.g. survival.wobble: the keys of that model
            shown = ", ".join(same[:6]) + (", ..." if len(same) > 6 else "")
            return f"the keys of {prefix} are: {shown}"
    groups = sorted({k.split(".")[0] for k in KEY_TYPES})
    return f"keys start with one of: {', '.join(groups)} (e.g. survival.escape_time_s)"


def _convert(key: str, value: Any, ftype: Any) -> Any:
    """``value`` (a string from the CLI or a TOML value) as the field's type."""
    args = typing.get_args(ftype)
    optional = (typing.get_origin(ftype) in (typing.Union, types.UnionType)) and type(None) in args
    base = next((a for a in args if a is not type(None)), ftype) if optional else ftype
    if isinstance(value, str):
        text = value.strip()
        if optional and text.lower() in ("none", "null", "paper"):
            return None
        if base is str:
            return text
        try:
            if base is int:
                return int(text)
            return float(text)
        except ValueError:
            raise SettingsError(
                f"{key}: {value!r} is not a {'whole number' if base is int else 'number'}"
                + ("; or 'none'" if optional else "")
            ) from None
    if base is str:
        if not isinstance(value, str):
            raise SettingsError(f"{key}: expected a string, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SettingsError(f"{key}: expected a number, got {value!r}")
    if base is int:
        if isinstance(value, float) and not value.is_integer():
            raise SettingsError(f"{key}: expected a whole number, got {value!r}")
        return int(value)
    return float(value)


def parse_assignment(text: str) -> tuple[str, str]:
    """``"KEY=VALUE"`` -> ``(key, value)``."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise SettingsError(f"{text!r} is not KEY=VALUE; {_keys_hint()}")
    return key.strip(), value.strip()


def flatten_tables(data: Mapping[str, Any]) -> dict[str, Any]:
    """The cascade TOML's tables as flat keys: ``[params.survival] escape_time_s`` ->
    ``survival.escape_time_s``; ``[prediction] horizon_s`` and ``[prediction.vehicle]
    growth_lon`` -> ``prediction.horizon_s``, ``prediction.vehicle.growth_lon``;
    a top-level ``baseline_threshold`` -> ``baseline.threshold``."""
    flat: dict[str, Any] = {}
    params = data.get("params", {})
    if not isinstance(params, Mapping):
        raise SettingsError("params: expected tables [params.<model>]")
    for model, table in params.items():
        if not isinstance(table, Mapping):
            raise SettingsError(f"params.{model}: expected a table [params.{model}]")
        for k, v in table.items():
            flat[f"{model}.{k}"] = v
    prediction = data.get("prediction", {})
    if not isinstance(prediction, Mapping):
        raise SettingsError("prediction: expected a table [prediction]")
    for k, v in prediction.items():
        if isinstance(v, Mapping):
            for kk, vv in v.items():
                flat[f"prediction.{k}.{kk}"] = vv
        else:
            flat[f"prediction.{k}"] = v
    if "baseline_threshold" in data:
        flat[BASELINE_KEY] = data["baseline_threshold"]
    return flat


def parse_settings(
    items: Mapping[str, Any] | Iterable[str] | None = None,
    *,
    base: ModelSettings | None = None,
) -> ModelSettings:
    """The settings of ``items`` on top of ``base`` (default: the paper's).

    ``items``: ``KEY=VALUE`` strings (the CLI's ``--set``) or a ``key -> value`` mapping
    (values strings or typed, e.g. from :func:`flatten_tables`). Later items win. Raises
    :class:`SettingsError` (one line, listing the valid keys) for an unknown key or a bad
    value."""
    base = base or ModelSettings()
    if items is None:
        pairs: list[tuple[str, Any]] = []
    elif isinstance(items, Mapping):
        pairs = list(items.items())
    else:
        pairs = [parse_assignment(t) for t in items]
    overrides = dict(base.overrides)
    model_changes: dict[str, dict[str, Any]] = {}
    pred_changes: dict[str, Any] = {}
    kind_changes: dict[str, dict[str, Any]] = {}
    threshold = base.baseline_threshold
    for key, raw in pairs:
        if key not in KEY_TYPES:
            raise SettingsError(f"unknown setting {key!r}; {_keys_hint(key)}")
        value = _convert(key, raw, KEY_TYPES[key])
        overrides[key] = value
        head, _, rest = key.partition(".")
        if key == BASELINE_KEY:
            if not (math.isfinite(value) and value >= 0):
                raise SettingsError(f"{key}: must be a finite number >= 0, got {value!r}")
            threshold = value
        elif head == "prediction":
            if "." in rest:
                kind, fname = rest.split(".", 1)
                kind_changes.setdefault(kind, {})[fname] = value
            else:
                pred_changes[rest] = value
        else:
            model_changes.setdefault(head, {})[rest] = value
    params = dict(base.params)
    try:
        for model, changes in model_changes.items():
            current = params.get(model, MODELS[model].default_params())
            params[model] = replace(current, **changes)
        table = base.prediction.uncertainty
        for kind, changes in kind_changes.items():
            table = replace(table, **{kind: replace(getattr(table, kind), **changes)})
        prediction = replace(base.prediction, uncertainty=table, **pred_changes)
    except RiskError as exc:
        raise SettingsError(str(exc)) from None
    return ModelSettings(
        params=params, prediction=prediction, baseline_threshold=threshold, overrides=overrides
    )


def describe(settings: ModelSettings) -> str:
    """``key=value`` of every override, or ``the paper's defaults``."""
    if not settings.overrides:
        return "the paper's defaults"
    return ", ".join(f"{k}={v}" for k, v in settings.overrides.items())


__all__ = [
    "BASELINE_KEY",
    "KEY_TYPES",
    "ModelSettings",
    "SettingsError",
    "describe",
    "flatten_tables",
    "parse_assignment",
    "parse_settings",
    "valid_keys",
]

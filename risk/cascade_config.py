"""The filter cascade's configuration: stages, tiers, the corridor stage, the shipped
cascades by name, and the TOML file that holds them (``docs/cascade.md``).

Split from :mod:`risk.cascade` (which runs a configuration and re-exports these names).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from risk.errors import RiskError
from risk.registry import BASELINE_THRESHOLD, MODELS
from risk.settings import BASELINE_KEY, ModelSettings, SettingsError, flatten_tables, parse_settings

_HERE = pathlib.Path(__file__).parent
#: The cascades shipped with the package, by name (``--cascade NAME``, ``cascade:NAME``):
#: ``planner``, calibrated against what planners react to (the default), and
#: ``survival``, the paper's, calibrated against survival analysis on synthetic scenes.
NAMED_CASCADES: dict[str, pathlib.Path] = {
    "planner": _HERE / "planner_cascade.toml",
    "survival": _HERE / "survival_cascade.toml",
}
DEFAULT_CASCADE_NAME = "planner"
DEFAULT_CASCADE_PATH = NAMED_CASCADES[DEFAULT_CASCADE_NAME]


@dataclass(frozen=True)
class CorridorSettings:
    """The corridor stage (``[corridor]`` in the TOML; :func:`risk.kernel.corridor_keep`):
    agents it selects skip the other stages, so no risk stage can drop them.

    It keeps the first ``leaders`` agents whose box lies in the ego's route corridor
    ahead (``|lateral offset| <= (w_ego + w_agent) / 2 + lateral_margin_m`` from the
    ego's first path candidate, extended straight) within the interaction range

        ``range = margin_m + v headway_s + max(v^2 / (2 brake_mps2), v dv / (2 sqrt(accel_mps2 brake_mps2)))``

    (``v`` the ego's speed, ``dv`` how fast it closes on the agent; the second term is
    the braking distance, the third IDM's dynamic gap), and, when ``crossing``, every
    agent whose path (at its speed, within ``horizon_s``) enters the corridor within the
    range before the ego has passed that point plus ``crossing_slack_s``."""

    # Defaults chosen on planner truth of idm and fop on 31 recorded scenes (docs/cascade.md,
    # "The corridor stage": 197 of 205 planner-important agent-frames, 1.6 agents a frame)
    leaders: int = 3
    headway_s: float = 1.5
    brake_mps2: float = 2.0
    accel_mps2: float = 1.0
    margin_m: float = 30.0
    lateral_margin_m: float = 1.5
    crossing: bool = True
    crossing_slack_s: float = 1.0
    horizon_s: float = 8.0

    def interaction_range_m(self, speed_mps: float, closing_mps: float) -> float:
        """The range (m) at ego speed ``speed_mps`` closing at ``closing_mps``."""
        v = max(speed_mps, 0.0)
        brake = v * v / (2.0 * self.brake_mps2)
        gap = v * max(closing_mps, 0.0) / (2.0 * math.sqrt(self.accel_mps2 * self.brake_mps2))
        return self.margin_m + v * self.headway_s + max(brake, gap)


_CORRIDOR_KEYS = {f.name for f in dataclasses.fields(CorridorSettings)}


class CascadeConfigError(RiskError):
    """An invalid cascade configuration; the message names the file and the key."""

    def __init__(self, key: str, problem: str, *, source: str = ""):
        self.key = key
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{key}: {problem}")


# ---------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class Stage:
    """One filter stage: keep an agent when ``risk >= threshold`` under ``model``."""

    model: str  # a name in risk.MODELS, e.g. "path_distance"
    threshold: float  # in the model's own units (distance risks in (0, 1], R_G in 1/m^2)


@dataclass(frozen=True)
class Tier:
    """A planner tier; tiers are nested, each one a subset of the one before."""

    name: str  # "behavior", "interactive", "cooperative"
    min_survival_risk: float  # survivors with survival risk >= this reach the tier
    max_agents: int | None = None  # optional cap: only the top-k by survival risk


@dataclass(frozen=True)
class CascadeConfig:
    """Stages, tiers and the survival baseline threshold of one cascade."""

    stages: tuple[Stage, ...]
    tiers: tuple[Tier, ...]
    baseline_threshold: float = BASELINE_THRESHOLD  # important when R_S >= this (paper)
    provenance: str = ""  # how the thresholds were made (calibration record)
    #: Model and prediction settings of the ``[params.<model>]`` and ``[prediction]``
    #: tables, as flat keys of :mod:`risk.settings` (empty: the paper's values).
    settings: Mapping[str, Any] = field(default_factory=dict)
    #: The corridor stage ahead of the risk stages (None: none).
    corridor: CorridorSettings | None = None
    #: The calibration's stated guarantee (``[guarantee]``: miss rate, confidence, units),
    #: kept as written; empty when none was stated.
    guarantee: Mapping[str, Any] = field(default_factory=dict)

    def model_settings(self) -> ModelSettings:
        """The parameters, prediction and baseline threshold this cascade names."""
        return parse_settings(
            self.settings, base=ModelSettings(baseline_threshold=self.baseline_threshold)
        )

    def with_settings(self, items: Any) -> CascadeConfig:
        """This cascade with the settings ``items`` (``KEY=VALUE`` strings or a mapping,
        see :func:`risk.settings.parse_settings`) on top of its own; ``baseline.threshold``
        sets :attr:`baseline_threshold`. Raises SettingsError for a bad key or value."""
        merged = parse_settings(items, base=self.model_settings())
        flat = {**self.settings, **{k: v for k, v in merged.overrides.items() if k != BASELINE_KEY}}
        return dataclasses.replace(
            self, settings=flat, baseline_threshold=merged.baseline_threshold
        )

    @property
    def stage_names(self) -> tuple[str, ...]:
        return tuple(s.model for s in self.stages)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "") -> CascadeConfig:
        """Build from a parsed TOML document; raises CascadeConfigError naming the key."""
        return _parse_config(data, source)

    @classmethod
    def from_toml(cls, path: str | pathlib.Path) -> CascadeConfig:
        """Read and validate a cascade TOML file."""
        path = pathlib.Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise CascadeConfigError("toml", f"not valid TOML ({exc})", source=str(path)) from None
        except UnicodeDecodeError:
            raise CascadeConfigError("toml", "not a UTF-8 text file", source=str(path)) from None
        except RecursionError:  # tomllib recurses once per nested array or table
            raise CascadeConfigError(
                "toml", "nested deeper than can be parsed (a cascade file nests two levels)",
                source=str(path),
            ) from None  # fmt: skip
        return _parse_config(data, str(path))

    @classmethod
    def default(cls) -> CascadeConfig:
        """The calibrated default cascade shipped with the package
        (:data:`DEFAULT_CASCADE_NAME`)."""
        return cls.named(DEFAULT_CASCADE_NAME)

    @classmethod
    def named(cls, name: str) -> CascadeConfig:
        """A shipped cascade by name (:data:`NAMED_CASCADES`)."""
        if name not in NAMED_CASCADES:
            raise CascadeConfigError(
                "cascade", f"no shipped cascade {name!r}; named: {', '.join(NAMED_CASCADES)}"
            )
        return cls.from_toml(NAMED_CASCADES[name])

    @classmethod
    def load(cls, name_or_path: str | pathlib.Path) -> CascadeConfig:
        """A shipped cascade's name (``planner``, ``survival``) or a TOML file's path."""
        if isinstance(name_or_path, str) and name_or_path in NAMED_CASCADES:
            return cls.named(name_or_path)
        return cls.from_toml(name_or_path)

    def to_dict(self) -> dict[str, Any]:
        """The TOML document of this configuration (``max_agents`` omitted when None)."""
        tiers = []
        for t in self.tiers:
            entry: dict[str, Any] = {"name": t.name, "min_survival_risk": t.min_survival_risk}
            if t.max_agents is not None:
                entry["max_agents"] = t.max_agents
            tiers.append(entry)
        out: dict[str, Any] = {
            "provenance": self.provenance,
            "baseline_threshold": self.baseline_threshold,
            "stages": [{"model": s.model, "threshold": s.threshold} for s in self.stages],
            "tiers": tiers,
        }
        if self.corridor is not None:
            out["corridor"] = dataclasses.asdict(self.corridor)
        if self.guarantee:
            out["guarantee"] = dict(self.guarantee)
        for key, value in self.settings.items():
            head, _, rest = key.partition(".")
            if value is None:
                value = "none"
            if head == "prediction":
                table = out.setdefault("prediction", {})
                if "." in rest:
                    kind, fname = rest.split(".", 1)
                    table.setdefault(kind, {})[fname] = value
                else:
                    table[rest] = value
            else:
                out.setdefault("params", {}).setdefault(head, {})[rest] = value
        return out

    def to_toml_string(self) -> str:
        """The configuration as TOML text (what :meth:`from_toml` reads back)."""
        import tomli_w

        return tomli_w.dumps(self.to_dict(), multiline_strings=True)


_TOP_KEYS = {
    "provenance", "baseline_threshold", "stages", "tiers", "params", "prediction", "corridor",
    "guarantee",
}  # fmt: skip
_STAGE_KEYS = {"model", "threshold"}
_TIER_KEYS = {"name", "min_survival_risk", "max_agents"}


def _parse_config(data: Mapping[str, Any], source: str) -> CascadeConfig:

    def fail(key: str, problem: str) -> CascadeConfigError:
        return CascadeConfigError(key, problem, source=source)

    def check_keys(table: Any, allowed: set[str], required: set[str], prefix: str) -> None:
        if not isinstance(table, Mapping):
            raise fail(prefix.rstrip("."), "expected a table")
        for key in table:
            if key not in allowed:
                raise fail(f"{prefix}{key}", f"unknown key; expected one of {sorted(allowed)}")
        for key in sorted(required - set(table)):
            raise fail(f"{prefix}{key}", "missing key")

    def number(value: Any, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise fail(key, f"expected a number, got {value!r}")
        value = float(value)
        if math.isnan(value) or value < 0:
            raise fail(key, f"must be a number >= 0, got {value!r}")
        return value

    check_keys(data, _TOP_KEYS, {"stages", "tiers"}, "")
    provenance = data.get("provenance", "")
    if not isinstance(provenance, str):
        raise fail("provenance", "expected a string")
    baseline = number(data.get("baseline_threshold", BASELINE_THRESHOLD), "baseline_threshold")

    raw_stages = data["stages"]
    if not isinstance(raw_stages, list) or not raw_stages:
        raise fail("stages", "expected a non-empty array of tables ([[stages]])")
    stages: list[Stage] = []
    for i, raw in enumerate(raw_stages):
        prefix = f"stages[{i}]."
        check_keys(raw, _STAGE_KEYS, _STAGE_KEYS, prefix)
        model = raw["model"]
        if model not in MODELS:
            raise fail(f"{prefix}model", f"unknown model {model!r}; valid: {', '.join(MODELS)}")
        if any(s.model == model for s in stages):
            raise fail(f"{prefix}model", f"model {model!r} is already used by an earlier stage")
        stages.append(Stage(model=model, threshold=number(raw["threshold"], f"{prefix}threshold")))

    raw_tiers = data["tiers"]
    if not isinstance(raw_tiers, list) or not raw_tiers:
        raise fail("tiers", "expected a non-empty array of tables ([[tiers]])")
    tiers = []
    for i, raw in enumerate(raw_tiers):
        prefix = f"tiers[{i}]."
        check_keys(raw, _TIER_KEYS, {"name", "min_survival_risk"}, prefix)
        name = raw["name"]
        if not isinstance(name, str) or not name:
            raise fail(f"{prefix}name", "expected a non-empty string")
        cap = raw.get("max_agents")
        if cap is not None and (isinstance(cap, bool) or not isinstance(cap, int) or cap < 1):
            raise fail(f"{prefix}max_agents", f"expected an integer >= 1, got {cap!r}")
        risk_min = number(raw["min_survival_risk"], f"{prefix}min_survival_risk")
        tiers.append(Tier(name=name, min_survival_risk=risk_min, max_agents=cap))
    if len({t.name for t in tiers}) != len(tiers):
        raise fail("tiers", "tier names must be unique")
    corridor = None
    if "corridor" in data:
        raw = data["corridor"]
        check_keys(raw, _CORRIDOR_KEYS, set(), "corridor.")
        values: dict[str, Any] = {}
        for key, value in raw.items():
            if key == "crossing":
                if not isinstance(value, bool):
                    raise fail("corridor.crossing", f"expected true or false, got {value!r}")
                values[key] = value
            elif key == "leaders":
                if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                    raise fail("corridor.leaders", f"expected an integer >= 0, got {value!r}")
                values[key] = value
            else:
                values[key] = number(value, f"corridor.{key}")
        for key in ("brake_mps2", "accel_mps2"):
            if key in values and values[key] <= 0:
                raise fail(f"corridor.{key}", f"must be > 0, got {values[key]!r}")
        corridor = CorridorSettings(**values)
    guarantee = data.get("guarantee", {})
    if not isinstance(guarantee, Mapping):
        raise fail("guarantee", "expected a table")
    try:
        flat = flatten_tables({k: data[k] for k in ("params", "prediction") if k in data})
        parse_settings(flat)  # checks every key and value
    except SettingsError as exc:
        raise fail("params/prediction", str(exc)) from None
    return CascadeConfig(
        stages=tuple(stages),
        tiers=tuple(tiers),
        baseline_threshold=baseline,
        provenance=provenance,
        settings=flat,
        corridor=corridor,
        guarantee=dict(guarantee),
    )

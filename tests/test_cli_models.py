"""``replay models`` and ``replay models --json``."""

from __future__ import annotations

import json

from click.testing import CliRunner

from replay.cli.app import main
from risk import MODELS


def test_table_lists_every_model_with_parameters_and_references():
    res = CliRunner().invoke(main, ["models"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].split() == ["name", "family", "parameters", "(defaults)", "paper", "complexity"]
    for spec in MODELS.values():
        row = next(line for line in lines if line.startswith(spec.name + " "))
        assert spec.family in row and spec.paper_ref in row and spec.complexity in row
    assert "escape_time_s=0.4 s" in res.output
    assert "on_path_tolerance_m=1.75 m" in res.output
    assert "n_circles=3" in res.output
    assert "horizon T = 12 s, step dt = 0.1 s" in res.output
    assert "survival risk >= 1e-25" in res.output


def test_json_is_machine_readable():
    res = CliRunner().invoke(main, ["models", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert [m["name"] for m in doc["models"]] == list(MODELS)
    surv = next(m for m in doc["models"] if m["name"] == "survival")
    assert surv["params"] == [
        {
            "name": "escape_time_s",
            "value": 0.4,
            "unit": "s",
            "help": "tau_esc: escape rate 1/tau_esc of the Poisson process",
        }
    ]
    assert doc["baseline"] == {"model": "survival", "threshold": 1e-25}
    assert doc["prediction"]["horizon_s"] == 12.0 and doc["prediction"]["dt_s"] == 0.1
    assert doc["prediction"]["uncertainty"]["vehicle"]["sigma_max_lon_m"] == 5.0
    enc = next(m for m in doc["models"] if m["name"] == "closest_encounter")
    assert {"name": "encounter_time_max_s", "value": None}.items() <= enc["params"][1].items()


def test_help_explains():
    res = CliRunner().invoke(main, ["models", "--help"])
    assert res.exit_code == 0
    assert "nine risk models" in res.output and "--json" in res.output


def test_unknown_option_is_a_usage_error():
    res = CliRunner().invoke(main, ["models", "--bogus"])
    assert res.exit_code == 2
    assert "Traceback" not in res.output

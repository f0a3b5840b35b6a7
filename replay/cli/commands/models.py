"""``replay models``: the nine risk models, their parameters and the prediction settings."""

from __future__ import annotations

import json
import textwrap
from typing import Any

import click

from risk import BASELINE_MODEL, BASELINE_THRESHOLD, MODELS, PredictionSettings


def _fmt(value: Any) -> str:
    if value is None:
        return "None"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _pair(lon: float, lat: float) -> str:
    return f"{_fmt(lon) + ' / ' + _fmt(lat):<13}"


def models_document() -> dict[str, Any]:
    """Everything ``replay models --json`` prints: models, baseline, prediction settings."""
    return {
        "models": [
            {
                "name": spec.name,
                "title": spec.title,
                "family": spec.family,
                "paper_ref": spec.paper_ref,
                "complexity": spec.complexity,
                "risk_unit": spec.unit,
                "params": spec.describe_params(),
            }
            for spec in MODELS.values()
        ],
        "baseline": {"model": BASELINE_MODEL, "threshold": BASELINE_THRESHOLD},
        "prediction": PredictionSettings().to_dict(),
    }


def _table(doc: dict[str, Any]) -> str:
    headers = ("name", "family", "parameters (defaults)", "paper", "complexity")
    rows: list[tuple[str, ...]] = []
    for m in doc["models"]:
        params = [
            f"{p['name']}={_fmt(p['value'])}"
            + (f" {p['unit']}" if p["unit"] and p["value"] is not None else "")
            + (" (= horizon)" if p["value"] is None else "")
            for p in m["params"]
        ] or ["-"]
        for i, text in enumerate(params):
            if i == 0:
                rows.append((m["name"], m["family"], text, m["paper_ref"], m["complexity"]))
            else:
                rows.append(("", "", text, "", ""))
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    line = "  ".join("-" * w for w in widths)
    out = ["  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)), line]
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    return "\n".join(out)


def _prediction_text(doc: dict[str, Any]) -> str:
    pred = doc["prediction"]
    lines = [
        f"Prediction: constant speed along the path, horizon T = {_fmt(pred['horizon_s'])} s, "
        f"step dt = {_fmt(pred['dt_s'])} s.",
        "Uncertainty sig(s) = min(sig0 + k * v * s, sig_max), longitudinal / lateral, in m:",
    ]
    for kind, u in pred["uncertainty"].items():
        lines.append(
            f"  {kind:<10} sig0 {_pair(u['sigma0_lon_m'], u['sigma0_lat_m'])}"
            f"  k {_pair(u['growth_lon'], u['growth_lat'])}"
            f"  sig_max {_pair(u['sigma_max_lon_m'], u['sigma_max_lat_m'])}".rstrip()
        )
    base = doc["baseline"]
    lines.append(
        f"Baseline: an agent is important when {base['model']} risk >= {base['threshold']:g}."
    )
    return "\n".join(lines)


@click.command("models")
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print one JSON document (models with parameter names, values, units and help; "
    "the baseline; the prediction settings) instead of the table.",
)
def models(as_json: bool) -> None:
    """List the nine risk models with their parameters and paper references.

    Every model returns one risk per agent, higher = riskier. The names are the ones the
    other commands accept (e.g. for --model) and that result files use. Paper references
    follow the numbering of the paper source (Puphal et al., ICRAE 2022): the models are in
    Sec. III. Complexity: p path points, n prediction steps, k circles.
    """
    doc = models_document()
    if as_json:
        click.echo(json.dumps(doc, indent=2))
        return
    click.echo(_table(doc))
    click.echo()
    click.echo(_prediction_text(doc))
    click.echo()
    notes = (
        "Risk values: distance and time models are in [0, 1]; gaussian is a density "
        "overlap in 1/m^2 (may exceed 1); survival is >= 0. See docs/models.md for every "
        "choice the specification leaves open."
    )
    click.echo(textwrap.fill(notes, width=100))

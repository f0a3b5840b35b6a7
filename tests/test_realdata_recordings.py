"""Real samples end to end: convert, ``replay run`` into an .rrd, and read the recording
back: every model's risk timeline has a finite value for every agent valid in a frame."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
from click.testing import CliRunner
from rerun import chunk as rr_chunk

from converters.scene.reader import read_scene
from recordings import layout as L
from replay.cli.app import main
from risk import MODELS

pytestmark = pytest.mark.realdata


def risk_timelines(rrd: pathlib.Path) -> dict[tuple[str, int], dict[int, float]]:
    """(model, agent id) -> {time in ns: raw risk} from each agent's
    ``/scene/agents/<id>/risk/<model>`` entities."""
    out: dict[tuple[str, int], dict[int, float]] = {}
    for chunk in rr_chunk.RrdReader(rrd).stream().to_chunks():
        # /scene/agents/<id>/risk/<model>
        parts = chunk.entity_path.strip("/").split("/")
        if chunk.is_static or len(parts) != 5 or "/" + "/".join(parts[:2]) != L.AGENTS:
            continue
        if parts[3] != L.RISK:
            continue
        batch = chunk.to_record_batch()
        column = next(n for n in batch.schema.names if n.endswith(":scalars"))
        times = batch.column(L.TIMELINE).cast("int64").to_pylist()
        values = batch.column(column).to_pylist()
        series = out.setdefault((parts[4], int(parts[2])), {})
        for t, v in zip(times, values, strict=True):
            if v is not None:
                series[t] = float(v[0])
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("source", "relative", "extra"),
    [
        ("waymo", "waymo/womd_637f20cafde22ff8.tfrecord", []),
        ("av2", "av2/scenario_0a1e6f0a-1817-4a98-b02e-db8c9327d151.parquet", []),
        ("commonroad", "commonroad/ZAM_Tjunction-1_97_T-1.xml", []),
    ],
)
def test_recording_covers_every_valid_agent(shared_data, tmp_path, source, relative, extra):
    scene_path = tmp_path / f"{source}.mcap"
    runner = CliRunner()
    converted = runner.invoke(
        main, ["convert", source, str(shared_data / relative), "-o", str(scene_path), *extra]
    )
    assert converted.exit_code == 0, converted.output
    rrd = tmp_path / f"{source}.rrd"
    ran = runner.invoke(main, ["run", str(scene_path), "-o", str(rrd), "--no-progress"])
    assert ran.exit_code == 0, ran.output

    timelines = risk_timelines(rrd)
    scene = read_scene(scene_path)
    checked = 0
    for frame in scene.frames:
        t_ns = round(frame.t * 1e9)
        for agent_id in frame.ids[frame.others]:
            for model in MODELS:
                value = timelines.get((model, int(agent_id)), {}).get(t_ns)
                assert value is not None and np.isfinite(value), (model, int(agent_id), frame.t)
                checked += 1
    assert checked > 100 * len(MODELS)

"""Replaying one scene into its files, as ``replay run`` and ``replay demo`` do: the sinks
of a run, the replay with its warnings, and the summary a person reads afterwards.

Library code for the command line and for notebooks: messages meant for the person
running it (the ego note, ``ReplayWarning``s) go to ``notify`` (the command line prints
them on stderr), and the summaries are returned as text.
"""

from __future__ import annotations

import pathlib
import warnings
from collections.abc import Callable, Sequence

from converters.scene.reader import open_scene
from converters.scene.writer import write_scene
from converters.synthetic import SyntheticSettings, generate_scene
from outputs.sinks import Annotator
from outputs.transaction import OutputGuard
from replay.core.egos import EgosSummary, pooled, run_every_ego
from replay.core.engine import ReplayWarning, RunSummary, Sink, Stride, run_scene
from replay.core.keep_lists import KeepListSink
from risk.cascade import CascadeConfig
from risk.frame import Scene

Notify = Callable[[str], None]

DEMO_SEED = 7  # fixed so that every demo shows the same scene (not a calibration seed)
DEMO_AGENTS = 100
DEMO_DURATION_S = 10.0
DEMO_FRAME_PERIOD_S = 0.1


def _quiet(message: str) -> None:
    pass


def replay_to_files(
    scene: pathlib.Path,
    *,
    rrd: pathlib.Path | None,
    table: pathlib.Path | None,
    cascade: CascadeConfig | None = None,
    ego: int | None = None,
    every: int | Stride = 1,
    progress: bool = True,
    inputs: tuple[pathlib.Path | None, ...] = (),
    notify: Notify = _quiet,
    keep_lists: pathlib.Path | None = None,
    annotators: Sequence[Annotator] = (),
    extra_sinks: Sequence[Sink] = (),
) -> RunSummary:
    """Replay ``scene`` into a Rerun recording, a table and/or keep-lists (each
    optional), all or nothing: the outputs are checked before the replay and appear
    together (:class:`outputs.transaction.OutputGuard`; ``inputs`` are refused as
    outputs). ``extra_sinks`` see the frames too (e.g. a hindsight tally)."""
    with OutputGuard(inputs=(scene, *inputs), files=(rrd, table, keep_lists)):
        sinks = [*make_sinks(rrd, table, keep_lists), *extra_sinks]
        reader = open_scene(scene)
        if ego is None:  # the scene's own ego: say which agent it is and why
            notify(ego_note(reader.metadata))
        return run_with_warnings(
            reader, notify=notify, sinks=sinks, cascade=cascade, ego=ego, progress=progress,
            every=every, annotators=annotators,
        )  # fmt: skip


def replay_every_ego_to_table(
    scene: pathlib.Path,
    *,
    table: pathlib.Path,
    cascade: CascadeConfig | None = None,
    every: int | Stride = 1,
    progress: bool = True,
    inputs: tuple[pathlib.Path | None, ...] = (),
    keep_lists: pathlib.Path | None = None,
    annotators: Sequence[Annotator] = (),
) -> EgosSummary:
    """Replay ``scene`` once per ego (every agent that moves) into one table (and
    keep-lists)."""
    with OutputGuard(inputs=(scene, *inputs), files=(table, keep_lists)):  # checked first
        return run_every_ego(
            scene, sinks=make_sinks(None, table, keep_lists), cascade=cascade, every=every,
            progress=progress, annotators=annotators,
        )  # fmt: skip


def demo_scene(
    *,
    n_agents: int = DEMO_AGENTS,
    seed: int = DEMO_SEED,
    duration_s: float = DEMO_DURATION_S,
    frame_period_s: float = DEMO_FRAME_PERIOD_S,
) -> Scene:
    """The demo's synthetic four-way intersection: ``n_agents`` vehicles (ego included)
    for ``duration_s`` at ``1 / frame_period_s`` Hz (shorter if the ego leaves the map)."""
    settings = SyntheticSettings(
        n_agents=n_agents, duration_s=duration_s, frame_period_s=frame_period_s
    )
    return generate_scene(settings, seed=seed)


def run_demo(
    output_dir: pathlib.Path,
    *,
    seed: int = DEMO_SEED,
    agents: int = DEMO_AGENTS,
    progress: bool = True,
    notify: Notify = _quiet,
) -> tuple[pathlib.Path, RunSummary]:
    """Generate the demo scene into ``output_dir/intersection.mcap`` and replay it into
    ``intersection.rrd`` and ``intersection.parquet`` beside it; returns the scene's path
    and the run's summary. All three files appear together or not at all; the folder is
    removed again on failure."""
    scene_path = output_dir / "intersection.mcap"
    rrd, table = scene_path.with_suffix(".rrd"), scene_path.with_suffix(".parquet")
    with OutputGuard(files=(scene_path, rrd, table), folders=(output_dir,)) as guard:
        notify(f"Generating a synthetic intersection: {agents} agents, seed {seed} ...")
        write_scene(scene_path, demo_scene(n_agents=agents, seed=seed))
        guard.commit_now(scene_path)  # the replay reads it back
        sinks = make_sinks(rrd, table)
        summary = run_with_warnings(scene_path, notify=notify, sinks=sinks, progress=progress)
    return scene_path, summary


def ego_note(metadata: dict[str, str]) -> str:
    """Which agent the scene's own ego is, and why (the converter's choice, which it
    records in the scene metadata as ``ego_track`` and ``ego_choice``)."""
    track = metadata.get("ego_track") or metadata.get("ego_id", "?")
    why = metadata.get("ego_choice") or "the scene's ego"
    return f"Ego: agent {metadata.get('ego_id', '?')} (source track {track}): {why}"


def format_egos_summary(egos: EgosSummary) -> str:
    """The end-of-run summary of an every-ego replay: the egos, then the pooled funnel."""
    shown = ", ".join(str(e) for e in egos.egos[:12]) + (", ..." if len(egos.egos) > 12 else "")
    stride = f", {egos.every}" if egos.every != Stride() else ""
    head = (
        f"Egos: {len(egos.egos)} agents that move {egos.min_travel_m:g} m or more ({shown});"
        f" {egos.ego_frames} ego-frames{stride}"
    )
    body = format_summary(pooled(egos)).replace(", ego id -1,", ", every ego,")
    return head + "\n" + body.replace("frames", "ego-frames", 1)


def make_sinks(
    rrd: pathlib.Path | None,
    table: pathlib.Path | None,
    keep_lists: pathlib.Path | None = None,
) -> list[Sink]:
    """The sinks of a run: the Rerun recording and/or the table (both checked before the
    replay starts, so a bad path fails at once)."""
    # Each output's library is loaded only when it is asked for, and where there is a
    # second CPU by the output process (outputs.process), while this one replays: rerun
    # takes about 1 s and polars 0.3 s to import (python -X importtime). With both, the
    # output process takes the recording and this one the table: it is idle by then, and
    # the process's imports and writes one after the other made it the critical path
    # (`replay demo` 0.3 s slower, measured).
    sinks: list[Sink] = []
    if keep_lists is not None:
        sinks.append(KeepListSink(keep_lists))
    if table is not None:
        from replay.core.tables import TableSink

        sinks.append(TableSink(table, background=rrd is None))
    if rrd is not None:
        from recordings import SceneRecorder

        sinks.append(SceneRecorder(rrd, background=True))
    return sinks


def run_with_warnings(scene, *, notify: Notify = _quiet, **kwargs) -> RunSummary:
    """:func:`replay.core.engine.run_scene` with its ``ReplayWarning``s passed to
    ``notify`` as ``Warning: ...`` lines (other warnings are shown as usual)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ReplayWarning)
        summary = run_scene(scene, **kwargs)
    for w in caught:
        if issubclass(w.category, ReplayWarning):
            notify(f"Warning: {w.message}")
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return summary


def format_summary(s: RunSummary, extra_outputs: tuple[pathlib.Path, ...] = ()) -> str:
    """The end-of-run summary: counts, the funnel, false negatives, times, files
    (``extra_outputs``: files written before the replay, listed first)."""
    skipped = f", {s.skipped_frames} skipped (ego missing)" if s.skipped_frames else ""
    name_w = max(len(n) for n in ("all other agents", *s.stage_names, *s.tier_names)) + 2
    lines = [
        f"Scene: {s.source or 'in memory'}",
        f"  {s.frames} frames{skipped}, ego id {s.ego_id}, {s.agents} agents, "
        f"{s.mean_others:.1f} other agents per frame",
        "Cascade (mean agents per frame; false negatives vs the survival baseline, "
        f"{s.baseline_agents} important agent-frames; compute time):",
        f"  {'all other agents':<{name_w}}{s.mean_others:7.1f}",
    ]
    for name, kept, fn, t in zip(
        s.stage_names, s.mean_kept, s.false_negatives, s.stage_time_s, strict=True
    ):
        lines.append(f"  {name:<{name_w}}{kept:7.1f}   FN {fn:<6d} {t:8.3f} s")
    tiers = ", ".join(f"{n} {k:.1f}" for n, k in zip(s.tier_names, s.mean_tier, strict=True))
    lines += [
        f"  tiers (survival sort): {tiers}   {s.sort_time_s:.3f} s",
        f"Time: cascade {sum(s.stage_time_s) + s.sort_time_s:.3f} s "
        f"(stages + sort) vs survival analysis on all agents {s.survival_all_time_s:.3f} s",
        "  "
        + ", ".join(
            [
                f"read {s.read_time_s:.2f} s",
                f"all models for the timelines {s.models_time_s:.2f} s",
                *(f"{k} {v:.2f} s" for k, v in s.sink_time_s.items()),
            ]
        ),
    ]
    outputs = (*extra_outputs, *s.outputs)
    if outputs:
        lines.append("Wrote:")
        lines += [f"  {p}" for p in outputs]
        rrd = [p for p in outputs if p.suffix == ".rrd"]
        if rrd:
            lines.append(f"Open the recording with: rerun {rrd[0]}")
    return "\n".join(lines)

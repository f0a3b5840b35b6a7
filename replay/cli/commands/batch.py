"""``replay batch``: convert, replay and analyse a whole dataset on every core or on Ray."""

from __future__ import annotations

import pathlib

import click

from outputs.transaction import OutputGuard
from replay.batch import CONVERT_KINDS, ENGINES, BatchReport, BatchSettings, run_batch
from replay.batch.engines import check_engine
from replay.cli.convert_options import time_step_option
from replay.cli.ego_options import ego_option, every_option
from replay.cli.limits import WORKERS
from replay.cli.settings_option import CASCADE_NAMES_HELP, CascadeFile, load_cascade, set_option
from replay.core.egos import ALL_EGOS
from replay.core.engine import Stride
from replay.errors import ReplayError

_FAILURES_SHOWN = 5


@click.command("batch")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=pathlib.Path))
@click.option(
    "-o", "--output", "out_dir", required=True,
    type=click.Path(file_okay=False, path_type=pathlib.Path),
    help="Output folder (created if needed). A rerun into the same folder skips the "
    "scenes that are complete there.",
)  # fmt: skip
@click.option(
    "--engine", type=click.Choice(ENGINES), default="local", show_default=True,
    help="'local': worker processes on this machine. 'ray': Ray tasks on a local Ray "
    "instance or on the cluster at --ray-address (needs: pip install 'riskreplay[ray]').",
)  # fmt: skip
@click.option(
    "--workers", type=WORKERS, default=None,
    help="Worker processes (local) or CPUs of the local Ray instance.  "
    "[default: the CPUs this process may use; on a Ray cluster: the cluster's]",
)  # fmt: skip
@click.option(
    "--ray-address", metavar="ADDR", default=None,
    help="The Ray cluster to run on: 'auto' (the cluster this node belongs to, started "
    "with 'ray start') or 'ray://HOST:10001' (Ray Client). Needs --engine ray; without "
    "it Ray starts a local instance.",
)  # fmt: skip
@click.option(
    "--convert", type=click.Choice(CONVERT_KINDS), default=None,
    help="Treat every input as this source (folders are searched for its files, e.g. "
    "*.xml for commonroad) without checking their content. Default: the source of each "
    "file is detected (MCAP scenes are replayed as they are; raw files of every source "
    "are converted to MCAP scenes in OUT/scenes/ first; data files no converter reads are "
    "listed in failures.csv).",
)  # fmt: skip
@click.option(
    "--paths", "path_mode", type=click.Choice(("map", "hindsight")), default="map",
    show_default=True,
    help="For raw inputs: agent paths from the lane graph ('map') or from each agent's "
    "own recorded future ('hindsight').",
)  # fmt: skip
@click.option(
    "--map", "map_osm", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    default=None,
    help="The Lanelet2 OSM map of INTERACTION track files. "
    "[default: the only *.osm file beside each CSV]",
)  # fmt: skip
@time_step_option
@click.option(
    "--rrd", is_flag=True, help="Also write a Rerun recording per scene (OUT/recordings/)."
)
@click.option(
    "--cascade", "cascade_file",
    type=CascadeFile(),
    help="Cascade TOML (stages, thresholds, tiers), e.g. from 'replay calibrate'. "
    "Default: the calibrated cascade shipped with riskreplay. " + CASCADE_NAMES_HELP,
)  # fmt: skip
@ego_option("Default: each scene's recorded ego. 'all' cannot go with --rrd.")
@every_option
@click.option(
    "--strict", is_flag=True,
    help="Exit with an error when any scene failed. Default: only when every scene failed.",
)  # fmt: skip
@click.option(
    "--progress/--no-progress", default=True, show_default=True,
    help="Progress bar on stderr.",
)  # fmt: skip
@set_option
def batch(
    inputs: tuple[pathlib.Path, ...],
    out_dir: pathlib.Path,
    engine: str,
    workers: int | None,
    ray_address: str | None,
    convert: str | None,
    path_mode: str,
    map_osm: pathlib.Path | None,
    time_step: str | float,
    rrd: bool,
    cascade_file: pathlib.Path | None,
    ego: int | str | None,
    every: Stride,
    strict: bool,
    progress: bool,
    sets: tuple[str, ...] = (),
) -> None:
    """Replay every scene of a dataset and compute its statistics, in parallel.

    INPUTS are files or folders (searched recursively) of MCAP scenes and raw recordings
    of any source 'replay convert' knows; each file's source is detected and raw inputs
    are converted first (OUT/scenes/). Every scene is replayed through the nine risk models and the
    cascade into its own table (OUT/tables/NAME.parquet, OUT/frames/NAME.parquet; with
    --rrd also OUT/recordings/NAME.rrd); then the tables are merged and the statistics
    of 'replay stats' are computed over all of them (OUT/stats/).

    A bad scene (damaged file, no ego, an error in a model) fails alone: the run goes on
    and lists it in OUT/failures.csv. Outputs are written atomically, so rerunning the
    same command resumes: complete scenes are skipped, the rest is recomputed.

    \b
    Examples:
      replay batch scenes/ -o out/
      replay batch ../shared/data/recorded -o corpus-out/
      replay batch womd/training/ --convert waymo -o womd-out/ --workers 8
      replay batch /shared/scenes/ -o /shared/out/ --engine ray --ray-address auto
    """
    if ray_address and engine != "ray":
        raise click.UsageError("--ray-address needs --engine ray")
    if map_osm is not None and convert not in (None, "interaction"):
        raise click.UsageError("--map applies to INTERACTION track files only")
    if ego == ALL_EGOS and rrd:
        raise click.UsageError(
            "--rrd writes one recording per scene, which shows one ego's view; it cannot go "
            "with --ego all"
        )
    check_engine(engine)
    cascade = load_cascade(cascade_file, sets)
    settings = BatchSettings(
        cascade=cascade,
        rrd=rrd,
        convert=convert,
        paths=path_mode,
        map_osm=None if map_osm is None else map_osm.absolute(),
        ego=ego,
        every=every,
        time_step=time_step,
    )
    # Locked and checked at once; scenes are committed one by one (resumable), so no
    # deferred transaction here. Stale temporary files of a killed run are removed.
    guard = OutputGuard(inputs=[*inputs, cascade_file, map_osm], folders=(out_dir,),
                        transaction=False)  # fmt: skip
    try:
        with guard:
            report = run_batch(
                inputs, out_dir, settings, engine=engine, workers=workers,
                ray_address=ray_address, progress=progress,
            )  # fmt: skip
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (replay.core.process_exit)
        # Running scenes finished and are complete; the same command resumes.
        exc.kept = (  # type: ignore[attr-defined]
            f"complete scenes are kept in {out_dir}; run the same command again to resume"
            " (they are skipped)"
        )
        raise
    click.echo(format_report(report, settings))
    if report.all_failed:
        raise ReplayError(
            f"all {len(report.failures)} scene(s) failed; see {report.out_dir / 'failures.csv'}"
        )
    if strict and report.failures:
        raise ReplayError(
            f"{len(report.failures)} failure(s) (--strict); see {report.out_dir / 'failures.csv'}"
        )


def format_report(r: BatchReport, settings: BatchSettings) -> str:
    """The end-of-run summary: counts, throughput, failures, output paths."""
    workers = f", {r.workers} workers" if r.workers else ", nothing to run"
    rate = f" ({r.replayed / r.run_seconds:.2f} scenes/s)" if r.replayed and r.run_seconds else ""
    lines = [
        f"Batch over {r.inputs} input file(s) in {r.seconds:.1f} s ({r.engine} engine{workers})",
        f"  scenes: replayed {r.replayed}{rate}, skipped {r.skipped} (complete from an "
        f"earlier run); failures: {len(r.failures)}",
    ]
    if r.conversions or r.conversions_skipped or settings.convert:
        what = f"{settings.convert} " if settings.convert else ""
        lines.append(
            f"  converted {r.conversions} {what}input(s), skipped "
            f"{r.conversions_skipped} (converted by an earlier run)"
        )
    if r.failures:
        lines.append(f"Failures ({len(r.failures)}; all in failures.csv):")
        for f in r.failures[:_FAILURES_SHOWN]:
            where = f.scene or pathlib.Path(f.input).name
            lines.append(f"  {where} [{f.stage}] {f.error_type}: {f.reason}")
        if len(r.failures) > _FAILURES_SHOWN:
            lines.append(f"  ... and {len(r.failures) - _FAILURES_SHOWN} more")
    lines.append("Wrote:")
    root = r.out_dir
    if r.conversions or r.conversions_skipped or settings.convert:
        lines.append(f"  {root / 'scenes'}/  (converted MCAP scenes)")
    if r.scenes:
        lines.append(f"  {root / 'tables'}/  ({len(r.scenes)} per-scene agents tables)")
        lines.append(f"  {root / 'frames'}/  (per-scene frames tables)")
        if settings.rrd:
            lines.append(f"  {root / 'recordings'}/  (open one with: rerun FILE.rrd)")
    if r.stats_files:
        lines.append(
            f"  {root / 'stats'}/  ({len(r.stats_files)} files: summary.json, tables, plots)"
        )
    lines.append(f"  {root / 'scenes.csv'}")
    lines.append(f"  {root / 'failures.csv'}")
    return "\n".join(lines)

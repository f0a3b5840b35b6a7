"""The registry of recorded-traffic sources: how to recognise, group and convert each one.

Built like :mod:`risk.registry`: :data:`SOURCES` is a literal dict of frozen
:class:`SourceSpec`, and code that converts (``replay convert``, ``replay batch``) iterates
over it and never special-cases a source by name. **Adding a dataset** is one reader module
in ``converters/`` plus one entry here: the entry says which files belong to the source
(``patterns`` and a cheap content check ``detect``), how found files form inputs
(``group``: one file, one folder, or several track files of one recording), which other
files a conversion reads (``companions``), how to convert an input (``scenes``) and the
help of its ``replay convert`` command (``help``, ``examples``, ``argument`` and the
options it takes).

:func:`discover` sorts the files of a folder tree into inputs of each source (and files
that look like data no source reads), for ``replay batch`` on a mixed corpus.
"""

from __future__ import annotations

import fnmatch
import os
import pathlib
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from converters import av2, av2_sensor, commonroad, interaction, scenarionet, waymo
from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.lanegraph import PathSettings
from converters.tfrecord import RecordError, masked_crc32c, read_records
from converters.tracks import Skipped
from risk.frame import Scene

SceneBuild = tuple[str, Callable[[], Scene]]
"""``(label, build)``: a label naming the scene before it is built (the input's name, or
``record-K`` of a multi-scene file) and a function that converts it."""


@dataclass(frozen=True, kw_only=True)
class SourceInput:
    """One input of a source: what one conversion reads."""

    source: str  # a key of SOURCES
    path: pathlib.Path  # the file or folder (an AV2 Sensor log)
    extra: tuple[pathlib.Path, ...] = ()  # more track files of the same scene (INTERACTION)
    map: pathlib.Path | None = None  # a map file given from outside (INTERACTION --map)

    @property
    def files(self) -> tuple[pathlib.Path, ...]:
        return (self.path, *self.extra)


@dataclass(frozen=True, kw_only=True)
class ReadOptions:
    """How a conversion runs (the common options of ``replay convert``)."""

    paths: str = "map"
    settings: PathSettings = field(default_factory=PathSettings)
    ego: int | None = None  # sources with ``ego_option`` only
    origin: tuple[float, float] = (0.0, 0.0)  # sources with ``map_option`` only
    skip_bad: bool = False
    progress: bool = False
    time_step: TimeStep = "auto"  # the clock check's choice (converters.clock)


@dataclass(frozen=True, kw_only=True)
class SourceSpec:
    """One source of recorded traffic."""

    name: str  # the ``replay convert`` subcommand and the batch ``--convert`` kind
    title: str  # one line, for listings
    help: str  # the body of the command's help
    examples: tuple[str, ...]
    argument: str  # metavar of the command's input argument
    patterns: tuple[str, ...]  # file-name patterns of the files ``detect`` looks at
    detect: Callable[[pathlib.Path], bool]  # does this file belong to the source (cheap)
    scenes: Callable[[SourceInput, ReadOptions, Skipped], Iterator[SceneBuild]]
    records: str  # what --skip-bad skips ("dynamic obstacles", "CSV rows", ...)
    group: Callable[[Sequence[pathlib.Path]], list[SourceInput]] | None = None  # default: one
    # input per file
    companions: Callable[[SourceInput], list[pathlib.Path]] = lambda _: []
    folder_input: bool = False  # the command's argument is a folder (or may be one)
    many_inputs: bool = False  # the command takes several files for one scene
    multi_scene: bool = False  # one input may hold several scenes (named NAME/SCENARIO)
    ego_option: bool = False  # takes --ego ID (sources without an ego of their own)
    map_option: bool = False  # takes --map and --origin

    def inputs(self, files: Sequence[pathlib.Path]) -> list[SourceInput]:
        """The inputs that ``files`` (all of this source) form."""
        if self.group is not None:
            return self.group(files)
        return [SourceInput(source=self.name, path=f) for f in files]


# ---------------------------------------------------------------------- detection helpers
def _head(path: pathlib.Path, size: int = 4096) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read(size)
    except OSError:
        return b""


def _is_tfrecord(path: pathlib.Path) -> bool:
    """The first record's length carries its masked CRC-32C (TFRecord framing)."""
    head = _head(path, 12)
    return len(head) == 12 and masked_crc32c(head[:8]) == int.from_bytes(head[8:], "little")


def _is_commonroad(path: pathlib.Path) -> bool:
    return b"<commonRoad" in _head(path)


_CSV_COLUMNS = ("track_id", "frame_id", "timestamp_ms")


def _is_track_csv(path: pathlib.Path) -> bool:
    first = _head(path, 1024).split(b"\n", 1)[0].decode("utf-8", "replace")
    columns = {c.strip() for c in first.split(",")}
    return all(c in columns for c in _CSV_COLUMNS)


def _is_parquet(path: pathlib.Path) -> bool:
    return _head(path, 4) == b"PAR1"


def _is_log_pose_file(path: pathlib.Path) -> bool:
    return av2_sensor.is_log_dir(path.parent)


# ---------------------------------------------------------------------- grouping
_RECORDING = re.compile(r"^(?P<what>.*?)_?(?P<number>\d+)$")


def _interaction_group(files: Sequence[pathlib.Path]) -> list[SourceInput]:
    """Track CSVs of one recording form one input: same folder, same trailing number
    (``vehicle_tracks_000.csv`` + ``pedestrian_tracks_000.csv``); vehicles first. The map
    is the only ``*.osm`` beside them (None when there is none or several: the conversion
    then says to give ``--map``)."""
    groups: dict[tuple[pathlib.Path, str], list[pathlib.Path]] = {}
    for f in sorted(files):
        m = _RECORDING.match(f.stem)
        key = (f.parent, m.group("number") if m else f.stem)
        groups.setdefault(key, []).append(f)
    out = []
    for members in groups.values():
        members.sort(key=lambda p: (not p.stem.startswith("vehicle"), p.name))
        out.append(
            SourceInput(
                source="interaction",
                path=members[0],
                extra=tuple(members[1:]),
                map=interaction_map_for(members[0]),
            )
        )
    return out


def interaction_map_for(csv: pathlib.Path) -> pathlib.Path | None:
    """The Lanelet2 map of a track CSV: the only ``*.osm`` beside it, else the dataset's
    own layout, ``maps/LOCATION.osm`` next to ``recorded_trackfiles/LOCATION/`` (or one
    level up); None when neither exists (the conversion then asks for ``--map``)."""
    beside = sorted(csv.parent.glob("*.osm"))
    if len(beside) == 1:
        return beside[0]
    if beside:
        return None
    location = csv.parent.name
    for root in (csv.parent.parent, csv.parent.parent.parent):
        candidate = root / "maps" / f"{location}.osm"
        if candidate.is_file():
            return candidate
    return None


def _av2_sensor_group(files: Sequence[pathlib.Path]) -> list[SourceInput]:
    return [SourceInput(source="av2-sensor", path=f.parent) for f in sorted(set(files))]


# ---------------------------------------------------------------------- conversions
def _waymo_scenes(inp: SourceInput, opt: ReadOptions, skipped: Skipped) -> Iterator[SceneBuild]:
    if not opt.skip_bad:  # every CRC first: a damaged file stops before anything is written
        for record in read_records(inp.path):
            if isinstance(record, RecordError):
                raise record
    for item in waymo.read_scenarios(inp.path, skip_bad=opt.skip_bad, skipped=skipped):

        def build(item: waymo.ScenarioRecord = item) -> Scene:
            return waymo.scenario_to_scene(
                item.scenario,
                source=inp.path,
                record=item.index,
                paths=opt.paths,
                settings=opt.settings,
                progress=opt.progress,
                time_step=opt.time_step,
            )

        yield f"record-{item.index}", build


def _av2_scenes(inp: SourceInput, opt: ReadOptions, skipped: Skipped) -> Iterator[SceneBuild]:
    for parquet in av2.find_scenarios(inp.path):

        def build(parquet: pathlib.Path = parquet) -> Scene:
            return av2.parquet_to_scene(
                parquet, paths=opt.paths, settings=opt.settings, progress=opt.progress,
                skip_bad=opt.skip_bad, skipped=skipped, time_step=opt.time_step,
            )  # fmt: skip

        yield parquet.stem, build


def _av2_companions(inp: SourceInput) -> list[pathlib.Path]:
    folder = inp.path if inp.path.is_dir() else inp.path.parent
    return sorted(folder.glob("log_map_archive_*.json"))


def _av2_sensor_scenes(
    inp: SourceInput, opt: ReadOptions, skipped: Skipped
) -> Iterator[SceneBuild]:
    for log in av2_sensor.find_logs(inp.path):

        def build(log: pathlib.Path = log) -> Scene:
            return av2_sensor.read_scene(
                log, paths=opt.paths, settings=opt.settings, progress=opt.progress,
                skip_bad=opt.skip_bad, skipped=skipped, time_step=opt.time_step,
            )  # fmt: skip

        yield log.name, build


def _av2_sensor_companions(inp: SourceInput) -> list[pathlib.Path]:
    return sorted(p for p in inp.path.rglob("*") if p.is_file())


def _commonroad_scenes(
    inp: SourceInput, opt: ReadOptions, skipped: Skipped
) -> Iterator[SceneBuild]:
    def build() -> Scene:
        return commonroad.read_scene(
            inp.path,
            ego=opt.ego,
            paths=opt.paths,
            settings=opt.settings,
            skip_bad=opt.skip_bad,
            skipped=skipped,
            progress=opt.progress,
            time_step=opt.time_step,
        )

    yield inp.path.stem, build


def _interaction_map(inp: SourceInput) -> pathlib.Path:
    if inp.map is not None:
        return inp.map
    found = interaction_map_for(inp.path)
    if found is None:
        n = len(list(inp.path.parent.glob("*.osm")))
        what = f"{n} .osm maps beside it" if n else "no .osm map beside it (nor in ../maps/)"
        raise ConversionError(f"{inp.path}: {what}; name the map with --map MAP.osm")
    return found


def _interaction_scenes(
    inp: SourceInput, opt: ReadOptions, skipped: Skipped
) -> Iterator[SceneBuild]:
    def build() -> Scene:
        return interaction.read_scene(
            inp.files,
            _interaction_map(inp),
            ego=opt.ego,
            origin=opt.origin,
            paths=opt.paths,
            settings=opt.settings,
            skip_bad=opt.skip_bad,
            skipped=skipped,
            progress=opt.progress,
            time_step=opt.time_step,
        )

    yield inp.path.stem, build


def _interaction_companions(inp: SourceInput) -> list[pathlib.Path]:
    try:
        return [*inp.extra, _interaction_map(inp)]
    except ConversionError:
        return list(inp.extra)


def _scenarionet_group(files: Sequence[pathlib.Path]) -> list[SourceInput]:
    """One input per folder of scenario pickles: a database folder (its index names its
    scenarios, perhaps in sub-folders, which it then claims) or a plain folder (all its
    scenarios). Shallow folders first, so a merged database claims its parts."""
    files = sorted(set(files))
    claimed: set[pathlib.Path] = set()
    out = []
    for folder in sorted({f.parent for f in files}, key=lambda p: (len(p.parts), p)):
        mine = [f for f in files if f.parent == folder and f not in claimed]
        if not mine:
            continue
        claimed.update(mine)
        if scenarionet.is_database(folder):
            claimed.update(p.absolute() for p in scenarionet.companions(folder))
        out.append(SourceInput(source="scenarionet", path=folder))
    return out


def _scenarionet_scenes(
    inp: SourceInput, opt: ReadOptions, skipped: Skipped
) -> Iterator[SceneBuild]:
    for f in scenarionet.scenario_files(inp.path):  # every named file exists, or nothing starts

        def build(f: pathlib.Path = f) -> Scene:
            return scenarionet.read_scene(
                f, paths=opt.paths, settings=opt.settings, progress=opt.progress,
                skip_bad=opt.skip_bad, skipped=skipped, time_step=opt.time_step,
            )  # fmt: skip

        yield f.stem, build


# ---------------------------------------------------------------------- the registry
SOURCES: dict[str, SourceSpec] = {
    spec.name: spec
    for spec in (
        SourceSpec(
            name="waymo",
            title="Waymo Open Motion Dataset (TFRecord of Scenario records)",
            help="Convert a Waymo Open Motion Dataset TFRecord file (Scenario records) to "
            "MCAP scenes.\n\nEach Scenario becomes one scene: every track is an agent (valid "
            "where Waymo marks its state valid), the self-driving car is the ego, the lanes "
            "are the map, and objects_of_interest / tracks_to_predict travel as labels. No "
            "TensorFlow is needed.\n\nEvery record's CRC is checked before anything is "
            "written, so a damaged file stops with an error naming the record (use "
            "--skip-bad to convert the others).",
            examples=(
                "replay convert waymo training.tfrecord-00000-of-01000 -o scenes/",
                "replay convert waymo one_scenario.tfrecord -o scene.mcap --paths hindsight",
            ),
            argument="TFRECORD",
            patterns=("*.tfrecord", "*.tfrecord-*", "*.tfrecords"),
            detect=_is_tfrecord,
            scenes=_waymo_scenes,
            records="records",
            multi_scene=True,
        ),
        SourceSpec(
            name="av2",
            title="Argoverse 2 motion forecasting (scenario parquet + map JSON)",
            help="Convert Argoverse 2 motion-forecasting scenarios to MCAP scenes.\n\n"
            "SOURCE is a scenario_<id>.parquet file, a scenario folder (the parquet and its "
            "log_map_archive_<id>.json), or a split folder holding scenario folders. The AV "
            "track is the ego; Argoverse 2 has no object sizes, so documented defaults per "
            "object type are used; the focal and scored tracks travel as labels. Without a "
            "map JSON beside a parquet, every agent gets a straight path.",
            examples=(
                "replay convert av2 val/0a1e6f0a-1817-4a98-b02e-db8c9327d151 -o scene.mcap",
                "replay convert av2 val/ -o scenes/ --skip-bad",
            ),
            argument="SOURCE",
            patterns=("scenario_*.parquet",),
            detect=_is_parquet,
            scenes=_av2_scenes,
            records="scenarios",
            companions=_av2_companions,
            folder_input=True,
            multi_scene=True,
        ),
        SourceSpec(
            name="av2-sensor",
            title="Argoverse 2 Sensor log (cuboid annotations, poses, map)",
            help="Convert an Argoverse 2 Sensor log to an MCAP scene.\n\nLOG_DIR holds "
            "annotations.feather (or annotations_with_ego.feather), "
            "city_SE3_egovehicle.feather and map/log_map_archive_*.json; a folder of logs "
            "gives one scene per log. Every cuboid is moved from the vehicle frame to the "
            "city frame with the vehicle's pose at the same timestamp; the autonomous "
            "vehicle is the ego; speeds come from finite differences of the positions; "
            "static categories (bollards, cones, barrels, signs) are left out.",
            examples=(
                "replay convert av2-sensor sensor/val/adcf7d18-0510-35b0-a2fa-b4cea13a6d76 "
                "-o log.mcap",
                "replay convert av2-sensor sensor/val/ -o scenes/",
            ),
            argument="LOG_DIR",
            patterns=(av2_sensor.POSES_FILE,),
            detect=_is_log_pose_file,
            scenes=_av2_sensor_scenes,
            records="logs",
            group=_av2_sensor_group,
            companions=_av2_sensor_companions,
            folder_input=True,
            multi_scene=True,
        ),
        SourceSpec(
            name="commonroad",
            title="CommonRoad XML scenario (2018b/2020a)",
            help="Convert a CommonRoad XML scenario (2018b/2020a) to an MCAP scene.\n\nEvery "
            "dynamic obstacle is an agent, every static obstacle a standing one; lanelets "
            "(centre line = mean of the two bounds) and their successor links are the map. "
            "A CommonRoad planning problem has no trajectory, so one of the dynamic "
            "obstacles is replayed as the ego (default: the vehicle that travels farthest). "
            "The frames are the time steps at which the ego has a state.",
            examples=(
                "replay convert commonroad USA_US101-5_1_T-1.xml -o us101.mcap",
                "replay convert commonroad ZAM_Tjunction-1_97_T-1.xml -o scenes/ --ego 2",
            ),
            argument="XML_FILE",
            patterns=("*.xml",),
            detect=_is_commonroad,
            scenes=_commonroad_scenes,
            records="obstacles",
            ego_option=True,
        ),
        SourceSpec(
            name="interaction",
            title="INTERACTION / levelX-style track CSVs with a Lanelet2 map",
            help="Convert the track CSV(s) of one INTERACTION (levelX-style) recording and "
            "its Lanelet2 map to a scene.\n\nSeveral CSVs of one recording (vehicle and "
            "pedestrian tracks) become one scene. A CSV needs track_id, frame_id, "
            "timestamp_ms, agent_type, x, y, vx, vy; psi_rad, length and width are used "
            "when present (pedestrian files lack them: the heading then follows the "
            "velocity and sizes are defaults per kind). The map is --map, else the only "
            "*.osm beside the first CSV; lat/lon nodes are projected (UTM at --origin).",
            examples=(
                "replay convert interaction vehicle_tracks_000.csv pedestrian_tracks_000.csv "
                "--map DR_USA_Intersection_EP0.osm -o ep0.mcap",
                "replay convert interaction vehicle_tracks_000.csv -o scenes/ --ego 3",
            ),
            argument="TRACKS_CSV",
            patterns=("*.csv",),
            detect=_is_track_csv,
            scenes=_interaction_scenes,
            records="CSV rows",
            group=_interaction_group,
            companions=_interaction_companions,
            many_inputs=True,
            ego_option=True,
            map_option=True,
        ),
        SourceSpec(
            name="scenarionet",
            title="ScenarioNet scenarios (nuScenes, nuPlan, Lyft, Waymo, AV2 as pickles)",
            help="Convert ScenarioNet scenarios to MCAP scenes, one per scenario.\n\n"
            "INPUT is a scenario .pkl or a ScenarioNet database folder: the files its "
            "dataset_mapping.pkl (or dataset_summary.pkl) names, else every *.pkl in it. "
            "Files are loaded without running anything from them: a pickle that names any "
            "Python global other than numpy's arrays and builtin containers is refused. The "
            "ego is metadata.sdc_id; cones and barriers are standing 'other' agents; "
            "lanes without successor links (nuScenes) are chained where one starts at "
            "another's end, and a vehicle off every lane follows its recorded future; "
            "Waymo's objects_of_interest / tracks_to_predict travel as labels.",
            examples=(
                "replay convert scenarionet sd_nuscenes_v1.0-mini_scene-0061.pkl -o scene.mcap",
                "replay convert scenarionet nuscenes_db/ -o scenes/",
            ),
            argument="INPUT",
            patterns=("*.pkl",),
            detect=scenarionet.is_scenario_file,
            scenes=_scenarionet_scenes,
            records="scenarios",
            group=_scenarionet_group,
            companions=lambda inp: scenarionet.companions(inp.path),
            folder_input=True,
            multi_scene=True,
        ),
    )
}

SCENE_PATTERNS: tuple[str, ...] = ("*.mcap",)
"""Files that are scenes already (``replay batch`` replays them without converting)."""

DATA_SUFFIXES = frozenset(
    {".xml", ".csv", ".parquet", ".feather", ".tfrecord", ".tfrecords", ".pkl"}
)
"""Suffixes of files that look like traffic data: one that no source claims is reported
(a file nobody reads silently is a dataset left out). Other files (READMEs, images, maps
that no track file uses) are ignored."""


def spec(name: str) -> SourceSpec:
    """The source called ``name``; ConversionError listing the valid names otherwise."""
    try:
        return SOURCES[name]
    except KeyError:
        raise ConversionError(f"unknown source {name!r}; valid: {', '.join(SOURCES)}") from None


def _matches(path: pathlib.Path, patterns: Iterable[str]) -> bool:
    return any(fnmatch.fnmatch(path.name, p) for p in patterns)


def detect(path: pathlib.Path) -> SourceSpec | None:
    """The source of one file (or of a log folder or ScenarioNet database folder), or None."""
    path = pathlib.Path(path)
    if path.is_dir():
        if av2_sensor.is_log_dir(path):
            return SOURCES["av2-sensor"]
        return SOURCES["scenarionet"] if scenarionet.is_database(path) else None
    for s in SOURCES.values():
        if _matches(path, s.patterns) and s.detect(path):
            return s
    return None


@dataclass
class Discovery:
    """What :func:`discover` found: inputs per source, scene files, and files that look
    like data but that no source reads."""

    inputs: list[SourceInput] = field(default_factory=list)
    scenes: list[pathlib.Path] = field(default_factory=list)
    unreadable: list[pathlib.Path] = field(default_factory=list)


def discover(paths: Sequence[str | os.PathLike], exclude: pathlib.Path | None = None) -> Discovery:
    """Sort the files named by ``paths`` (files, log folders, or folder trees searched
    recursively) into inputs of each source, MCAP scenes, and unreadable data files.

    Sources claim files in registry order; a file that a source reads besides its input
    (a map, a log's other files) is claimed with it. Files under ``exclude`` are ignored.
    """
    files: list[pathlib.Path] = []
    for raw in paths:
        p = pathlib.Path(raw).expanduser().absolute()
        if p.is_dir() and not av2_sensor.is_log_dir(p):
            files += sorted(f for f in p.rglob("*") if f.is_file())
        elif p.is_dir():
            files.append(p / av2_sensor.POSES_FILE)
        elif p.is_file():
            files.append(p)
        else:
            raise FileNotFoundError(2, "no such file or folder", str(raw))
    if exclude is not None:
        ex = exclude.absolute()
        files = [f for f in files if not f.is_relative_to(ex)]
    found = Discovery()
    claimed: set[pathlib.Path] = set()
    for s in SOURCES.values():
        mine = [f for f in files if f not in claimed and _matches(f, s.patterns) and s.detect(f)]
        for inp in s.inputs(mine):
            found.inputs.append(inp)
            claimed.update(inp.files)
            claimed.update(pathlib.Path(c).absolute() for c in s.companions(inp))
        claimed.update(mine)
    for f in files:
        if f in claimed:
            continue
        if _matches(f, SCENE_PATTERNS):
            found.scenes.append(f)
        elif f.suffix.lower() in DATA_SUFFIXES or ".tfrecord" in f.name:
            found.unreadable.append(f)
    return found


def unreadable_reason(path: pathlib.Path) -> str:
    """One line for a data file no source reads."""
    known = "; ".join(f"{s.name}: {', '.join(s.patterns)}" for s in SOURCES.values())
    if path.suffix.lower() == ".pkl":  # a pickle beside the data, or a damaged scenario
        return (
            f"{path}: a pickle that is not a ScenarioNet scenario (its start names no"
            " 'version', 'length' and 'tracks' or 'metadata'); convert it with 'replay"
            " convert scenarionet' to see why, or move it out of the input folder"
        )
    return (
        f"{path}: no converter reads this file (not one of: {known}); convert it with "
        "'replay convert SOURCE' naming the source, or move it out of the input folder"
    )

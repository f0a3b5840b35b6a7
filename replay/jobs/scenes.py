"""Scene identity: which files a corpus command reads, and the key of each.

Every corpus command (``replay evaluate``, ``replay stats``; ``replay plan`` and
``replay calibrate`` next) finds its inputs with :func:`resolve_inputs` and keys them with
:func:`scene_refs`:

- **One file, one scene.** The same file named twice, or through two paths (a folder and
  a file inside it, a symlink, a hard link), is read once: files are told apart by
  device and inode, not by the path they were given as.
- **Unique keys.** A scene's key is its path relative to the deepest folder that holds
  every input, without the suffix: ``replay evaluate d1 d2`` keys ``d1/a/x.mcap`` and
  ``d2/a/x.mcap`` as ``d1/a/x`` and ``d2/a/x``, two scenes; scenes given from one folder
  keep their file names (``x``). A scene and a table with the same key (``x.mcap``,
  ``x.parquet``) keep their suffixes in the key. The key is the ``scene`` column of the
  tables a scene produces and the name of its part files (:mod:`replay.jobs.runner`).
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Sequence
from dataclasses import dataclass

from replay.errors import ReplayError

SCENE_SUFFIXES = (".mcap",)
TABLE_SUFFIXES = (".parquet", ".csv")


@dataclass(frozen=True)
class Inputs:
    """The files named on the command line, split by kind (each list sorted)."""

    scenes: tuple[pathlib.Path, ...]
    tables: tuple[pathlib.Path, ...]


@dataclass(frozen=True)
class SceneRef:
    """One input file of a corpus command: ``key`` (unique among the run's inputs, see the
    module docstring), ``path`` (absolute) and ``kind`` (``scene`` or ``table``)."""

    key: str
    path: pathlib.Path
    kind: str

    @property
    def dataset(self) -> str:
        """The dataset of a scene: the name of the folder its file is in."""
        return self.path.parent.name


def resolve_inputs(
    paths: Sequence[pathlib.Path],
    *,
    output_dir: pathlib.Path | None = None,
    output_stems: Sequence[str] = (),
) -> Inputs:
    """Scenes (``.mcap``) and tables (``.parquet``, ``.csv``) among ``paths``. A folder
    contributes its scenes, in sub-folders too (as ``replay batch`` finds them; hidden
    files and folders are left out), and the tables directly inside it (a folder's
    sub-folders hold other tables: ``replay batch`` writes frames tables beside its
    agents tables). Nothing inside ``output_dir`` (the command's own output folder) is
    taken from a folder, except, when the output folder is an input folder itself,
    files that are not outputs (``output_stems``: the names the command writes), so
    that a second ``replay stats DIR -o DIR`` does not read its own ``errors.csv``.
    The same file found twice (by inode) is listed once."""
    scenes: list[pathlib.Path] = []
    tables: list[pathlib.Path] = []
    out = None if output_dir is None else output_dir.absolute()
    stems = set(output_stems)

    def ours(f: pathlib.Path) -> bool:
        if out is None:
            return False
        where = f.absolute()
        if where.parent == out:
            return where.stem in stems or where.name == "summary.json"
        return where.is_relative_to(out)

    for p in paths:
        if p.is_dir():
            found = [f for f in sorted(p.rglob("*")) if _kind(f) == "scene" and _visible(f, p)]
            found = [f for f in found if f.is_file()]
            found += [f for f in sorted(p.iterdir()) if f.is_file() and _kind(f) == "table"]
            found = [f for f in found if not ours(f) and not f.name.startswith(".")]
            if not found:
                raise ReplayError(
                    f"{p}: no .mcap scene (in it or its sub-folders) or .parquet/.csv table"
                    " in this folder"
                )
        else:
            if not _kind(p):
                raise ReplayError(
                    f"{p}: expected an MCAP scene (.mcap) or a table (.parquet, .csv), "
                    f"got {p.suffix or 'no suffix'!r}"
                )
            found = [p]
        for f in found:
            (scenes if _kind(f) == "scene" else tables).append(f)
    return Inputs(tuple(distinct_files(scenes)), tuple(distinct_files(tables)))


def file_identity(path: str | os.PathLike[str]) -> tuple[int, int] | str:
    """What tells files apart: device and inode (a symlink, a hard link and the file are
    one), or the absolute path of a path that cannot be read (reported when read)."""
    try:
        st = os.stat(path)
    except OSError:
        return os.path.abspath(path)
    return (st.st_dev, st.st_ino)


def check_not_outputs(
    inputs: Inputs, output_dir: pathlib.Path, output_names: Sequence[str]
) -> None:
    """Refuse an input that the command would write over (a file named as one of its
    outputs, ``output_names``, directly in ``output_dir``), before any scene runs: found
    when the outputs are committed, it came after the parts were written."""
    out = output_dir.absolute()
    for f in (*inputs.scenes, *inputs.tables):
        if f.absolute().parent == out and f.name in output_names:
            raise ReplayError(
                f"{out / f.name}: is also an input ({f}); refusing to write over it. Give "
                "another output folder (-o) or move the input"
            )


def distinct_files(files: Sequence[pathlib.Path]) -> list[pathlib.Path]:
    """``files`` without repeats of one file (:func:`file_identity`: a symlink, a hard
    link, a file given itself and inside its folder); the first path given is kept."""
    seen: set[tuple[int, int] | str] = set()
    out = []
    for f in files:
        identity = file_identity(f)
        if identity not in seen:
            seen.add(identity)
            out.append(f)
    return out


def _visible(f: pathlib.Path, root: pathlib.Path) -> bool:
    return not any(part.startswith(".") for part in f.relative_to(root).parts)


def _kind(path: pathlib.Path) -> str:
    suffix = path.suffix.lower()
    if suffix in SCENE_SUFFIXES:
        return "scene"
    return "table" if suffix in TABLE_SUFFIXES else ""


def scene_refs(inputs: Inputs) -> list[SceneRef]:
    """Every input with its unique key (see the module docstring), scenes first, each
    kind in the order of ``inputs``."""
    files = [*inputs.scenes, *inputs.tables]
    kinds = ["scene"] * len(inputs.scenes) + ["table"] * len(inputs.tables)
    absolute = [pathlib.Path(os.path.abspath(f)) for f in files]
    if not absolute:
        return []
    root = pathlib.Path(os.path.commonpath([str(p.parent) for p in absolute]))
    rel = [p.relative_to(root).as_posix() for p in absolute]
    bare = [r[: -len(p.suffix)] if p.suffix else r for r, p in zip(rel, absolute, strict=True)]
    counts: dict[str, int] = {}
    for b in bare:
        counts[b] = counts.get(b, 0) + 1
    keys = [b if counts[b] == 1 else r for b, r in zip(bare, rel, strict=True)]
    return [SceneRef(k, p, kind) for k, p, kind in zip(keys, absolute, kinds, strict=True)]

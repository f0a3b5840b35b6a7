"""The rules of docs/architecture.md that import-linter does not cover: no module-level
import cycles, imports at the top of library modules, mcap and click only in their layers
(also for modules added after the contracts were written), and one base for every error.

(The layers and the forbidden imports are import-linter contracts in pyproject.toml,
checked by ``lint-imports`` in ``.ci/run``.)
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pathlib

from conftest import ROOT

from risk.errors import RiskReplayError

PACKAGES = ("risk", "outputs", "converters", "replay", "recordings")

#: Imports inside functions, each kept for a reason measured or stated at the import
#: (start-up cost, an optional dependency, an import cycle inside ``risk``). New ones
#: need a reason too: add them here with it.
ALLOWED_INNER_IMPORTS = {
    # tomli_w only to write a cascade file
    ("risk/cascade_config.py", "tomli_w"),
    # numba's BLAS probe answered before numba's own import of arraymath (0.3-0.6 s saved
    # per process; risk/kernel_jit.py explains)
    ("risk/kernel_jit.py", "numba.np"),
    # numba (about 0.9 s with its set-up) only when the ahead-of-time kernel is not built,
    # and only to build it (risk/kernel_aot_build.py)
    ("risk/kernel.py", "risk"),
    ("risk/kernel_aot_build.py", "numba.pycc"),
    # the per-source dispatch of batch conversions, each converter loaded when its
    # dataset is converted (a failure to load is the task's "setup" failure)
    ("replay/batch/tasks.py", "converters"),
    ("replay/batch/tasks.py", "converters.errors"),
    ("replay/batch/tasks.py", "converters.scene.writer"),
    ("replay/batch/tasks.py", "converters.tracks"),
    # polars (0.3 s to import) only for a Parquet keep-list (JSON Lines needs none)
    ("replay/core/keep_lists.py", "polars"),
    # matplotlib (about 1 s to import) only when replay plan writes its plots
    ("replay/analysis/planner_eval/study.py", "replay.analysis.planner_eval"),
    # optional dependency, installed with the 'ray' extra
    ("replay/jobs/engines.py", "ray"),
    # optional dependency, installed with the 'planner' extra (fiss-planner's Frenet
    # planners); a missing extra is a one-line error naming it
    ("replay/planning/frenet.py", "fiss_planner"),
    # pdm's compiled loops (numba, about 0.3 s) only in processes that plan with pdm
    ("replay/planning/pdm.py", "replay.planning.pdm_kernel"),
    # the LQR tracker imports the tracker interface: loaded when that tracker is asked for
    ("replay/planning/tracking.py", "replay.planning.lqr"),
    # rerun (about 1 s) only for workers that write a recording / on a failure
    ("recordings/__init__.py", "recordings.recorder"),
    # the writer (rerun, about 1 s): only when writing, or in the writer process
    ("recordings/recorder.py", "recordings"),
    # polars (about 0.3 s): only to build or write a table, else in the output process
    ("replay/core/tables.py", "replay.core"),
    ("replay/core/worker.py", "recordings"),
    ("replay/core/scene_run.py", "replay.core.tables"),
    ("replay/core/scene_run.py", "recordings"),
    ("replay/jobs/failures.py", "recordings.errors"),
    # matplotlib (about 1 s) only in the driver, not in every spawned worker
    ("replay/batch/driver.py", "replay.analysis.stats.run"),
    ("replay/batch/driver.py", "replay.analysis.stats.streaming"),
    ("replay/analysis/experiment/report.py", "replay.analysis.stats.plots"),
    # importlib.metadata (about 25 ms of every command's start-up) only for __version__
    ("replay/__init__.py", "importlib.metadata"),
}


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if path.name.endswith("_pb2.py"):
                continue
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _top_level_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Imports run when the module loads: module body, ``if``/``try`` blocks in it, but
    not ``if TYPE_CHECKING:``."""
    found: list[ast.Import | ast.ImportFrom] = []
    stack: list[ast.stmt] = list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        elif isinstance(node, ast.If) and not _is_type_checking(node):
            stack += node.body + node.orelse
        elif isinstance(node, ast.Try):
            stack += node.body + node.orelse + node.finalbody
            for handler in node.handlers:
                stack += handler.body
    return found


def _targets(node: ast.Import | ast.ImportFrom, modules: dict[str, pathlib.Path]) -> set[str]:
    """The project modules an import statement loads (explicitly named)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
    return {n for n in names if n in modules}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        graph[name] = set().union(*(_targets(n, modules) for n in _top_level_imports(tree))) - {
            name
        }
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_level_import_cycles():
    graph = _graph()
    assert {m.split(".")[0] for m in graph} == set(PACKAGES)
    assert len(graph) > 60
    assert _cycles(graph) == []


def _file_graph() -> dict[str, set[str]]:
    """Which modules each module names in any import statement: at the top, inside
    functions, and under ``if TYPE_CHECKING:`` alike (an edge a reader follows)."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import) or (
                isinstance(node, ast.ImportFrom) and not node.level
            ):
                found |= _targets(node, modules)
        graph[name] = found - {name}
    return graph


def test_no_file_level_import_cycles():
    """No two files import each other, directly or round a loop, by any import at all:
    a type or a late import shared both ways goes into a module of its own (as
    recordings/frames.py and replay/core/table_columns.py do)."""
    graph = _file_graph()
    assert graph["replay.core.tables"] >= {"replay.core.table_file"}  # (late imports count)
    assert _cycles(graph) == []


def test_imports_inside_functions_are_the_listed_ones():
    modules = _modules()
    found = set()
    for path in modules.values():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith("replay/cli/commands/") or rel == "replay/cli/app.py":
            continue  # the CLI loads each command's module on first use (replay/cli/app.py)
        for func in ast.walk(tree):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(func):
                if isinstance(node, ast.Import):
                    found |= {(rel, a.name) for a in node.names}
                elif isinstance(node, ast.ImportFrom):
                    found.add((rel, node.module or ""))
    assert found - ALLOWED_INNER_IMPORTS == set()


def _imported_names(path: pathlib.Path) -> set[str]:
    """Every module an ``import`` statement anywhere in the file names (also in functions)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


#: third-party package -> the only package of ours that may import it
ONLY_IN = {"mcap": "converters.scene", "mcap_protobuf": "converters.scene", "click": "replay.cli"}


def test_mcap_and_click_stay_in_their_layers():
    users: dict[str, set[str]] = {library: set() for library in ONLY_IN}
    for name, path in _modules().items():
        for imported in _imported_names(path):
            top = imported.split(".")[0]
            if top in users:
                users[top].add(name)
    for library, owner in ONLY_IN.items():
        outside = {m for m in users[library] if m != owner and not m.startswith(owner + ".")}
        assert outside == set(), f"{library} imported outside {owner}"
    # not vacuous: the owners do import them
    assert "converters.scene.writer" in users["mcap"] and "converters.scene.reader" in users["mcap"]
    assert "replay.cli.app" in users["click"]


#: Exception classes of ours that are not meant for the user (each with its reason).
INTERNAL_EXCEPTIONS: set[str] = {
    # SIGTERM / SIGHUP as a KeyboardInterrupt (a stop, like Ctrl-C; not an error)
    "replay.core.process_exit.Stopped",
}


def test_every_error_derives_from_the_one_base():
    found = {}
    for name in sorted(_modules()):
        module = importlib.import_module(name)
        for obj in vars(module).values():
            if (
                inspect.isclass(obj)
                and issubclass(obj, BaseException)
                and not issubclass(obj, Warning)
                and obj.__module__ == name
            ):
                found[f"{name}.{obj.__qualname__}"] = obj
    assert {"risk.errors.RiskError", "outputs.process.OutputProcessError"} <= set(found)
    assert len(found) >= 15
    strays = {
        qualname
        for qualname, cls in found.items()
        if not issubclass(cls, RiskReplayError) and qualname not in INTERNAL_EXCEPTIONS
    }
    assert strays == set()


def test_commands_do_not_import_each_other():
    """A command parses, calls the library and prints: logic two commands share lives in
    the library (e.g. replay.core.scene_run for run and demo), not in a command module.
    (Groups load their subcommands by name, as replay/cli/app.py does: no import.)"""
    modules = _modules()
    commands = {m for m in modules if m.startswith("replay.cli.commands.")}
    assert {"replay.cli.commands.run", "replay.cli.commands.demo"} <= commands
    graph = _file_graph()
    assert {c: graph[c] & commands for c in commands if graph[c] & commands} == {}


def test_the_scene_package_imports_no_converter():
    """converters.scene sits below every converter (the import contract lists today's
    modules; this also covers ones added later): of the converters package it imports
    only itself and the shared error type."""
    graph = _file_graph()
    scene = {m for m in graph if m == "converters.scene" or m.startswith("converters.scene.")}
    assert {"converters.scene.reader", "converters.scene.writer"} <= scene
    allowed = scene | {"converters", "converters.errors"}
    outside = {
        (m, t) for m in scene for t in graph[m] if t.startswith("converters") and t not in allowed
    }
    assert outside == set()

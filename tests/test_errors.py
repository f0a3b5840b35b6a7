"""The one error base (:class:`risk.errors.RiskReplayError`): its one-line text, its round
trip between processes, and the command line catching it (and only it) as ``Error: ...``."""

from __future__ import annotations

import pickle

import click
import pytest
from click.testing import CliRunner

from converters.errors import ConversionError
from converters.scene.errors import SceneFormatError
from outputs.transaction import OutputError
from replay.cli.app import LazyGroup
from replay.errors import ReplayError
from risk.errors import FrameError, RiskError, RiskReplayError, UnknownModelError


def test_message_and_hint_make_one_line():
    error = ConversionError("no tracks in scene.csv", hint="pass --source interaction")
    assert error.message == "no tracks in scene.csv" and error.hint == "pass --source interaction"
    assert str(error) == "no tracks in scene.csv; pass --source interaction"
    assert str(ReplayError("nothing to do")) == "nothing to do"
    assert str(ReplayError()) == "ReplayError"  # never an empty Error: line


def test_package_errors_keep_their_builtin_kinds():
    # callers that caught ValueError / RuntimeError before the common base still do
    assert issubclass(RiskError, ValueError) and issubclass(ReplayError, RuntimeError)
    for cls in (RiskError, ConversionError, ReplayError, SceneFormatError, OutputError):
        assert issubclass(cls, RiskReplayError)


@pytest.mark.parametrize(
    "error",
    [
        FrameError("speed", "must be >= 0", index=2, agent_id=7),
        UnknownModelError("ttx", ["ttc", "survival"]),
        ConversionError("bad record", hint="use --skip-bad"),
    ],
)
def test_errors_survive_pickling(error):
    # errors cross process boundaries (the pool, batch workers); subclasses whose
    # __init__ takes other arguments than the message rebuild too
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is type(error) and str(back) == str(error)
    assert back.__dict__ == error.__dict__


def _group_running(command: click.Command) -> LazyGroup:
    group = LazyGroup(name="replay", lazy_commands={})
    group.get_command = lambda ctx, name: command if name == "go" else None  # type: ignore[method-assign]
    group.list_commands = lambda ctx: ["go"]  # type: ignore[method-assign]
    return group


def test_cli_prints_any_subclass_of_the_base_as_one_error_line():
    class NewPackageError(RiskReplayError):  # a package the CLI has never heard of
        pass

    @click.command()
    def go() -> None:
        raise NewPackageError("the widget is upside down", hint="turn it over")

    result = CliRunner().invoke(_group_running(go), ["go"])
    assert result.exit_code == 1
    assert result.output == "Error: the widget is upside down; turn it over\n"


def test_cli_leaves_bugs_alone():
    @click.command()
    def go() -> None:
        raise ValueError("a bug, not a user error")

    result = CliRunner().invoke(_group_running(go), ["go"])
    assert result.exit_code == 1 and isinstance(result.exception, ValueError)
    assert "Error:" not in result.output

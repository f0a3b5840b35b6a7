"""The ``replay`` command line.

Subcommands live in ``replay/cli/commands/<name>.py`` and are imported only when used, so that
``replay --help`` stays fast. Errors meant for the user (every package's derive from
:class:`risk.errors.RiskReplayError`) become one line ``Error: ...`` and exit code 1,
without a traceback; so do system errors (``OSError``: a missing file, a full disk),
whose message names the file (or standard output: ``replay models > /dev/full``).

Stopping: Ctrl-C, SIGTERM and SIGHUP (installed here, once, around every command: see
:mod:`replay.core.process_exit`) unwind the command like an error, so that its output
guard removes temporary and partial files and its workers are stopped; the command then
prints one line saying what was kept and exits 130, 143 or 129.
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import importlib.util
import os
import sys

import click

from outputs.atomic import placed_outputs
from outputs.transaction import target_of_temp
from replay.core.process_exit import exit_status, signal_name, stop_on_signals
from risk.errors import RiskReplayError

__all__ = ["main"]

# name -> "module:attribute"; the order is the order of ``replay --help``.
COMMANDS: dict[str, str] = {
    "demo": "replay.cli.commands.demo:demo",
    "run": "replay.cli.commands.run:run",
    "convert": "replay.cli.commands.convert:convert",
    "inspect": "replay.cli.commands.inspect:inspect_cmd",
    "calibrate": "replay.cli.commands.calibrate:calibrate",
    "stats": "replay.cli.commands.stats:stats",
    "evaluate": "replay.cli.commands.evaluate:evaluate",
    "plan": "replay.cli.commands.plan:plan",
    "experiment": "replay.cli.commands.experiment:experiment",
    "batch": "replay.cli.commands.batch:batch",
    "models": "replay.cli.commands.models:models",
}


class LazyGroup(click.Group):
    """A click group that imports each subcommand's module on first use.

    ``lazy_commands`` maps a subcommand name to ``"module:attribute"``; entries whose
    module does not exist are not listed.
    """

    def __init__(self, *args, lazy_commands: dict[str, str] | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.lazy_commands = COMMANDS if lazy_commands is None else lazy_commands

    def list_commands(self, ctx: click.Context) -> list[str]:
        return [name for name, target in self.lazy_commands.items() if _module_exists(target)]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = self.lazy_commands.get(cmd_name)
        if target is None or not _module_exists(target):
            return None
        module_name, attr = target.split(":")
        return getattr(importlib.import_module(module_name), attr)

    def invoke(self, ctx: click.Context):
        if sys.stdout is None:  # started with stdout closed (``>&-``): fail on first use
            sys.stdout = _ClosedStream()
        try:
            with stop_on_signals():  # the one place SIGTERM / SIGHUP are handled
                return super().invoke(ctx)
        except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP: clean-up has run
            _stopped(ctx, exc)
        except OSError as exc:
            if exc.errno != errno.EPIPE and not isinstance(exc, BrokenPipeError):
                _end_line(sys.stderr)
                raise click.ClickException(capped(_os_message(exc))) from None
            quiet_broken_pipe()
        except RiskReplayError as exc:  # the one base of every error meant for the user
            _end_line(sys.stderr)  # (a progress bar may have left the cursor mid-line)
            raise click.ClickException(capped(str(exc))) from None
        except click.ClickException as exc:  # a command's own, and usage errors
            exc.message = capped(exc.message)  # type: ignore[misc]
            raise


#: Longest error line: a value quoted from a file (5,000 digits, a list of names) made
#: one line of thousands of characters (issue 36).
MAX_ERROR_CHARS = 500


def capped(message: str) -> str:
    """``message`` on one line of at most :data:`MAX_ERROR_CHARS` characters: its start
    and its end (which says what to do), the middle replaced by an ellipsis."""
    line = " ".join(message.split())
    if len(line) <= MAX_ERROR_CHARS:
        return line
    tail = MAX_ERROR_CHARS // 4
    return f"{line[: MAX_ERROR_CHARS - tail - 3]} … {line[-tail:]}"


class _ClosedStream:
    """Stands in for a closed stdout: writing to it fails (exit 1) instead of vanishing."""

    def write(self, text: str) -> int:
        raise OSError(errno.EBADF, "standard output is closed")

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


def _stopped(ctx: click.Context, exc: BaseException) -> None:
    """One line on stderr saying what was kept, then exit ``128 + signal``."""
    _end_line(sys.stderr)
    kept = getattr(exc, "kept", None) or (
        "nothing was written (a command's outputs appear only when it finishes);"
        " run it again to start over"
    )
    with contextlib.suppress(OSError, ValueError):
        click.echo(f"Stopped by {signal_name(getattr(exc, 'signum', 2))}: {kept}", err=True)
    ctx.exit(exit_status(exc))


def _end_line(stream: object) -> None:
    """Start a fresh line on ``stream`` if a progress bar left the cursor inside one."""
    with contextlib.suppress(Exception):
        if stream.isatty():  # type: ignore[attr-defined]
            stream.write("\r\033[K")  # type: ignore[attr-defined]


def _os_message(exc: OSError) -> str:
    """The error's message, naming the target file rather than its temporary file (or
    standard output, when that is what failed: ``replay models > /dev/full``)."""
    if not exc.filename and exc.strerror and _from_stdout(exc):
        _stdout_to_devnull()  # (so that the exit's own flush does not fail again)
        written = placed_outputs()
        if not written:
            return f"cannot write to standard output: {exc.strerror}"
        names = ", ".join(str(p) for p in written[:3]) + (", ..." if len(written) > 3 else "")
        return (
            f"cannot write to standard output ({exc.strerror}) after writing {len(written)}"
            f" output(s), which are complete and kept: {names}"
        )
    if exc.errno in (errno.ENOTDIR, errno.EEXIST) and exc.filename:
        # (a file where a folder is needed, or the other way round: say what to do)
        return (
            f"{target_of_temp(exc.filename)}: {exc.strerror} (a file stands where a folder is"
            " needed, or a folder where a file is); choose another path or move it away"
        )
    if exc.strerror and exc.filename:
        name = target_of_temp(exc.filename)
        if name != exc.filename:
            return f"cannot write {name}: {exc.strerror}"
        return f"{exc.strerror}: {exc.filename}"
    message = str(exc) or type(exc).__name__
    if exc.filename and str(exc.filename) not in message:
        message = f"{message}: {target_of_temp(exc.filename)}"
    return message


def _from_stdout(exc: OSError) -> bool:
    """True when ``exc`` came from ``click.echo`` writing to stdout (not stderr): an
    error without a file name (``replay models > /dev/full``) then names stdout."""
    tb = exc.__traceback__
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_name == "echo" and frame.f_globals.get("__name__") == "click.utils":
            return not frame.f_locals.get("err", False)
        tb = tb.tb_next
    return False


def _stdout_to_devnull() -> None:
    with contextlib.suppress(OSError, ValueError, AttributeError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        finally:
            os.close(devnull)


def quiet_broken_pipe() -> None:
    """The reader of stdout went away (``replay models | head -1``): end quietly with
    status 0, as Unix tools do. Later writes (and the final flush) go to /dev/null."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass  # stdout is not a real file (a test runner): nothing to redirect
    finally:
        os.close(devnull)
    raise SystemExit(0)


def _module_exists(target: str) -> bool:
    return importlib.util.find_spec(target.split(":")[0]) is not None


@click.group(
    cls=LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.version_option(None, "--version", "-V", package_name="riskreplay", prog_name="replay")
def main() -> None:
    """Importance filtering with driving risk models, on recorded and synthetic traffic.

    Convert traffic logs to MCAP scenes, replay them through the nine risk models of
    Puphal et al. (ICRAE 2022) and their filter cascade, and review the results in the
    Rerun viewer or as tables.

    \b
    Start here:
      replay demo                      a synthetic intersection, end to end
      replay run scene.mcap            the cascade over every frame -> scene.rrd
      replay models                    the nine risk models and their parameters
    """

"""Which writers a ``replay`` command line will need, judged from its words alone, and the
output process (:mod:`outputs.process`) started for them before anything heavy loads.

Standard library only: ``replay``'s entry point (:mod:`replay.__main__`) calls
:func:`start_for` before it imports click and the CLI, so that the output process's
imports (rerun, about 1 s) begin as early as they can.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from outputs import process as background

#: The modules that write a recording and a table (imported by the output process).
RECORDING_WRITER = "recordings.writer"
TABLE_WRITER = "replay.core.table_file"


def output_writers(args: Sequence[str]) -> tuple[str, ...]:
    """The writer modules that ``replay ARGS`` will need, judged from the words alone (a
    wrong guess costs only an idle import): the recording's writer when there is a
    recording (``demo``; ``run`` unless ``--no-rrd`` or ``--ego all``), else the table's
    (``--table`` or ``--ego all``). Nothing for ``--help``."""
    args = list(args)
    if not args or args[0] not in ("run", "demo") or {"--help", "-h"} & set(args):
        return ()
    if args[0] == "demo":
        return (RECORDING_WRITER,)
    pairs = list(zip(args, [*args[1:], ""], strict=True))
    every_ego = any(a == "--ego=all" or (a == "--ego" and b == "all") for a, b in pairs)
    table = every_ego or any(a == "--table" or a.startswith("--table=") for a in args)
    record = not every_ego and "--no-rrd" not in args
    # (with both, the table is written in the replay's process: make_sinks says why)
    return (RECORDING_WRITER,) if record else (TABLE_WRITER,) * table


def start_for(args: Sequence[str]) -> background.OutputProcess | None:
    """Start the shared output process for ``replay ARGS`` when it will write something
    (and :func:`outputs.process.available` agrees); pair with
    :func:`outputs.process.release`. Nothing while the shell completes a word (click's
    ``_REPLAY_COMPLETE``)."""
    if os.environ.get("_REPLAY_COMPLETE"):
        return None
    preload = output_writers(args)
    return background.start(preload) if preload else None

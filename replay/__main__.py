"""``replay`` (the console script) and ``python -m replay``.

The output process (:mod:`outputs.process`) is started by the outputs themselves, when
a recording or a table sink begins (``SceneRecorder.begin``, ``TableSink.begin``): one
place, and nothing here guesses from the command line what a command will write."""

from __future__ import annotations

from replay.cli.app import main

if __name__ == "__main__":
    main()

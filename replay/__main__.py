"""``replay`` (the console script) and ``python -m replay``.

The output process starts first (:mod:`replay.early_output`), 0.1-0.2 s before the CLI's
own imports would let it, then the CLI runs."""

from __future__ import annotations

import sys

from base import background
from replay.early_output import start_for


def main() -> None:
    process = start_for(sys.argv[1:])
    try:
        from replay.cli import main as cli

        cli()
    finally:
        background.release(process)


if __name__ == "__main__":
    main()

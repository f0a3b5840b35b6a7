"""``replay`` (the console script) and ``python -m replay``.

The output process starts first (:mod:`replay.cli.output_prestart`), 0.1-0.2 s before the CLI's
own imports would let it, then the CLI runs."""

from __future__ import annotations

import sys

from outputs import process as background
from replay.cli.output_prestart import start_for


def main() -> None:
    process = start_for(sys.argv[1:])
    try:
        from replay.cli.app import main as cli

        cli()
    finally:
        background.release(process)


if __name__ == "__main__":
    main()

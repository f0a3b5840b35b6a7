"""Which exceptions are meant for the user: the CLI prints them as one line ``Error: ...``
without a traceback, and ``replay batch`` records them without the code location."""

from __future__ import annotations

from base.background import OutputProcessError  # standard library only: cheap to import
from base.guard import OutputError
from base.memory import MemoryLimitError


def user_errors() -> tuple[type[BaseException], ...]:
    """Exception types whose message is meant for the user (no traceback)."""
    # Imported on call, not at the top: ``risk`` loads numpy and the models (0.2 s with
    # ``python -X importtime``, twice what ``replay --help`` takes) and ``recordings``
    # loads rerun (about 1 s), which neither ``replay --help`` nor a batch worker that
    # writes no recording should pay.
    from converters.errors import ConversionError
    from recordings.errors import RecordingError
    from replay.errors import ReplayError
    from risk.errors import RiskError

    return (
        RiskError, ConversionError, ReplayError, RecordingError, OutputError,
        OutputProcessError, MemoryLimitError, OSError,
    )  # fmt: skip

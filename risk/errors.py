"""The one base of every error meant for the user, and the risk package's own errors.

:class:`RiskReplayError` sits here, in the lowest layer, so that every package (``risk``
and everything above it) can derive its errors from it. Standard library only: importing
this module loads nothing else (``risk/__init__.py`` loads its names on first use), so
the output process and the command line's start-up can import it for free.
"""

from __future__ import annotations

from typing import Any


class RiskReplayError(Exception):
    """Base of every error whose message is meant for the user.

    ``message`` says what is wrong, ``hint`` (optional) what to do about it; ``str()`` is
    the one line the command line prints after ``Error:`` (``message; hint``), without a
    traceback. Only the command line turns these into ``Error: ...`` and an exit status;
    ``replay batch`` records them without the code location. Anything else that escapes
    is a bug and keeps its traceback.
    """

    def __init__(self, message: object = "", *args: object, hint: str = "") -> None:
        super().__init__(message, *args)
        self.message = str(message)
        self.hint = hint

    def __str__(self) -> str:
        text = self.message or type(self).__name__
        return f"{text}; {self.hint}" if self.hint else text

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuilt without calling ``__init__``: subclasses take other arguments than
        # their message (FrameError's field and problem), and errors cross process
        # boundaries (the process pool, the batch workers).
        return (_rebuild, (type(self), self.args, self.__dict__))


def _rebuild(
    cls: type[RiskReplayError], args: tuple[object, ...], state: dict[str, Any]
) -> RiskReplayError:
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(state)
    return error


class RiskError(RiskReplayError, ValueError):
    """Base class of every error the risk package raises on bad input."""


class FrameError(RiskError):
    """A frame failed validation: names the agent (index and id) and the field."""

    def __init__(
        self, field: str, problem: str, *, index: int | None = None, agent_id: int | None = None
    ):
        self.field = field
        self.index = index
        self.agent_id = agent_id
        where = ""
        if index is not None:
            where = f"agent #{index}" + (f" (id {agent_id})" if agent_id is not None else "") + ": "
        super().__init__(f"{where}{field}: {problem}")


class UnknownModelError(RiskError):
    """A model name that is not in the registry; lists the valid ones."""

    def __init__(self, name: str, valid: list[str]):
        self.name = name
        self.valid = valid
        super().__init__(f"unknown risk model {name!r}; valid models: {', '.join(valid)}")

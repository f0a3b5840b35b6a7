"""Exceptions raised by the risk package.

Each carries a message a user can act on; only the CLI turns them into ``Error: ...``.
"""

from __future__ import annotations


class RiskError(ValueError):
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

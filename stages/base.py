"""The bottom layer both ``skyroute.stages`` and ``skyroute.pipeline`` import: the exception
hierarchy and the frozen settings base.  Nothing here imports another ``skyroute`` module, so
``stages`` never imports ``pipeline`` (``skyroute.pipeline.errors`` and
``skyroute.pipeline.model`` re-export these names for API stability).

Exceptions (rioxarray style): every message says what is wrong and how to fix it.  The CLI turns
any :class:`SkyrouteError` into a one-line message and exit code 2; anything else is a bug and
keeps its traceback.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class FrozenModel(BaseModel):
    """Base of all settings: immutable, strict about unknown keys."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)


class SkyrouteError(Exception):
    """Base class of every error skyroute raises on purpose."""


class ScenarioError(SkyrouteError, ValueError):
    """A scenario catalog entry is invalid.  ``problems`` lists every problem, each prefixed
    with its YAML path (``mission.start: ...``)."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = list(problems)
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{source}: {len(self.problems)} problem(s):\n{lines}")


class UnknownNameError(SkyrouteError, KeyError):
    """A name (scenario, planner, vehicle, option) is not one of the known ones."""

    def __init__(self, kind: str, name: str, known: list[str] | tuple[str, ...]):
        self.kind, self.name, self.known = kind, name, list(known)
        super().__init__(f"unknown {kind} {name!r}; known {kind}s: {', '.join(sorted(self.known))}")

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class DataError(SkyrouteError, OSError):
    """An input data file is missing, unreadable or malformed (the message names the file)."""


class InputError(SkyrouteError, ValueError):
    """A value given to a function or command is out of range or inconsistent."""


class CRSError(InputError):
    """A coordinate reference system cannot be resolved or does not fit the data."""


class CacheError(SkyrouteError):
    """The stage cache cannot be read or written."""


class PlanningError(SkyrouteError):
    """A planner could not produce a flyable plan; the message gives the reasons."""


class DegenerateCostError(InputError):
    """The cost weights select only terms that are the same per metre everywhere (e.g. risk with
    no land use): every path would score alike; the message names the data source to add."""

"""The bottom layer both ``skyroute.stages`` and ``skyroute.pipeline`` import: the exception
hierarchy and the frozen settings base.  Nothing here imports another ``skyroute`` module, so
``stages`` never imports ``pipeline`` (``skyroute.pipeline.errors`` and
``skyroute.pipeline.model`` re-export these names for API stability).

Exceptions (rioxarray style): every message says what is wrong and how to fix it.  The CLI turns
any :class:`SkyrouteError` into a one-line message and exit code 2; anything else is a bug and
keeps its traceback.
"""

from __future__ import annotations

import math
import types
import typing
from functools import lru_cache

from pydantic import BaseModel, ConfigDict, model_validator
from pydantic_core import PydanticCustomError


def _leaf_types(annotation) -> set:
    """The concrete types an annotation can hold (through Optional, unions, tuples, lists and
    Annotated), e.g. ``tuple[float, ...] | None`` -> {float, NoneType}."""
    out: set = set()
    stack = [annotation]
    while stack:
        a = stack.pop()
        origin = typing.get_origin(a)
        if origin is typing.Annotated:
            stack.append(typing.get_args(a)[0])
        elif origin in (typing.Union, types.UnionType, tuple, list, set, frozenset, typing.Literal):
            if origin is typing.Literal:
                out.update(type(v) for v in typing.get_args(a))
            else:
                stack.extend(x for x in typing.get_args(a) if x is not Ellipsis)
        elif origin is not None:
            out.add(origin)
        else:
            out.add(a)
    return out


@lru_cache(maxsize=4096)
def _number_field(model: type, name: str) -> tuple[bool, bool]:
    """(a number is meant and not true/false, a non-finite number is refused) for a field."""
    f = model.model_fields.get(name)
    if f is None:
        return False, False
    leaves = _leaf_types(f.annotation)
    numeric = bool(leaves & {int, float}) and not (leaves & {bool, str, typing.Any})
    default = f.default
    inf_ok = isinstance(default, float) and not math.isfinite(default)
    return numeric, numeric and float in leaves and not inf_ok


def _bad_number(v, finite: bool, depth: int = 0) -> str | None:
    """Why ``v`` (a value or a nested list of values for a number field) is refused, or None."""
    if isinstance(v, bool):
        return f"give a number, not {str(v).lower()} (true/false are not numbers)"
    if finite:
        x = None
        if isinstance(v, float):
            x = v
        elif isinstance(v, str) and v.strip().lower().lstrip("+-").lstrip(".") in ("inf", "infinity", "nan"):
            x = float("nan")
        if x is not None and not math.isfinite(x):
            return f"give a finite number, not {v!s} (.inf / .nan make no sense here)"
    if isinstance(v, list | tuple) and depth < 3:
        for item in v:
            why = _bad_number(item, finite, depth + 1)
            if why is not None:
                return why
    return None


class FrozenModel(BaseModel):
    """Base of all settings: immutable, strict about unknown keys.  A number field refuses
    ``true``/``false`` (YAML booleans would otherwise be read as 1/0) and, unless its default
    is itself infinite, ``.inf``/``.nan``."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)

    @model_validator(mode="before")
    @classmethod
    def _numbers_are_numbers(cls, data):
        if isinstance(data, dict):
            for key, v in data.items():
                if not isinstance(key, str):
                    continue
                numeric, finite = _number_field(cls, key)
                if numeric:
                    why = _bad_number(v, finite)
                    if why is not None:
                        raise PydanticCustomError("number_field", "{key}: {why}", {"key": key, "why": why})
        return data


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


class ClusterError(SkyrouteError):
    """The dask cluster a command runs on failed (every worker lost, the scheduler gone); the
    message says what was lost and how to go on (restart the workers, or run without
    ``--scheduler``)."""


class DegenerateCostError(InputError):
    """The cost weights select only terms that are the same per metre everywhere (e.g. risk with
    no land use): every path would score alike; the message names the data source to add."""


def read_limited(path, max_bytes: int, what: str = "input") -> bytes:
    """The bytes of a user's file, never more than ``max_bytes`` [bytes]: the limit holds for
    streams whose size the file system does not know (``/dev/zero``, ``/dev/urandom``, a FIFO,
    a file that grows while it is read), which are read in chunks and refused once they pass it.
    A FIFO, socket or device is refused before it is opened (opening a FIFO with no writer would
    wait forever).  Raises :class:`DataError` naming the file: not found, a folder, not a regular
    file, unreadable, or too large (with the limit)."""
    import os

    p = os.fspath(path)
    limit = int(max_bytes)
    note_input(p)
    why = file_problem(p, what)
    if why is not None:
        raise DataError(why if "regular file" not in why else f"{why} (at most {limit:,} bytes)")
    try:
        with open(p, "rb") as f:
            chunks: list[bytes] = []
            n = 0
            while True:
                b = f.read(min(1 << 20, limit + 1 - n))
                if not b:
                    break
                chunks.append(b)
                n += len(b)
                if n > limit:
                    raise DataError(f"{what} file {p}: more than {limit:,} bytes (a stream or device such as "
                                    f"/dev/zero never ends); give a regular {what} file of at most {limit:,} bytes")
            return b"".join(chunks)
    except PermissionError:
        raise DataError(f"{what} file {p} cannot be read (permission denied); check its permissions") from None
    except OSError as exc:
        if isinstance(exc, DataError):
            raise
        raise DataError(f"{what} file {p} cannot be read: {exc.strerror or exc}") from None

# ------------------------------------------------------------------ the files a command read
# Every file a user gives (scenario, data, events, fleet, vehicle...) is noted here as it is read,
# so that a command's output folder can refuse to replace any of them
# (:mod:`skyroute.pipeline.outfolder`).  Cleared at the start of each CLI command.
_INPUTS: dict[str, None] = {}


def note_input(path) -> None:
    """Record ``path`` as an input of the running command (resolved; ignored if it is not a
    path to an existing file)."""
    import os

    try:
        p = os.path.realpath(os.fspath(path))
    except (TypeError, ValueError, OSError):
        return
    _INPUTS.setdefault(p, None)


def inputs_read() -> list[str]:
    """The resolved paths :func:`note_input` recorded, in order."""
    return list(_INPUTS)


def forget_inputs() -> None:
    """Start a new command: no input recorded."""
    _INPUTS.clear()


def file_problem(path, what: str = "input") -> str | None:
    """Why ``path`` is not a regular file skyroute can read (the wording of :func:`read_limited`:
    not found, a folder, a FIFO, a socket, a device), or None.  Nothing is opened."""
    import os
    import stat

    p = os.fspath(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        return f"{what} file not found: {p}; check the path"
    except (OSError, ValueError) as exc:
        return f"{what} file {p} cannot be read: {getattr(exc, 'strerror', None) or exc}"
    if stat.S_ISDIR(mode):
        return f"{what} file {p} is a folder; give a file"
    if not stat.S_ISREG(mode):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
        return f"{what} file {p} is {kind}, not a regular file; give a regular {what} file"
    return None


#: The memory limit of the running command [bytes], for readers that size an allocation from a
#: file's header (a raster window): a function ``skyroute.pipeline.budget`` registers
#: (``--max-memory``, ``$SKYROUTE_MAX_MEMORY``, else 80 % of the machine); None: no limit.
memory_limit_hook = None


def memory_limit_bytes() -> float:
    """The running command's memory limit [bytes] (:data:`memory_limit_hook`), else inf."""
    return float(memory_limit_hook()) if memory_limit_hook is not None else math.inf

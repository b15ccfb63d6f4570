"""The one YAML reader of every file a user gives (scenario, vehicle, events, fleet, risk tags).

``yaml.safe_load`` alone accepts too much: bytes that are not UTF-8 raise ``UnicodeDecodeError``
(a traceback), a key given twice silently keeps the last value, and a 1 KB "billion laughs"
alias bomb expands to gigabytes.  :func:`read_yaml_file` / :func:`read_yaml_text` refuse each
with one :class:`~skyroute.stages.base.ScenarioError` problem naming the file, the place (line,
column) and the fix:

* a file larger than :data:`MAX_BYTES`, a file that is not UTF-8 (or holds NUL bytes);
* anything PyYAML cannot parse (tags such as ``!!python/object`` included: safe loading);
* a mapping key given twice (``<<`` merge keys may override, as YAML specifies);
* more than :data:`MAX_ALIASES` aliases (``*name``), or a document whose aliases expand it to
  more than :data:`MAX_NODES` nodes;
* nesting deeper than :data:`MAX_DEPTH`;
* a string holding a NUL character (``"\\0"``: no name or path may hold one).

It lives in ``stages`` (the bottom layer) so that :mod:`skyroute.stages.vehicle` uses it too.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from skyroute.stages.base import DataError, ScenarioError, read_limited

MAX_BYTES = 16 << 20       # a scenario is a few KB; a fleet file of 10 000 missions ~ 2 MB
MAX_ALIASES = 64           # the shipped files use none; a hand-written anchor or two is fine
MAX_NODES = 1_000_000      # nodes after alias expansion (an alias bomb has billions)
MAX_DEPTH = 64             # nesting of sequences / mappings

_MERGE_TAG = "tag:yaml.org,2002:merge"


class _Refused(yaml.YAMLError):
    """A well-formed YAML document this reader refuses (duplicate key, alias bomb...)."""

    def __init__(self, problem: str, mark=None):
        super().__init__(problem)
        self.problem = problem
        self.problem_mark = mark


class _Loader(yaml.SafeLoader):
    """SafeLoader that counts aliases and refuses duplicate keys."""

    def __init__(self, stream):
        super().__init__(stream)
        self._n_aliases = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self._n_aliases += 1
            if self._n_aliases > MAX_ALIASES:
                ev = self.peek_event()
                raise _Refused(f"more than {MAX_ALIASES} YAML aliases (*name): write the values out "
                               "instead of referring to anchors (an alias bomb is refused)", ev.start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, Any] = {}
            for key_node, _ in node.value:
                if key_node.tag == _MERGE_TAG:
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    hash(key)
                except TypeError:
                    raise _Refused(f"a mapping key must be a plain value, not {type(key).__name__}",
                                   key_node.start_mark) from None
                if key in seen:
                    first = seen[key]
                    raise _Refused(f"key {key!r} is given twice (first at line {first.line + 1}); "
                                   "keep one of them", key_node.start_mark)
                seen[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


def _expanded_size(root: yaml.Node) -> int:
    """Nodes of the document with every alias expanded (shared nodes counted per reference),
    computed without expanding it; raises _Refused beyond MAX_NODES or MAX_DEPTH."""
    memo: dict[int, int] = {}
    active: set[int] = set()
    # iterative post-order so deep nesting cannot overflow the Python stack
    stack: list[tuple[yaml.Node, int, bool]] = [(root, 0, False)]
    while stack:
        node, depth, done = stack.pop()
        if id(node) in memo:
            continue
        if depth > MAX_DEPTH:
            raise _Refused(f"nesting deeper than {MAX_DEPTH} levels", node.start_mark)
        if isinstance(node, yaml.SequenceNode):
            kids = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            kids = [n for kv in node.value for n in kv]
        else:
            memo[id(node)] = 1
            continue
        if done:
            total = 1 + sum(memo[id(k)] for k in kids)
            if total > MAX_NODES:
                raise _Refused(f"the document expands to more than {MAX_NODES:,} values through its "
                               "aliases (an alias bomb): write the values out", node.start_mark)
            memo[id(node)] = total
            active.discard(id(node))
        else:
            if any(id(k) in active for k in kids):
                raise _Refused("an alias refers to a value that contains it (a recursive structure)",
                               node.start_mark)
            active.add(id(node))
            stack.append((node, depth, True))
            stack.extend((k, depth + 1, False) for k in kids if id(k) not in memo)
    return memo[id(root)]


def _nul_string(doc: Any) -> str | None:
    """The YAML path of the first string (key or value) holding a NUL character, or None."""
    stack: list[tuple[Any, str]] = [(doc, "")]
    while stack:
        node, path = stack.pop()
        if isinstance(node, str):
            if "\x00" in node:
                return path
        elif isinstance(node, dict):
            for k, v in node.items():
                sub = f"{path}.{k}" if path else str(k)
                if isinstance(k, str) and "\x00" in k:
                    return sub
                stack.append((v, sub))
        elif isinstance(node, list):
            stack.extend((v, f"{path}[{i}]") for i, v in enumerate(node))
    return None


def _problem(exc: BaseException) -> str:
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    if isinstance(exc, _Refused):
        return f"<file>: refused{where}: {what}"
    return f"<file>: not valid YAML{where}: {what}"


def read_yaml_text(text: str | bytes, source: str, what: str = "YAML") -> Any:
    """Parse one YAML document (``text``: str or raw bytes, decoded as UTF-8) with the checks of
    this module; ``source`` names the file in the error, ``what`` the kind of file."""
    if isinstance(text, bytes | bytearray):
        if len(text) > MAX_BYTES:
            raise ScenarioError(source, [f"<file>: {len(text):,} bytes is too large for a {what} file "
                                         f"(at most {MAX_BYTES:,})"])
        try:
            text = bytes(text).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ScenarioError(source, [f"<file>: not a UTF-8 text file (byte 0x{text[exc.start]:02x} at "
                                         f"offset {exc.start}); give a {what} file saved as UTF-8"]) from None
    if "\x00" in text:
        raise ScenarioError(source, [f"<file>: holds NUL bytes, so it is not a text file; give a {what} file"])
    text = text.removeprefix("\ufeff")
    try:
        loader = _Loader(text)     # the reader refuses non-printable characters here already
    except yaml.YAMLError as exc:
        raise ScenarioError(source, [_problem(exc)]) from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node)
        doc = loader.construct_document(node)
        where = _nul_string(doc)
        if where is not None:
            raise ScenarioError(source, [f"{where or '<root>'}: a text holds a NUL character (\\0), which no name "
                                         "or path may hold; remove it"])
        return doc
    except yaml.YAMLError as exc:
        raise ScenarioError(source, [_problem(exc)]) from None
    except RecursionError:
        raise ScenarioError(source, [f"<file>: nesting too deep (more than {MAX_DEPTH} levels)"]) from None
    finally:
        loader.dispose()


def read_yaml_file(path: str | Path, what: str = "YAML") -> Any:
    """Read and parse a user's YAML file (see the module docstring for what is refused).
    Raises ScenarioError naming the file; a missing or unreadable file is one too, and so is a
    stream or device (``/dev/zero`` never ends: at most :data:`MAX_BYTES` are read, by
    :func:`~skyroute.stages.base.read_limited`)."""
    p = Path(path)
    try:
        data = read_limited(p, MAX_BYTES, what)
    except DataError as exc:
        raise ScenarioError(str(p), [f"<file>: {exc}"]) from None
    return read_yaml_text(data, str(p), what)

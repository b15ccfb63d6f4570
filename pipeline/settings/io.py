"""Reading scenarios and events: catalog names and paths, YAML, :class:`ScenarioError` with every problem,
:func:`load_scenario`, :func:`with_events`, :func:`scenario_at`."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter, ValidationError

from skyroute.pipeline.errors import ScenarioError, UnknownNameError
from skyroute.pipeline.settings.checks import (
    _clamp_default_max_altitude,
    _event_problems,
    _semantic_problems,
)
from skyroute.pipeline.settings.common import DEFAULT_SCENARIO, _is_file, _problems_from
from skyroute.pipeline.settings.events import Event, GnssEvent, ObstacleEvent, WindEvent
from skyroute.pipeline.settings.schema import Obstacle, Scenario
from skyroute.stages import yaml_io
from skyroute.stages.base import DataError, read_limited
from skyroute.stages.yaml_io import read_yaml_file


def catalog_dir() -> Path:
    """The folder of the installed scenario catalog."""
    return Path(str(resources.files("skyroute.catalogs")))

def scenario_paths() -> dict[str, Path]:
    """Known scenario names -> YAML files (built-in catalog plus ``$SKYROUTE_CATALOG`` folders)."""
    folders = [catalog_dir() / "scenarios"]
    extra = os.environ.get("SKYROUTE_CATALOG")
    if extra:
        folders += [Path(p) for p in extra.split(os.pathsep) if p]
    out: dict[str, Path] = {}
    for folder in folders:
        for f in sorted(folder.glob("*.yaml")):
            out.setdefault(f.stem, f)
    return out

#: the scenario keys whose string values are data file paths (``almanacs``: a list of them)
PATH_KEYS = frozenset({"path", "landuse", "landing_sites", "nofly_zones", "risk_tags", "almanacs"})


def _shipped_path(rel: Path) -> Path | None:
    """The file of the shipped catalog a relative data path names when it is read from the
    catalog's scenario folder (``../data/x``, the catalog scenarios' own spelling) or from its
    data folder (``x``), or None: only a file inside the catalog folder counts."""
    root = catalog_dir().resolve()
    for folder in (root / "scenarios", root / "data"):
        p = (folder / rel).resolve()
        if p.is_relative_to(root) and p.exists():
            return p
    return None


def _resolve_path(value: str, base: Path, where: str) -> str:
    """``value`` (a data path, ``$VARS`` expanded) made absolute w.r.t. ``base``.  A relative
    path not found there but found in the shipped catalog (:func:`_shipped_path`: a catalog
    scenario copied elsewhere) resolves to the shipped file, with a warning naming ``where``."""
    rel = Path(os.path.expandvars(value))
    here = (base / rel).resolve()
    if rel.is_absolute() or here.exists():
        return str(here)
    shipped = _shipped_path(rel)
    if shipped is None:
        return str(here)
    import warnings

    warnings.warn(f"{where}: {value} is not next to the scenario ({here}); using the file shipped with skyroute: "
                  f"{shipped} (`skyroute scenarios --copy NAME DIR` writes a catalog scenario with absolute data "
                  "paths)", UserWarning, stacklevel=2)
    return str(shipped)


def _resolve_paths(node: Any, base: Path, key: str = "", where: str = "") -> Any:
    """Make every relative path in a data path field (:data:`PATH_KEYS`) absolute w.r.t. ``base``
    (see :func:`_resolve_path`); ``where``: the YAML path of ``node``, for the warnings."""
    if isinstance(node, dict):
        return {k: _resolve_paths(v, base, k, f"{where}.{k}" if where else str(k)) for k, v in node.items()}
    if isinstance(node, list):
        if key == "almanacs":
            return [_resolve_path(v, base, f"{where}[{i}]") if isinstance(v, str) else v for i, v in enumerate(node)]
        return [_resolve_paths(v, base, key, f"{where}[{i}]") for i, v in enumerate(node)]
    if isinstance(node, str) and key in PATH_KEYS:
        return _resolve_path(node, base, where)
    return node

def _path_changes(raw: Any, absolute: Any, out: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """``(old, new)`` for every string of ``raw`` that :func:`_resolve_paths` changed."""
    if isinstance(raw, dict):
        for k, v in raw.items():
            _path_changes(v, absolute[k], out)
    elif isinstance(raw, list):
        for v, a in zip(raw, absolute, strict=True):
            _path_changes(v, a, out)
    elif isinstance(raw, str) and raw != absolute:
        out.append((raw, absolute))
    return out


def _yaml_scalar(text: str) -> str:
    """``text`` as a YAML scalar: plain when it holds only path characters, else double-quoted."""
    import json
    import re

    return text if re.fullmatch(r"[A-Za-z0-9_./+@~-]+", text) and text[0] not in "-~@" else json.dumps(text)


def copy_scenario(name: str, folder: str | Path) -> tuple[Path, int]:
    """Write catalog scenario ``name`` as ``folder/<name>.yaml`` with its data paths made
    absolute (so it runs from anywhere; comments and layout kept), ready to edit.  Returns the
    file written and the number of paths changed.  An existing file is never replaced
    (InputError); an unknown name is an UnknownNameError."""
    import re

    from skyroute.pipeline.errors import InputError
    from skyroute.stages.base import read_limited
    from skyroute.stages.yaml_io import MAX_BYTES, read_yaml_text

    known = scenario_paths()
    if name not in known:
        raise UnknownNameError("scenario", name, list(known))
    src = known[name]
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--copy {name} {folder}: {folder} is a file, not a folder; give a folder")
    dest = folder / f"{name}.yaml"
    if os.path.lexists(dest):
        raise InputError(f"--copy {name} {folder}: {dest} exists and is not replaced; remove or rename it, or "
                         "give another folder")
    text = read_limited(src, MAX_BYTES, "scenario").decode("utf-8")
    raw = read_yaml_text(text, str(src), "scenario")
    absolute = _resolve_paths(raw, src.parent)
    pairs = _path_changes(raw, absolute, [])
    changes = dict(pairs)
    out = text
    for old in sorted(changes, key=len, reverse=True):   # the longest first: no value inside another
        pat = re.compile(r"""(?P<q>["']?)(?<![\w./~$-])""" + re.escape(old) + r"""(?![\w./-])(?P=q)""")
        out = pat.sub(lambda m, new=changes[old]: _yaml_scalar(new), out)
    header = (f"# copied from the skyroute catalog scenario {name} ({src}) by `skyroute scenarios --copy`:\n"
              "# its data paths are made absolute; edit freely\n")
    out = header + out
    if read_yaml_text(out, str(dest), "scenario") != absolute:   # an unusual layout: write the data plainly
        import yaml

        out = header + yaml.safe_dump(absolute, sort_keys=False, allow_unicode=True, width=100)
    tmp = folder / f".{name}.yaml.skyroute-{os.getpid()}.tmp"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp.write_text(out, encoding="utf-8")
        try:
            os.link(tmp, dest)              # atomic, and fails when the file appeared meanwhile
        except FileExistsError:
            raise
        except OSError:                     # no hard links here (some file systems): exclusive create
            with open(dest, "x", encoding="utf-8") as f:
                f.write(out)
    except FileExistsError:
        raise InputError(f"--copy {name} {folder}: {dest} exists and is not replaced; remove or rename it, or "
                         "give another folder") from None
    except OSError as exc:
        raise InputError(f"--copy {name} {folder}: cannot write {dest} ({exc.strerror or exc}); give a folder you "
                         "may write to") from None
    finally:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
    return dest, len(pairs)


def _sorted_labels(raw_events: Any, fmt: str = "events[{}]") -> list[str]:
    """YAML paths of the events in the order the scenario keeps them (by time, stable)."""
    if not isinstance(raw_events, list):
        return []
    order = sorted(range(len(raw_events)), key=lambda i: float(raw_events[i]["t_s"]))
    return [fmt.format(i) for i in order]

def parse_scenario(raw: Any, source: str = "<scenario>", base: Path | None = None) -> Scenario:
    """Validate a scenario mapping (already parsed YAML).  Raises ScenarioError with every problem."""
    if not isinstance(raw, dict):
        raise ScenarioError(source, ["<root>: a scenario must be a YAML mapping (key: value)"])
    if base is not None:
        raw = _resolve_paths(raw, base)
    try:
        sc = Scenario.model_validate(raw)
    except ValidationError as exc:
        raise ScenarioError(source, _problems_from(exc)) from None
    sc = _clamp_default_max_altitude(sc)
    problems = _semantic_problems(sc)
    if sc.events:
        problems += _event_problems(sc, _sorted_labels(raw.get("events")))
    if problems:
        raise ScenarioError(source, problems)
    if base is not None:
        sc = sc.model_copy(update={"source_path": Path(source)})
    return sc

def load_scenario(name_or_path: str | Path = DEFAULT_SCENARIO) -> Scenario:
    """Load and validate a scenario by catalog name (``helsinki-medical``) or YAML path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or _is_file(p):
        if not _is_file(p):
            raise ScenarioError(str(p), [f"<file>: scenario file not found: {p}"])
    else:
        known = scenario_paths()
        if str(name_or_path) not in known:
            raise UnknownNameError("scenario", str(name_or_path), list(known))
        p = known[str(name_or_path)]
    raw = read_yaml_file(p, "scenario")
    sc = parse_scenario(raw, source=str(p), base=p.parent)
    from skyroute.pipeline.outfolder import note_scenario_inputs

    note_scenario_inputs(sc)   # an output folder may never replace a file the command reads
    return sc

_EVENTS = TypeAdapter(tuple[Event, ...])

#: a JSON number PyYAML (YAML 1.1) reads as a float: a dot, and a signed exponent if any
#: (``1e5`` and ``1.5e3`` are strings to it)
_YAML_FLOAT = re.compile(r"-?[0-9]+\.[0-9]*(?:[eE][-+][0-9]+)?")


class _NotPlainJSON(ValueError):
    """The text is not JSON that reads exactly as YAML would: let the YAML reader decide."""


def _json_pairs(pairs: list[tuple[str, Any]]) -> dict:
    out = dict(pairs)
    if len(out) != len(pairs):
        raise _NotPlainJSON("a key given twice")     # the YAML reader names it, with its line
    return out


def _json_constant(name: str) -> Any:
    raise _NotPlainJSON(name)       # NaN, Infinity: not JSON; YAML reads them as strings


def _json_float(text: str) -> float | str:
    return float(text) if _YAML_FLOAT.fullmatch(text) else text


def _json_size(doc: Any) -> tuple[int, int]:
    """(values, deepest nesting) of a parsed document, counted as the YAML reader counts them
    (:func:`skyroute.stages.yaml_io._expanded_size`: a mapping key is a value too)."""
    n, deepest = 0, 0
    stack: list[tuple[Any, int]] = [(doc, 0)]
    while stack:
        node, depth = stack.pop()
        n += 1
        deepest = max(deepest, depth)
        if isinstance(node, dict):
            n += len(node)      # the keys
            stack.extend((v, depth + 1) for v in node.values())
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node)
    return n, deepest


def _read_yaml(p: Path) -> Any:
    """An events file parsed once.  A JSON file (JSON is YAML, and what a program writes: a
    generated file of 100 000 events or a 200 000-vertex polygon is ~10 MB, 40-60 s for PyYAML's
    pure-Python parser) is read by :func:`json.loads` in well under a second, giving the values
    YAML gives (numbers without a dot stay strings as in YAML 1.1) and refusing what
    :func:`~skyroute.stages.yaml_io.read_yaml_file` refuses (more than ``MAX_NODES`` values or
    ``MAX_DEPTH`` levels); anything else (YAML proper, a duplicate key, ``NaN``, a NUL, bytes that
    are not UTF-8) goes to that reader, which names the problem and its line."""
    try:
        data = read_limited(p, yaml_io.MAX_BYTES, "events")
    except DataError as exc:
        raise ScenarioError(str(p), [f"<file>: {exc}"]) from None
    head = data[:64].lstrip(b"\xef\xbb\xbf \t\r\n")
    if head[:1] in (b"[", b"{"):
        try:
            text = data.decode("utf-8").removeprefix("\ufeff")
            if "\x00" in text:
                raise _NotPlainJSON("NUL")
            doc = json.loads(text, object_pairs_hook=_json_pairs, parse_constant=_json_constant,
                             parse_float=_json_float)
            if yaml_io._nul_string(doc) is not None:
                raise _NotPlainJSON("NUL")
        except (ValueError, RecursionError):    # JSONDecodeError, UnicodeDecodeError, _NotPlainJSON
            pass
        else:
            n, deepest = _json_size(doc)
            if deepest > yaml_io.MAX_DEPTH:
                raise ScenarioError(str(p), [f"<file>: refused: nesting deeper than {yaml_io.MAX_DEPTH} levels"])
            if n > yaml_io.MAX_NODES:
                raise ScenarioError(str(p), [f"<file>: refused: {n:,} values, more than the {yaml_io.MAX_NODES:,} "
                                             "an events file may hold; split it or simplify its polygons"])
            return doc
    return yaml_io.read_yaml_text(data, str(p), "events")

def _raw_events_of(path: str | Path) -> list:
    p = Path(path)
    if not _is_file(p):
        raise ScenarioError(str(p), [f"<file>: events file not found: {p}"])
    raw = _read_yaml(p)
    if isinstance(raw, dict) and set(raw) == {"events"}:
        raw = raw["events"]
    if not isinstance(raw, list):
        raise ScenarioError(str(p), ["<root>: an events file holds a list of events, or a mapping with one key "
                                     "`events:` holding that list (each event: t_s, kind, ...)"])
    return _resolve_paths({"events": raw}, p.parent)["events"]

def load_events_file(path: str | Path) -> tuple[Event, ...]:
    """Read and validate an events file: a YAML list of events, or a mapping whose only key
    ``events`` holds that list (the ``events:`` section of a scenario).  Relative paths
    (almanacs, gridded wind) are resolved against the file's folder.  Events stay in file order
    (:func:`with_events` sorts them by time).  Raises ScenarioError naming the file and each
    problem's YAML path (``events[2]: unknown kind 'fog'; ...``)."""
    raw = _raw_events_of(path)
    try:
        return _EVENTS.validate_python(raw)
    except ValidationError as exc:
        raise ScenarioError(str(path), _problems_from(exc, prefix=("events",))) from None

def with_events(sc: Scenario, events: Sequence[Event] | str | Path, source: str | None = None) -> Scenario:
    """``sc`` with ``events`` (a sequence of events, or an events file read with
    :func:`load_events_file`) appended and the whole list re-validated against the scenario
    (intruder ids, polygons in the AOI, data files) and sorted by time (stable).  Backs
    ``skyroute fly --events FILE``; errors name the file (or ``source``) and the event's place in it."""
    if isinstance(events, str | Path):
        source = source or str(events)
        events = load_events_file(events)
    source = source or "added events"
    new = list(events)
    try:
        new = list(_EVENTS.validate_python(new))  # events built by hand are checked too
    except ValidationError as exc:
        raise ScenarioError(source, _problems_from(exc, prefix=("events",))) from None
    tagged = [(f"scenario events[{i}]", False, e) for i, e in enumerate(sc.events)]
    tagged += [(f"events[{i}]", True, e) for i, e in enumerate(new)]
    tagged.sort(key=lambda t: t[2].t_s)
    out = sc.model_copy(update={"events": tuple(t[2] for t in tagged)})
    problems = _event_problems(out, [t[0] for t in tagged], [t[1] for t in tagged])
    if problems:
        raise ScenarioError(f"{source} (events added to scenario {sc.name!r})", problems)
    return out

def check_event_times(sc: Scenario, mission_end_s: float) -> list[str]:
    """Problems of events that come after the end of the mission (``mission_end_s`` [s after the
    start], known only once the plan is made): one line each, for the engine to raise."""
    out = []
    for k, e in enumerate(sc.events):
        if e.t_s > mission_end_s:
            name = f" {e.id!r}" if e.id else ""
            out.append(f"events[{k}]: {e.kind} event{name} at {e.t_s:g} s comes after the end of the mission at "
                       f"{mission_end_s:.1f} s (events are times after the mission start); move it earlier or drop it")
    return out

def scenario_at(sc: Scenario, t_s: float) -> Scenario:
    """The scenario with every map-changing event up to ``t_s`` [s after the start] applied, so
    the affected maps are recomputed through the same (cached) stages:

    * ``wind``: replaces ``data.uniform_wind`` / ``data.wind`` (wind stage);
    * ``gnss``: ``out_of_service`` adds to ``gnss.exclude_satellites``, ``almanacs`` replaces
      ``data.almanacs`` (satellites stage, then coverage);
    * ``obstacle``: adds to ``data.obstacles`` (surface stage, then everything built on it).

    ``intruder``, ``intruder_update`` and ``nofly`` events change no map.  Stages whose settings
    these do not touch keep their cache keys."""
    data, gnss = sc.data, sc.gnss
    d_upd: dict[str, Any] = {}
    excluded = list(gnss.exclude_satellites)
    obstacles = list(data.obstacles)
    for e in sc.events:
        if e.t_s > t_s:
            break  # sorted by time
        if isinstance(e, WindEvent):
            d_upd.update(uniform_wind=e.uniform_wind, wind=e.wind)
        elif isinstance(e, GnssEvent):
            excluded += [s for s in e.out_of_service if s not in excluded]
            if e.almanacs:
                d_upd["almanacs"] = e.almanacs
        elif isinstance(e, ObstacleEvent):
            xy = e.polygon_xy(sc)
            obstacles.append(Obstacle(polygon=tuple((float(x), float(y)) for x, y in xy), height_agl_m=e.height_agl_m))
    if len(obstacles) != len(data.obstacles):
        d_upd["obstacles"] = tuple(obstacles)
    upd: dict[str, Any] = {}
    if d_upd:
        upd["data"] = data.model_copy(update=d_upd)
    if tuple(excluded) != gnss.exclude_satellites:
        upd["gnss"] = gnss.model_copy(update={"exclude_satellites": tuple(excluded)})
    return sc.model_copy(update=upd) if upd else sc

"""Small shared pieces of the scenario settings: field types, name and id checks, the wind sources, and the
YAML paths of validation problems."""

from __future__ import annotations

import datetime as dt
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationError, model_validator

from skyroute.pipeline.model import FrozenModel

PositiveFloat = Annotated[float, Field(gt=0)]

NonNegFloat = Annotated[float, Field(ge=0)]

Bounds = tuple[float, float, float, float]

DEFAULT_SCENARIO = "helsinki-medical"
EVENT_KINDS = ("intruder", "intruder_update", "wind", "gnss", "nofly", "obstacle")

_NAME_OK = re.compile(r"^[^\x00-\x1f\x7f/\\:*?\"<>|]+$")

def _is_file(p: str | Path) -> bool:
    """``Path(p).is_file()`` that is False, not an exception, for a name too long or with a NUL."""
    try:
        return Path(p).is_file()
    except (OSError, ValueError):
        return False

def unsafe_name(v: str) -> str | None:
    """Why ``v`` is not a safe single path component (a folder name under skyroute-out/), or None."""
    if not v or not v.strip():
        return "is empty"
    if v != v.strip():
        return "has leading or trailing spaces"
    if not _NAME_OK.match(v):
        return "is not a single folder name: it holds a path separator or a character not allowed in file names (/ \\ : * ? \" < > | or a control character)"
    if v in (".", "..") or v.startswith((".", "-")):
        return "starts with '.' or '-'"
    if len(v) > 100:
        return f"is {len(v)} characters long (at most 100)"
    return None

MAX_INTRUDER_SPEED_MPS = 150.0
"""The fastest intruder a scenario or an event may declare [m/s] (540 km/h: faster than any
aircraft sharing the very-low-level airspace of a drone)."""
MAX_WIND_SPEED_MPS = 100.0
"""The strongest wind a scenario or an event may declare [m/s] (close to the strongest gust
ever measured at the surface, 113 m/s)."""


class UniformWind(FrozenModel):
    """Vertically constant wind: ``speed_mps`` [m/s] (at most :data:`MAX_WIND_SPEED_MPS`),
    ``direction_deg`` [deg, meteorological: where it blows FROM, clockwise from north],
    ``elevation_deg`` [deg, -90 .. 90]."""

    speed_mps: NonNegFloat
    direction_deg: float
    elevation_deg: float = 0.0

    @model_validator(mode="after")
    def _bounded(self) -> UniformWind:
        """The message names the field and its bound (as the events' checks do)."""
        if not self.speed_mps <= MAX_WIND_SPEED_MPS:
            raise ValueError(f"speed_mps {self.speed_mps:g} m/s is out of range: it must be at most "
                             f"{MAX_WIND_SPEED_MPS:g} m/s (see the bounds in pipeline/settings/common.py)")
        if not math.isfinite(self.direction_deg):
            raise ValueError(f"direction_deg {self.direction_deg} is not a finite angle [deg]")
        if not -90.0 <= self.elevation_deg <= 90.0:
            raise ValueError(f"elevation_deg {self.elevation_deg:g} deg is out of range: it must be in [-90, 90] deg")
        return self

class GriddedWind(FrozenModel):
    """Gridded wind from CF NetCDF/zarr (u, v [, w] on pressure or height levels)."""

    path: Path
    time_utc: dt.datetime | None = None
    profile: Literal["levels", "power", "constant"] = "levels"

SAT_ID = re.compile(r"^[GERCJ]\d{2}$")

def _check_sat_ids(ids: Sequence[str]) -> tuple[str, ...]:
    bad = [s for s in ids if not SAT_ID.match(str(s))]
    if bad:
        raise ValueError(f"satellite id(s) {', '.join(repr(b) for b in bad)} not understood; give them as "
                         "`skyroute sky` prints them: a system letter G, E, R, C or J and two digits (G05, E11)")
    return tuple(dict.fromkeys(ids))

Vertex = tuple[float, float]

def _check_polygon(v: tuple[Vertex, ...], units: str) -> tuple[Vertex, ...]:
    """A simple polygon: >= 3 distinct vertices, not self-intersecting (shapely's validity)."""
    import shapely
    from shapely.validation import explain_validity

    pts = list(v)
    if len(pts) > 1 and pts[0] == pts[-1]:
        pts = pts[:-1]  # a closed ring given with its first vertex repeated
    if len(pts) < 3:
        raise ValueError(f"a polygon needs at least 3 vertices [{units}], got {len(pts)}")
    if not all(math.isfinite(c) for p in pts for c in p):
        raise ValueError("polygon vertices must be finite numbers")
    poly = shapely.Polygon(pts)
    if not poly.is_valid:
        raise ValueError(f"the polygon is not valid ({explain_validity(poly)}): it must not cross itself "
                         "and its vertices must go around it in order")
    if poly.area <= 0:
        raise ValueError("the polygon has no area (its vertices are on one line)")
    return tuple(pts)

Waypoint = tuple[float, float, float, float]

def _yaml_path(loc: Sequence[Any]) -> str:
    """``('events', 2, 'intruder', 'waypoints')`` -> ``events[2].waypoints`` (list indices in
    brackets; the tag pydantic adds for a tagged union member is not part of the YAML path)."""
    out = ""
    for k, p in enumerate(loc):
        s = str(p)
        if s.startswith("function-"):
            continue
        if isinstance(p, int):
            out += f"[{p}]"
        elif k > 0 and isinstance(loc[k - 1], int) and s in EVENT_KINDS:
            continue
        else:
            out += f".{s}" if out else s
    return out

def _problems_from(exc: ValidationError, prefix: Sequence[Any] = ()) -> list[str]:
    out = []
    kinds = ", ".join(EVENT_KINDS)
    for err in exc.errors():
        loc = _yaml_path([*prefix, *err["loc"]])
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "number_field":      # FrozenModel: true/false or .inf/.nan given for a number
            loc = _yaml_path([*prefix, *err["loc"], err["ctx"]["key"]])
            msg = err["ctx"]["why"]
        elif err["type"] == "extra_forbidden":
            msg = ("unknown key (check the spelling; valid keys: catalogs/README.md or "
                   "`python -m skyroute.pipeline.settings_reference`)")
        elif err["type"] == "missing":
            msg = "required key is missing"
        elif err["type"] == "union_tag_invalid":
            msg = f"unknown kind {err.get('ctx', {}).get('tag')!r}; kinds: {kinds}"
        elif err["type"] == "union_tag_not_found":
            msg = f"give the event's kind: {kinds}"
        out.append(f"{loc or '<root>'}: {msg}")
    return out

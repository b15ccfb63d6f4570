"""Scenario events (``events:`` of a scenario or an events file): intruders, wind, GNSS, no-fly zones,
obstacles.

Every number of an event is finite and physically bounded, so that a typing slip (``1e6`` for
``1e1``) is refused here, with its YAML path and the limit, rather than flown (an intruder at
10^6 m/s makes the replay's distances infinite):

* intruder speed (``velocity_mps`` norm, or the speed between two ``waypoints``) at most
  :data:`MAX_INTRUDER_SPEED_MPS` = 150 m/s (540 km/h: faster than any aircraft sharing the
  very-low-level airspace of a drone);
* wind speed (``uniform_wind.speed_mps``) at most :data:`MAX_WIND_SPEED_MPS` = 100 m/s (close to
  the strongest gust ever measured at the surface, 113 m/s, and far above any wind a drone meets);
  ``direction_deg`` finite, ``elevation_deg`` in [-90, 90] deg;
* map coordinates ``x``, ``y`` at most :data:`MAX_COORDINATE_M` = 10^8 m in absolute value (any
  projected CRS stays within 4 10^7 m), heights above ground at most :data:`MAX_AGL_M` = 10^5 m;
* ``duration_s`` at most :data:`MAX_DURATION_S` = 86400 s (a day), ``radius_m`` at most
  :data:`MAX_RADIUS_M` = 1000 m, an obstacle's ``height_agl_m`` at most :data:`MAX_AGL_M`;
* times ``t_s``, ``start_s`` finite (``end_s`` and a zone's ``max_agl_m`` may be ``.inf``: open).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.settings.common import (
    MAX_INTRUDER_SPEED_MPS,
    MAX_WIND_SPEED_MPS,  # noqa: F401  (documented here; checked by UniformWind)
    GriddedWind,
    NonNegFloat,
    PositiveFloat,
    UniformWind,
    Vertex,
    Waypoint,
    _check_polygon,
    _check_sat_ids,
)

if TYPE_CHECKING:      # annotations only
    from skyroute.pipeline.settings.schema import Scenario

MAX_COORDINATE_M = 1.0e8
"""The largest map coordinate (absolute value) of a track [m]."""
MAX_AGL_M = 1.0e5
"""The highest height above ground of a track or an obstacle [m]."""
MAX_DURATION_S = 86400.0
"""The longest ``duration_s`` of a position + velocity track [s]."""
MAX_RADIUS_M = 1000.0
"""The largest intruder ``radius_m`` [m]."""


def _bounded(x: float, what: str, limit: float, unit: str, low: float | None = None) -> float:
    """``x`` when finite and at most ``limit`` (and at least ``low``), else ValueError naming
    ``what`` and the limit."""
    if not math.isfinite(x):
        raise ValueError(f"{what} {x} is not a finite number")
    if x > limit or (low is not None and x < low):
        rng = f"at most {limit:g} {unit}" if low is None else f"in [{low:g}, {limit:g}] {unit}"
        raise ValueError(f"{what} {x:g} {unit} is out of range: it must be {rng} "
                         "(see the bounds in pipeline/settings/events.py)")
    return x


def _check_point(x: float, y: float, alt: float, what: str) -> None:
    """A track point: map x, y [m] and height above ground [m], finite and bounded."""
    _bounded(x, f"{what} x", MAX_COORDINATE_M, "m", -MAX_COORDINATE_M)
    _bounded(y, f"{what} y", MAX_COORDINATE_M, "m", -MAX_COORDINATE_M)
    _bounded(alt, f"{what} altitude", MAX_AGL_M, "m AGL")


class _EventBase(FrozenModel):
    t_s: NonNegFloat  # time of the event [s after the mission start]
    id: str | None = None

    @field_validator("t_s")
    @classmethod
    def _t_finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError(f"event time {v} s is not a finite number of seconds after the mission start")
        return v

    @property
    def label(self) -> str:
        """A short name for tables and logs: ``intruder hawk at 10 s``, ``wind at 30 s``."""
        who = f" {self.id}" if self.id else ""
        return f"{getattr(self, 'kind', 'event')}{who} at {self.t_s:g} s"

class _TrackForms(_EventBase):
    """An intruder track: ``waypoints`` [[t_s, x_m, y_m, alt_agl_m], ...] (map x/y [m], AGL [m],
    times strictly increasing) or ``position`` [x_m, y_m, alt_agl_m] + ``velocity_mps`` [vx, vy, vz]
    [m/s] flown for ``duration_s`` [s] from the event time."""

    via: Literal["uspace", "v2v"] = "uspace"
    waypoints: tuple[Waypoint, ...] | None = None
    position: tuple[float, float, float] | None = None
    velocity_mps: tuple[float, float, float] | None = None
    duration_s: PositiveFloat = 300.0

    @field_validator("waypoints")
    @classmethod
    def _waypoints(cls, v: tuple[Waypoint, ...] | None) -> tuple[Waypoint, ...] | None:
        if v is None:
            return v
        if len(v) < 2:
            raise ValueError(f"a track needs at least 2 waypoints [[t_s, x_m, y_m, alt_agl_m], ...], got {len(v)}")
        for k in range(1, len(v)):
            if not v[k][0] > v[k - 1][0]:
                raise ValueError(f"times must increase strictly (waypoint {k} at {v[k][0]:g} s is not after "
                                 f"waypoint {k - 1} at {v[k - 1][0]:g} s)")
        for k, w in enumerate(v):
            if not math.isfinite(w[0]):
                raise ValueError(f"waypoint {k}: time {w[0]} s is not a finite number")
            if w[3] < 0:
                raise ValueError(f"waypoint {k} at {w[0]:g} s: altitude {w[3]:g} m AGL is below the ground")
            _check_point(w[1], w[2], w[3], f"waypoint {k} at {w[0]:g} s:")
        for k in range(1, len(v)):
            (t0, *p0), (t1, *p1) = v[k - 1], v[k]
            speed = math.dist(p0, p1) / (t1 - t0)
            if not speed <= MAX_INTRUDER_SPEED_MPS:
                raise ValueError(f"waypoints {k - 1} -> {k} ({t0:g} s -> {t1:g} s) are flown at {speed:.4g} m/s, "
                                 f"faster than the {MAX_INTRUDER_SPEED_MPS:g} m/s an intruder may fly; check the "
                                 "times [s] and coordinates [m]")
        return v

    @field_validator("position")
    @classmethod
    def _position(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is not None:
            _check_point(v[0], v[1], max(v[2], 0.0), "position")
        return v

    @field_validator("velocity_mps")
    @classmethod
    def _velocity(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is None:
            return v
        if not all(math.isfinite(c) for c in v):
            raise ValueError(f"velocity {list(v)} m/s has a non-finite component")
        speed = math.hypot(*v)
        if speed > MAX_INTRUDER_SPEED_MPS:
            raise ValueError(f"speed |velocity_mps| = {speed:.4g} m/s is faster than the {MAX_INTRUDER_SPEED_MPS:g} "
                             "m/s an intruder may fly; give [vx, vy, vz] in m/s")
        return v

    @field_validator("duration_s")
    @classmethod
    def _duration(cls, v: float) -> float:
        return _bounded(v, "duration_s", MAX_DURATION_S, "s")

    @model_validator(mode="after")
    def _one_form(self):
        has_wp, has_pos = self.waypoints is not None, self.position is not None
        if has_wp == has_pos:
            raise ValueError("give exactly one track form: waypoints [[t_s, x_m, y_m, alt_agl_m], ...] or "
                             "position [x_m, y_m, alt_agl_m] with velocity_mps [vx, vy, vz]")
        if has_pos and self.velocity_mps is None:
            raise ValueError("position [x_m, y_m, alt_agl_m] needs velocity_mps [vx, vy, vz] [m/s]")
        if has_wp and ({"velocity_mps", "duration_s"} & self.model_fields_set):
            raise ValueError("velocity_mps and duration_s go with position, not with waypoints")
        if has_pos:
            assert self.position is not None
            if self.position[2] < 0:
                raise ValueError(f"position altitude {self.position[2]:g} m AGL is below the ground")
            end = self.track()[-1]
            if end[3] < 0:
                raise ValueError(f"the track goes below the ground (altitude {end[3]:g} m AGL at {end[0]:g} s); "
                                 "shorten duration_s or change velocity_mps")
        return self

    def track(self) -> np.ndarray:
        """The track as ``(k, 4)`` rows [t_s, x_m, y_m, alt_agl_m] (position + velocity: two
        waypoints, at the event time and ``duration_s`` later)."""
        if self.waypoints is not None:
            return np.asarray(self.waypoints, dtype=np.float64)
        assert self.position is not None and self.velocity_mps is not None
        p, v = np.asarray(self.position, np.float64), np.asarray(self.velocity_mps, np.float64)
        return np.array([[self.t_s, *p], [self.t_s + self.duration_s, *(p + v * self.duration_s)]])

class IntruderEvent(_TrackForms):
    """A tactical intruder not known at planning time, known from ``t_s`` [s] on (via the
    U-space service or V2V): ``id``, ``radius_m`` [m] and its track (waypoints or position +
    velocity)."""

    kind: Literal["intruder"]
    id: str
    radius_m: PositiveFloat = 2.0

    @field_validator("radius_m")
    @classmethod
    def _radius(cls, v: float) -> float:
        return _bounded(v, "radius_m", MAX_RADIUS_M, "m")

class IntruderUpdateEvent(_TrackForms):
    """A new track for an intruder known earlier (``traffic.intruders`` or an earlier
    ``intruder`` event), from ``t_s`` [s] on; ``radius_m`` [m] unchanged when not given."""

    kind: Literal["intruder_update"]
    id: str
    radius_m: PositiveFloat | None = None

    @field_validator("radius_m")
    @classmethod
    def _radius(cls, v: float | None) -> float | None:
        return v if v is None else _bounded(v, "radius_m", MAX_RADIUS_M, "m")

class WindEvent(_EventBase):
    """A new wind from ``t_s`` [s] on: exactly one of ``uniform_wind`` or ``wind`` (gridded)."""

    kind: Literal["wind"]
    uniform_wind: UniformWind | None = None
    wind: GriddedWind | None = None

    @model_validator(mode="after")
    def _one(self) -> WindEvent:
        if (self.uniform_wind is None) == (self.wind is None):
            raise ValueError("give exactly one of uniform_wind {speed_mps, direction_deg} or wind {path, ...}")
        return self

class GnssEvent(_EventBase):
    """GNSS change from ``t_s`` [s] on: satellites ``out_of_service`` (ids as ``skyroute sky``
    prints them: G05, E11) and/or a new almanac set ``almanacs`` (paths relative to the YAML)."""

    kind: Literal["gnss"]
    out_of_service: tuple[str, ...] = ()
    almanacs: tuple[Path, ...] = ()

    @field_validator("out_of_service")
    @classmethod
    def _ids(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return _check_sat_ids(v)

    @model_validator(mode="after")
    def _some(self) -> GnssEvent:
        if not self.out_of_service and not self.almanacs:
            raise ValueError("give out_of_service [G05, ...] and/or almanacs [file, ...]")
        return self

class _PolygonEvent(_EventBase):
    """A polygon as ``polygon_lonlat`` [[lon, lat], ...] [deg] or ``polygon`` [[x_m, y_m], ...]
    in the map CRS [m] (>= 3 vertices, not self-intersecting)."""

    polygon_lonlat: tuple[Vertex, ...] | None = None
    polygon: tuple[Vertex, ...] | None = None

    @field_validator("polygon_lonlat")
    @classmethod
    def _ll(cls, v: tuple[Vertex, ...] | None) -> tuple[Vertex, ...] | None:
        if v is None:
            return v
        for lon, lat in v:
            if not (-180 <= lon <= 180 and -90 <= lat <= 90):
                raise ValueError(f"vertex ({lon:g}, {lat:g}) is not [lon, lat] in [-180, 180] x [-90, 90] deg")
        return _check_polygon(v, "lon, lat")

    @field_validator("polygon")
    @classmethod
    def _xy(cls, v: tuple[Vertex, ...] | None) -> tuple[Vertex, ...] | None:
        return v if v is None else _check_polygon(v, "x_m, y_m")

    @model_validator(mode="after")
    def _one_polygon(self):
        if (self.polygon_lonlat is None) == (self.polygon is None):
            raise ValueError("give exactly one of polygon_lonlat [[lon, lat], ...] [deg] or polygon [[x_m, y_m], ...] [m]")
        return self

    def polygon_xy(self, sc: Scenario) -> np.ndarray:
        """The polygon's vertices ``(k, 2)`` in the map CRS of ``sc`` [m]."""
        if self.polygon is not None:
            return np.asarray(self.polygon, dtype=np.float64)
        ll = np.asarray(self.polygon_lonlat, dtype=np.float64)
        x, y = sc.grid.from_lonlat(ll[:, 0], ll[:, 1])
        return np.column_stack([x, y]).astype(np.float64)

class NoFlyEvent(_PolygonEvent):
    """A new no-fly zone (e.g. a police operation): polygon, altitude band ``min_agl_m`` ..
    ``max_agl_m`` [m AGL] and time window ``start_s`` (default: the event time) .. ``end_s``
    (default: open) [s after the mission start]."""

    kind: Literal["nofly"]
    min_agl_m: NonNegFloat = 0.0
    max_agl_m: float = math.inf
    start_s: NonNegFloat | None = None
    end_s: float = math.inf

    @model_validator(mode="before")
    @classmethod
    def _default_start(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("start_s") is None and "t_s" in data:
            data = {**data, "start_s": data["t_s"]}
        return data

    @model_validator(mode="after")
    def _bands(self) -> NoFlyEvent:
        _bounded(self.min_agl_m, "min_agl_m", MAX_AGL_M, "m AGL")
        if math.isnan(self.max_agl_m) or math.isnan(self.end_s):
            raise ValueError("max_agl_m and end_s must be numbers (.inf: open)")
        if self.start_s is not None and not math.isfinite(self.start_s):
            raise ValueError(f"start_s {self.start_s} is not a finite time [s after the mission start]")
        if not self.max_agl_m > self.min_agl_m:
            raise ValueError(f"max_agl_m {self.max_agl_m:g} must be above min_agl_m {self.min_agl_m:g}")
        assert self.start_s is not None
        if self.start_s < self.t_s:
            raise ValueError(f"start_s {self.start_s:g} s is before the event time t_s {self.t_s:g} s "
                             "(a zone cannot be active before it is announced)")
        if not self.end_s > self.start_s:
            raise ValueError(f"end_s {self.end_s:g} s must be after start_s {self.start_s:g} s")
        return self

class ObstacleEvent(_PolygonEvent):
    """A new static obstacle (e.g. a crane): polygon and ``height_agl_m`` [m] above the
    highest ground under it, burnt into the surface model from ``t_s`` [s] on."""

    kind: Literal["obstacle"]
    height_agl_m: PositiveFloat

    @field_validator("height_agl_m")
    @classmethod
    def _height(cls, v: float) -> float:
        return _bounded(v, "height_agl_m", MAX_AGL_M, "m")

#: One scenario event, told apart by its ``kind``.
Event = Annotated[IntruderEvent | IntruderUpdateEvent | WindEvent | GnssEvent | NoFlyEvent | ObstacleEvent,
                  Field(discriminator="kind")]

MAP_EVENT_KINDS = ("wind", "gnss", "obstacle")

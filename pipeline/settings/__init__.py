"""Scenario catalogs: YAML files validated into frozen, typed settings.

A scenario names an area of interest, its data sources, a mission, a vehicle profile,
constraints and planner settings.  :func:`load_scenario` reads a catalog entry (by name or
path), resolves data paths relative to the YAML file and validates everything at once:
a :class:`~skyroute.pipeline.errors.ScenarioError` lists *every* problem, each prefixed by
its YAML path (``mission.start: altitude 900 m is above constraints.max_altitude_agl_m 150``).

The package: :mod:`.common` (field types, names, wind sources), :mod:`.events` (event models),
:mod:`.schema` (the sections and :class:`Scenario`), :mod:`.checks` (cross-checks), :mod:`.io`
(reading and :func:`load_scenario`); every name is importable from here."""

from skyroute.pipeline.settings.checks import (  # noqa: F401
    _clamp_default_max_altitude,
    _event_problems,
    _outside_aoi,
    _raster_problems,
    _semantic_problems,
    _vehicle_altitude_problems,
    _vehicle_file_problems,
    _vehicle_max_altitude_m,
    planner_vehicle_problems,
)
from skyroute.pipeline.settings.common import (  # noqa: F401
    _NAME_OK,
    DEFAULT_SCENARIO,
    EVENT_KINDS,
    SAT_ID,
    Bounds,
    GriddedWind,
    NonNegFloat,
    PositiveFloat,
    UniformWind,
    Vertex,
    Waypoint,
    _check_polygon,
    _check_sat_ids,
    _is_file,
    _problems_from,
    _yaml_path,
    unsafe_name,
)
from skyroute.pipeline.settings.events import (  # noqa: F401
    MAP_EVENT_KINDS,
    Event,
    GnssEvent,
    IntruderEvent,
    IntruderUpdateEvent,
    NoFlyEvent,
    ObstacleEvent,
    WindEvent,
    _EventBase,
    _PolygonEvent,
    _TrackForms,
)
from skyroute.pipeline.settings.io import (  # noqa: F401
    _EVENTS,
    _raw_events_of,
    _read_yaml,
    _resolve_paths,
    _sorted_labels,
    catalog_dir,
    check_event_times,
    load_events_file,
    load_scenario,
    parse_scenario,
    scenario_at,
    scenario_paths,
    with_events,
)
from skyroute.pipeline.settings.schema import (  # noqa: F401
    PLANNERS,
    AoiSettings,
    BuildingsSource,
    Constraints,
    DataSources,
    GnssSettings,
    GroundReference,
    Intruder,
    Mission,
    MissionPoint,
    NavsimSettings,
    Obstacle,
    PlannerSettings,
    Scenario,
    SurfaceSource,
    TacticalSettings,
    TerrainSource,
    TrafficSettings,
    parse_planner,
)

__all__ = ["PositiveFloat", "NonNegFloat", "Bounds", "DEFAULT_SCENARIO", "unsafe_name", "UniformWind", "GriddedWind", "SAT_ID", "Vertex", "Waypoint", "EVENT_KINDS", "IntruderEvent", "IntruderUpdateEvent", "WindEvent", "GnssEvent", "NoFlyEvent", "ObstacleEvent", "Event", "MAP_EVENT_KINDS", "PLANNERS", "AoiSettings", "BuildingsSource", "TerrainSource", "SurfaceSource", "Obstacle", "GroundReference", "DataSources", "MissionPoint", "Mission", "Constraints", "GnssSettings", "Intruder", "TrafficSettings", "PlannerSettings", "parse_planner", "NavsimSettings", "TacticalSettings", "Scenario", "planner_vehicle_problems", "catalog_dir", "scenario_paths", "parse_scenario", "load_scenario", "load_events_file", "with_events", "check_event_times", "scenario_at"]

"""Public entry points: run a scenario's pipeline and check its mission against the maps."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import ScenarioError
from skyroute.pipeline.graph import RunResult, code_version_of, run_pipeline
from skyroute.pipeline.model import stable_hash
from skyroute.pipeline.settings import DEFAULT_SCENARIO, Scenario, load_scenario

if TYPE_CHECKING:
    import xarray as xr


def check_mission(scenario: Scenario, surface: xr.Dataset, grid=None, points: Sequence[str] = ("start", "goal")) -> None:
    """Refuse a mission whose start or goal lies inside a building or the terrain (the point's
    altitude, ``alt_agl_m`` above the terrain, must be above the surface there).  ``grid``: the
    grid of ``surface`` when it is not the scenario's (``skyroute inspect`` builds a small window
    around each point); ``points``: the mission points checked."""
    # a callable scheduler: dask looks a named one up by importing distributed (~0.5 s)
    from dask.local import get_sync

    g = grid or scenario.grid
    problems = []
    for name in points:
        p = getattr(scenario.mission, name)
        x, y = scenario.point_xy(p)
        r, c = (int(i) for i in g.cell_of(x, y))
        terr = float(surface["terrain"][r, c].compute(scheduler=get_sync))
        top = float(surface["surface"][r, c].compute(scheduler=get_sync))
        alt = terr + p.alt_agl_m
        if alt <= top:
            problems.append(f"mission.{name}: altitude {p.alt_agl_m:g} m above ground is inside a building or "
                            f"the terrain (surface {top - terr:.1f} m above ground there); raise alt_agl_m or move the point")
    if problems:
        raise ScenarioError(str(scenario.source_path or scenario.name), problems)


def run_scenario(scenario: Scenario | str = DEFAULT_SCENARIO, *, cache: Cache | None = None,
                 targets: Sequence[str] | None = None, scheduler: str = "threads", workers: int | None = None,
                 progress: bool = False, force: Sequence[str] = ()) -> RunResult:
    """Run every stage of ``scenario`` (a :class:`Scenario`, catalog name or YAML path).

    Stage outputs come from the cache when their inputs, settings and code are unchanged.
    """
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    cache = cache or Cache()
    result = run_pipeline(sc, cache=cache, targets=targets, scheduler=scheduler, workers=workers,
                          progress=progress, force=force)
    if "surface" in result.datasets:
        # the check's result is a function of the (content-addressed) surface, the grid, the
        # mission points and its code: once passed, a run with the same inputs reads no map
        surf = next(r for r in result.records if r.name == "surface")
        key = mission_check_key(sc, surf.key) if surf.path else None
        if key is None or not cache.passed("mission", key):
            check_mission(sc, result.datasets["surface"])
            if key is not None:
                cache.note_passed("mission", key)
    return result


def mission_check_key(scenario: Scenario, surface_key: str) -> str:
    """Key of :func:`check_mission` on the surface stage entry ``surface_key``: its code
    (with the point and grid geometry it uses), the grid and the mission's start and goal."""
    cv = code_version_of(check_mission, modules=("skyroute.pipeline.settings.schema", "skyroute.stages.gridspec"))
    return stable_hash("check_mission", cv, surface_key, scenario.grid, scenario.mission.start, scenario.mission.goal)

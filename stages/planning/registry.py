"""The planner registry: every STEP I planner skyroute knows, in one table (issue 25).

Everything that lists planners reads it: the CLI's ``--planner`` / ``--planners`` choices, the
scenario validation (``planner.name``), ``skyroute compare``, :func:`plan_step1` and
:func:`plan_strategic`'s dispatch, and the docs.  Pure data, no imports: reading it costs
nothing at start-up and pulls no planner into a stage's code closure.

Adding a planner is one module with its solve function and one :class:`PlannerInfo` line here
(see ARCHITECTURE.md, "Adding a planner").
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FIXED_WING_PLANNERS", "PLANNERS", "REGISTRY", "ROTORCRAFT_PLANNERS", "PlannerInfo", "planner_help"]


@dataclass(frozen=True)
class PlannerInfo:
    """One planner: ``name`` (the scenario's ``planner.name``), ``kind`` of vehicle it plans for
    (``"rotorcraft"`` or ``"fixed-wing"``), ``solver`` (``module:function`` of its solve
    function), ``stops_on`` (the counted work that ends it: results never depend on the clock),
    ``seeded`` (``planner.seed`` changes its result) and a one-line ``description``."""

    name: str
    kind: str
    solver: str
    stops_on: str
    seeded: bool
    description: str


REGISTRY: dict[str, PlannerInfo] = {p.name: p for p in (
    PlannerInfo("astar", "rotorcraft", "skyroute.stages.planning.grid_planner:plan_grid",
                "node expansions, then refinement segment evaluations", False,
                "3-D lattice A* with a consistent heuristic, then shortcut + vertex relaxation (seed 000)"),
    PlannerInfo("bitstar", "rotorcraft", "skyroute.stages.planning.bitstar:plan_bitstar",
                "BIT* iterations (planner.time_budget_s x BITSTAR_ITERATIONS_PER_S)", True,
                "OMPL BIT* on the continuous space (seed 000 III-A)"),
    PlannerInfo("potential", "rotorcraft", "skyroute.stages.planning.potential:plan_potential",
                "the wave reaching the start (a finite voxel set)", False,
                "numerical potential field on the skeleton of free space (seed 004 III-B)"),
    PlannerInfo("eeastar", "fixed-wing", "skyroute.stages.planning.fixedwing:plan_fixedwing",
                "lattice expansions", False, "energy-efficient A* for fixed-wing aircraft (seed 002)"),
    PlannerInfo("astar-fw", "fixed-wing", "skyroute.stages.planning.fixedwing:plan_fixedwing",
                "lattice expansions", False, "shortest-distance A* on the fixed-wing lattice (seed 002 baseline)"),
    PlannerInfo("energy-optimal", "fixed-wing", "skyroute.stages.planning.fixedwing:plan_fixedwing",
                "lattice expansions", False, "Dijkstra on energy over the fixed-wing lattice (seed 002 baseline)"),
    PlannerInfo("bitstar-dubins", "fixed-wing", "skyroute.stages.planning.bitstar_dubins:dubins_result",
                "BIT* iterations (planner.time_budget_s x DUBINS_ITERATIONS_PER_S)", True,
                "OMPL BIT* on the Dubins-airplane space (continuous curves)"),
)}

PLANNERS: tuple[str, ...] = tuple(REGISTRY)
FIXED_WING_PLANNERS: tuple[str, ...] = tuple(n for n, p in REGISTRY.items() if p.kind == "fixed-wing")
ROTORCRAFT_PLANNERS: tuple[str, ...] = tuple(n for n, p in REGISTRY.items() if p.kind == "rotorcraft")


def planner_help() -> str:
    """The planners by vehicle kind, for help texts."""
    return (f"rotorcraft: {', '.join(ROTORCRAFT_PLANNERS)}; fixed-wing: {', '.join(FIXED_WING_PLANNERS)}")

"""Synthetic encounters flown on a scenario's cached plan and maps (issue 22): the harness of
``tests/test_tactical_escape.py`` and ``benchmarks/bench_encounters.py``.

:func:`encounter_case` loads a scenario's strategic plan, maps and replay settings once (the
stages come from the cache); :func:`fly_encounter` flies one
:class:`~skyroute.stages.tactical.encounters.Encounter` with a rotorcraft method (``levels`` or
``octant``, :func:`~skyroute.stages.tactical.replay.replay`) or the fixed-wing ``local`` planner
(:func:`~skyroute.stages.tactical.fw_local.simulate_local`) and measures the outcome by brute
force (:func:`~skyroute.stages.tactical.encounters.flown_losses`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["EncounterCase", "EncounterOutcome", "encounter_case", "fly_encounter"]


@dataclass
class EncounterCase:
    """A scenario's plan and maps, loaded once: ``traj`` / ``t0_s`` (the chosen plan's exact
    trajectory), ``goal_xyz``, ``world`` (the replay's maps), ``params`` (FlyParams),
    ``vehicle``, ``start_time_utc``, ``dop_threshold``, ``kind`` (multirotor / fixed-wing) and,
    for fixed-wing scenarios, the plan's samples ``plan_t_s`` / ``plan_xyz_m``."""

    name: str
    traj: object
    t0_s: float
    goal_xyz: np.ndarray
    world: object
    params: object
    vehicle: object
    start_time_utc: str
    dop_threshold: float | None
    kind: str
    plan_t_s: np.ndarray
    plan_xyz_m: np.ndarray
    crs_wkt: str = ""
    vertical_datum: str = ""
    local: dict | None = None        # fixed-wing: the local planner's params, wind and floor samplers


@dataclass
class EncounterOutcome:
    """One encounter flown: the outcome, the smallest brute-force separation margin [m] from the
    time each intruder was known (``inf`` without intruders), ``lost`` (that margin < 0: a known
    conflict the flight did not avoid), ``unknown_loss`` (a loss before the intruder was reported:
    a replanned path met it earlier than the plan would have), ``declared_unavoidable`` (the replay
    accepted a predicted loss), the chosen levels, ``escapes`` (how many), ``decision_s`` (the
    compute time [s] of each level 2 and 3 and each escape decision; fixed-wing: each escape
    choice) and the FlightLog (fixed-wing: the LocalResult)."""

    outcome: str
    margin_m: float
    lost: bool
    declared_unavoidable: bool
    chosen: list
    escapes: int
    decision_s: list
    log: object
    unknown_loss: bool = False


def encounter_case(scenario, *, cache=None, method: str | None = None) -> EncounterCase:
    """Load ``scenario`` (a name, a YAML path or a Scenario) through the cached stages."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fly import _world, fly_params, tactical_method
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import Scenario, load_scenario
    from skyroute.stages.base import PlanningError
    from skyroute.stages.planning.strategic import plan_from_dataset, trajectory_from_dataset
    from skyroute.stages.vehicle import load_vehicle

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    sc = sc.model_copy(update={"events": ()})
    res = run_scenario(sc, cache=cache or Cache(), targets=["plan"])
    plan = res["plan"].load()
    chosen, _ = plan_from_dataset(plan)
    if chosen is None:
        raise PlanningError(f"scenario {sc.name!r} has no flyable plan to fly encounters on")
    veh = load_vehicle(sc.vehicle)
    kind = "fixed-wing" if veh.kind == "fixed-wing" else "multirotor"
    surf = res["surface"]
    tr = trajectory_from_dataset(plan) if kind == "multirotor" else None
    traj, t0 = tr if tr is not None else (None, float(chosen.t_s[0]))
    m = tactical_method(sc, method) if kind == "multirotor" else "local"
    params = fly_params(sc, method=m) if kind == "multirotor" else None
    local = None
    if kind == "fixed-wing":
        from skyroute.pipeline.fly_fw import local_params, local_problem
        from skyroute.stages.planning.step3 import wind_sampler
        from skyroute.stages.tactical.fw_local import floor_sampler

        pr = local_problem(sc, res)
        local = {"params": local_params(sc, None), "wind_at": wind_sampler(pr), "floor_at": floor_sampler(pr)}
    return EncounterCase(sc.name, traj, float(t0), np.asarray(chosen.xyz_m[-1], float), _world(res), params, veh,
                         sc.mission.start_time_utc.isoformat(), chosen.dop_threshold, kind,
                         np.asarray(chosen.t_s, float), np.asarray(chosen.xyz_m, float),
                         str(surf["surface"].rio.crs), surf["surface"].attrs.get("vertical_datum", ""), local)


class _PlanTrack:
    """A plan's samples as the minimal trajectory interface the encounter builder reads."""

    def __init__(self, t_s: np.ndarray, xyz_m: np.ndarray):
        self.t, self.p = t_s - t_s[0], xyz_m
        self.duration_s = float(self.t[-1])

    def sample(self, tau):
        tau = np.atleast_1d(np.asarray(tau, float))
        return np.column_stack([np.interp(tau, self.t, self.p[:, k]) for k in range(3)])

    def velocity(self, tau):
        v = np.gradient(self.p, self.t, axis=0)
        tau = np.atleast_1d(np.asarray(tau, float))
        return np.column_stack([np.interp(tau, self.t, v[:, k]) for k in range(3)])


def plan_track(case: EncounterCase):
    """The plan the encounters are drawn against: the exact trajectory (rotorcraft) or the plan's
    samples (fixed-wing), with ``sample`` / ``velocity`` at trajectory times and ``duration_s``."""
    return case.traj if case.traj is not None else _PlanTrack(case.plan_t_s, case.plan_xyz_m)


def fly_encounter(case: EncounterCase, enc, *, method: str = "levels", seed: int = 0) -> EncounterOutcome:
    """Fly ``enc`` on ``case`` with ``method`` (``levels`` / ``octant``: multirotor; ``local``:
    fixed-wing) and measure it (brute force every 0.05 s)."""
    from skyroute.stages.tactical.encounters import encounter_events, flown_losses

    if case.kind == "fixed-wing":
        return _fly_fixedwing(case, enc)
    from skyroute.stages.tactical.replay import replay

    params = dataclasses.replace(case.params, method=method, seed=seed)
    events = encounter_events(enc, case.traj, case.t0_s)
    log = replay(case.traj, case.t0_s, goal_xyz=case.goal_xyz, world=case.world, world_at=lambda t: case.world,
                 events=events, strategic_intruders=[], vehicle=case.vehicle, params=params,
                 start_time_utc=case.start_time_utc, dop_threshold=case.dop_threshold, scenario=case.name,
                 crs_wkt=case.crs_wkt, vertical_datum=case.vertical_datum)
    margin = min(flown_losses(log, known_only=True).values(), default=math.inf)
    before = min(flown_losses(log).values(), default=math.inf) < 0 <= margin
    chosen = [a.level for a in log.attempts if a.chosen]
    return EncounterOutcome(log.outcome, margin, margin < 0, bool(log.losses), chosen, len(log.escapes),
                            [float(a.compute_s) for a in log.attempts if a.level in ("2", "3", "escape")], log,
                            before)


def _fly_fixedwing(case: EncounterCase, enc) -> EncounterOutcome:
    from skyroute.stages.tactical.encounters import encounter_intruders
    from skyroute.stages.tactical.fw_local import (
        LocalAgent,
        LocalTrack,
        brute_force_min_separation,
        simulate_local,
    )

    drawn = encounter_intruders(enc, plan_track(case), case.t0_s)
    tracks = [LocalTrack(it.id, it.times_s, it.xyz_m, it.radius_m) for _t, it, _v in drawn]
    known = {it.id: t for t, it, _v in drawn}
    loc = case.local
    res = simulate_local([LocalAgent("own", case.plan_t_s, case.plan_xyz_m, case.vehicle)], intruders=tracks,
                         params=loc["params"], wind_at=loc["wind_at"], floor_at=loc["floor_at"], baseline=False,
                         known_from_s=known)
    pairs = brute_force_min_separation(res, tracks)
    margin = min((r["min_distance_m"] - r["threshold_m"] for r in pairs), default=math.inf)
    kinds = [m["kind"] for m in res.manoeuvres]
    return EncounterOutcome("goal" if math.isfinite(res.arrived_s[0]) else "failed", margin, margin < 0,
                            any(not m.get("keeps_separation", True) for m in res.manoeuvres), kinds,
                            len(kinds), [m["compute_s"] for m in res.manoeuvres if "compute_s" in m], res)

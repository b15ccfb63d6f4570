"""Tactical replanning benchmark (issue 11): random tactical intruders on two cities.

For each city the strategic plan is computed (cached stages), then each random intruder is
flown as a single-event replay (:func:`skyroute.stages.tactical.replay.replay`): it crosses
the plan at a random time, angle (0-360 deg: crossing, overtaking and head-on encounters),
speed and altitude offset, and is reported 8-30 s before the encounter (t_coll > t_rep).
Printed per city and overall: success rate per level (flyable among tried), the chosen level
distribution, p50 / p95 compute time per level and per replanning, against the targets of
issue 11 (level 1 < 20 ms, levels 2 and 3 p95 < 0.5 s) and as a ratio to the strategic plan's
own compute time (the baseline: re-planning the mission from scratch), measured in the same
run.  Seeded: the same ``--seed`` gives the same encounters.

    python benchmarks/bench_tactical.py [--n 200] [--seed 0] [--quick] [--cities NAME_OR_YAML ...]

``--cities`` takes catalog names or scenario files, e.g. the 6 x 6 km Helsinki AOI of issue 23
(a plan of 9.6 M cells, where level 3 replans with the multi-resolution A*).
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

CITIES = ("helsinki-medical", "rotterdam-canyon")


def _city(name: str, cache_dir: str | None):
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fly import _world, fly_params
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.planning.strategic import plan_from_dataset, trajectory_from_dataset

    sc = load_scenario(name)
    res = run_scenario(sc, cache=Cache(cache_dir), targets=["plan"])
    plan = res["plan"].load()
    chosen, _ = plan_from_dataset(plan)
    traj, t0 = trajectory_from_dataset(plan)
    return sc, res, plan, chosen, traj, t0, _world(res), fly_params(sc)


def _encounter(rng, chosen, t0, traj):
    from skyroute.stages.traffic import Intruder

    T = traj.duration_s
    tau = t0 + rng.uniform(0.2, 0.8) * T
    p = traj.sample([tau - t0])[0]
    ang = rng.uniform(0, 2 * math.pi)
    speed = rng.uniform(5.0, 12.0)
    u = np.array([math.cos(ang), math.sin(ang), 0.0]) * speed
    dz = rng.uniform(-3.0, 3.0)
    q = p + np.array([0.0, 0.0, dz])
    it = Intruder("bench", np.array([tau - 40.0, tau + 40.0]), np.stack([q - 40.0 * u, q + 40.0 * u]), 2.0)
    t_e = max(tau - rng.uniform(8.0, 30.0), t0 + 0.5)
    return it, t_e


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="random intruders in all (split between the cities)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="10 intruders, one city")
    ap.add_argument("--cache-dir", default=os.environ.get("SKYROUTE_CACHE_DIR"))
    ap.add_argument("--cities", nargs="+", default=list(CITIES), help="catalog scenarios or scenario YAML files")
    a = ap.parse_args()
    from skyroute.stages.tactical.replay import TacticalEvent, replay

    cities = a.cities[:1] if a.quick else a.cities
    n_per = 10 if a.quick else max(a.n // len(cities), 1)
    rows_all = []
    for name in cities:
        sc, res, plan, chosen, traj, t0, world, params = _city(name, a.cache_dir)
        from skyroute.stages.vehicle import load_vehicle

        veh = load_vehicle(sc.vehicle)
        base_s = float(plan.attrs.get("compute_s", math.nan))
        rng = np.random.default_rng(a.seed)
        rows = []
        t_start = time.perf_counter()
        for k in range(n_per):
            it, t_e = _encounter(rng, chosen, t0, traj)
            log = replay(traj, t0, goal_xyz=chosen.xyz_m[-1], world=world, world_at=lambda t, w=world: w,
                         events=[TacticalEvent(t_e, "intruder", "intruder bench", intruder=it)],
                         strategic_intruders=[], vehicle=veh, params=params,
                         start_time_utc=sc.mission.start_time_utc.isoformat(), dop_threshold=chosen.dop_threshold,
                         scenario=sc.name)
            for r in log.attempts:
                rows.append({"city": name, "k": k, "level": r.level, "flyable": r.flyable, "chosen": r.chosen,
                             "compute_s": r.compute_s, "t_coll_s": r.t_coll_s, "reasons": r.reasons})
            if not log.attempts:
                rows.append({"city": name, "k": k, "level": "none", "flyable": True, "chosen": True,
                             "compute_s": 0.0, "t_coll_s": math.inf})
            print(f"\r{name}: {k + 1}/{n_per} replays ({time.perf_counter() - t_start:.0f} s)", end="", flush=True)
        print()
        _report(name, rows, base_s)
        rows_all += rows
    if len(cities) > 1:
        _report("all", rows_all, math.nan)


def _report(name: str, rows: list[dict], base_s: float) -> None:
    print(f"\n== {name}: {len({(r['city'], r['k']) for r in rows})} encounters "
          f"(strategic plan compute time, the baseline: {base_s:.2f} s)")
    print(f"{'level':8s} {'tried':>6s} {'flyable':>8s} {'chosen':>7s} {'p50 ms':>9s} {'p95 ms':>9s} {'p95/base':>9s}")
    for lv in ("1", "2", "3", "landing", "none"):
        rs = [r for r in rows if r["level"] == lv]
        if not rs:
            continue
        cs = np.array([r["compute_s"] for r in rs]) * 1e3
        ok = sum(r["flyable"] for r in rs)
        ch = sum(r["chosen"] for r in rs)
        p50, p95 = np.percentile(cs, 50), np.percentile(cs, 95)
        print(f"{lv:8s} {len(rs):6d} {ok / len(rs):8.1%} {ch:7d} {p50:9.1f} {p95:9.1f} {p95 / 1e3 / base_s:9.3f}")
    fails = [r for r in rows if r["level"] == "landing" and not r["flyable"]]
    if fails:
        kinds = {"separation during the braking / landing path": "separation from intruder",
                 "RRT found no way out of the reserved volumes": "STEP II reached",
                 "cannot slow down for the corners": "cannot slow down",
                 "navigation error above dp_max": "navigation error"}
        counts = {k: sum(v in r["reasons"] for r in fails) for k, v in kinds.items()}
        print("failed landings (" + str(len(fails)) + "), reasons named among the sites tried: "
              + ", ".join(f"{k} {n}" for k, n in counts.items() if n))
    per = {}
    for r in rows:
        per[(r["city"], r["k"])] = per.get((r["city"], r["k"]), 0.0) + r["compute_s"]
    tot = np.array(list(per.values())) * 1e3
    print(f"per replanning (all levels): p50 {np.percentile(tot, 50):.1f} ms, p95 {np.percentile(tot, 95):.1f} ms; "
          "targets: level 1 < 20 ms, levels 2 and 3 p95 < 500 ms")


if __name__ == "__main__":
    main()

"""``skyroute navsim``: Monte Carlo navigation along a scenario's plan (or a flown trajectory).

The plan, maps and sky come from the cached stages (:func:`run_scenario`, target ``plan``);
the trajectory is the chosen plan's exact trajectory sampled at ``navsim.rate_hz`` (or the
``flown.csv`` of ``skyroute fly``, resampled); the line of sight and occlusion along it come
from the exact visibility heights (:func:`skyroute.stages.navsim.flight_geometry`) and the
simulation is :func:`skyroute.stages.navsim.simulate`.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from skyroute.pipeline.budget import MAX_NAVSIM_RUNS, check_navsim
from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import InputError
from skyroute.pipeline.fly_common import shortest_flight_s
from skyroute.pipeline.progress import dask_tasks, phase
from skyroute.pipeline.runner import RunResult, run_scenario
from skyroute.pipeline.settings import Scenario

__all__ = ["MAX_FLOWN_BYTES", "NavsimResult", "add_protection_levels", "integrity_budget", "navsim_params",
           "navsim_scenario", "read_flown_csv"]

MAX_FLOWN_BYTES = 256 << 20   # a flown.csv: ~60 B per 0.1 s tick, 256 MB is a 100 h flight


@dataclass
class NavsimResult:
    result: RunResult
    ds: object                 # the simulate() Dataset
    source: str                # "plan" or the flown.csv path
    surface_uncertainty_m: float
    t_s: np.ndarray | None = None        # the simulated trajectory
    xyz_m: np.ndarray | None = None
    dop_threshold: float | None = None   # the plan's coverage level (the morphing map's floor)


def integrity_budget(sc: Scenario):
    """The protection level's budgets of ``sc.navsim`` (integrity and false alert split
    equally between horizontal and vertical)."""
    from skyroute.stages.integrity import IntegrityBudget

    n = sc.navsim
    return IntegrityBudget(p_hmi_hor=n.pl_p_hmi / 2, p_hmi_vert=n.pl_p_hmi / 2, p_fa_hor=n.pl_p_fa / 2,
                           p_fa_vert=n.pl_p_fa / 2, p_sat=n.pl_p_sat)


def navsim_params(sc: Scenario):
    from skyroute.stages.navsim import NavsimParams

    n = sc.navsim
    return NavsimParams(sigma_uere_m=sc.gnss.uere_m, nlos_bias_mean_m=n.nlos_bias_mean_m,
                        nlos_bias_distribution=n.nlos_bias_distribution, nlos_noise_factor=n.nlos_noise_factor,
                        nlos_reception_prob=n.nlos_reception_prob, gnss_rate_hz=n.gnss_rate_hz,
                        mu_nlos_weak=n.mu_nlos_weak, scale_r_by_dop=n.scale_r_by_dop)


def add_protection_levels(ds, los_enu, visible, sigma_uere_m: float, budget=None) -> None:
    """Add ``hpl_m``, ``vpl_m`` (time) [m] to the simulate() Dataset ``ds`` (in place): the
    single-fault solution-separation protection levels of the snapshot least squares of the
    line-of-sight satellites (:func:`skyroute.stages.integrity.pl_series`, the proposed
    filter's set), budgets in the variables' attrs (``budget_*``)."""
    from skyroute.stages.integrity import IntegrityBudget, pl_series

    budget = IntegrityBudget() if budget is None else budget
    hpl, vpl = pl_series(los_enu, visible, sigma_uere_m, budget)
    attrs = {f"budget_{k}": v for k, v in budget.as_dict().items()}
    ds["hpl_m"] = ("time", hpl, {"units": "m", "long_name": "horizontal protection level, single-fault solution "
                                 "separation of the line-of-sight snapshot (+inf = none)", **attrs})
    ds["vpl_m"] = ("time", vpl, {"units": "m", "long_name": "vertical protection level, single-fault solution "
                                 "separation of the line-of-sight snapshot (+inf = none)", **attrs})


def read_flown_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, xyz_m)`` of a ``flown.csv`` written by ``skyroute fly`` (columns t_s, x_m, y_m,
    z_m); one ``error:`` line for a file that is not one."""
    import io

    from skyroute.stages.base import DataError, read_limited

    path = Path(path)
    try:     # a missing file, a folder, a device or FIFO, or more than MAX_FLOWN_BYTES: one line
        text = read_limited(path, MAX_FLOWN_BYTES, "--trajectory").decode("utf-8")
    except DataError as exc:
        raise InputError(f"{exc} (give the flown.csv of `skyroute fly`)") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"--trajectory {path}: not a UTF-8 text file ({exc.reason} at byte {exc.start}); give the "
                         "flown.csv of `skyroute fly`") from None
    try:
        with io.StringIO(text, newline="") as fh:
            rows = list(csv.DictReader(fh))
        t = np.array([float(r["t_s"]) for r in rows])
        p = np.array([[float(r["x_m"]), float(r["y_m"]), float(r["z_m"])] for r in rows])
    except (KeyError, ValueError, csv.Error) as exc:
        raise InputError(f"--trajectory {path}: not a flown.csv of `skyroute fly` (needs columns t_s, x_m, y_m, "
                         f"z_m; {exc})") from None
    if t.size < 2 or not np.all(np.diff(t) > 0):
        raise InputError(f"--trajectory {path}: needs at least two samples with increasing t_s")
    return t, p


def navsim_scenario(sc: Scenario, *, cache: Cache | None = None, runs: int | None = None, seed: int | None = None,
                    trajectory: Path | None = None, scheduler: str = "threads", progress: bool = False) -> NavsimResult:
    """Plan (cached) and simulate the navigation of ``sc``'s chosen plan or of ``trajectory``.
    ``progress``: show the stages' progress (the simulation's phases are shown whenever the
    command shows progress, :mod:`skyroute.pipeline.progress`)."""
    from skyroute.stages.base import PlanningError
    from skyroute.stages.grid import Grid
    from skyroute.stages.navsim import flight_geometry, simulate
    from skyroute.stages.planning.strategic import plan_from_dataset, trajectory_from_dataset
    from skyroute.stages.vehicle import load_vehicle

    n = sc.navsim
    runs = n.runs if runs is None else runs
    seed = n.seed if seed is None else seed
    if not (isinstance(runs, int) and 1 <= runs <= MAX_NAVSIM_RUNS):
        raise InputError(f"--runs {runs}: give an integer from 1 to {MAX_NAVSIM_RUNS:,}")
    params = navsim_params(sc)
    flown = read_flown_csv(trajectory) if trajectory is not None else None   # bad files: before any work
    if not sc.data.almanacs:
        raise InputError(f"scenario {sc.name!r} has no almanac (data.almanacs): navsim needs satellites")
    dt = 1.0 / n.rate_hz
    if flown is not None:     # the memory of the Monte Carlo, before any work: the flight's epochs
        check_navsim(sc, runs, math.floor((flown[0][-1] - flown[0][0]) / dt + 1e-9) + 1.0)
    else:                     # the plan does not exist yet: at least the straight line at top speed
        check_navsim(sc, runs, math.floor(shortest_flight_s(sc) / dt) + 1.0, at_least=True)
    result = run_scenario(sc, cache=cache or Cache(), targets=["plan"], scheduler=scheduler, progress=progress)
    if flown is None:
        plan = result["plan"].load()
        chosen, _ = plan_from_dataset(plan)
        tr = trajectory_from_dataset(plan)
        if chosen is None:
            raise PlanningError(f"no strategic plan to simulate: {plan.attrs.get('reason', '')}")
        if tr is not None:
            traj, t0 = tr
            t = t0 + np.arange(0.0, traj.duration_s + 1e-9, dt)
            xyz = traj.sample(t - t0)
        else:   # a fixed-wing plan: its samples (lines and arcs sampled densely), linearly interpolated
            ts, ps = np.asarray(chosen.t_s, float), np.asarray(chosen.xyz_m, float)
            t = np.arange(ts[0], ts[-1] + 1e-9, dt)
            xyz = np.column_stack([np.interp(t, ts, ps[:, k]) for k in range(3)])
        source = "plan"
        dop_threshold = chosen.dop_threshold
    else:
        tf, pf = flown
        t = np.arange(tf[0], tf[-1] + 1e-9, dt)
        xyz = np.column_stack([np.interp(t, tf, pf[:, k]) for k in range(3)])
        source = str(trajectory)
        dop_threshold = max(sc.gnss.dop_thresholds)
    check_navsim(sc, runs, float(t.size))       # the planned flight's epochs, before the simulation
    surf = result["surface"].load()
    holder = SimpleNamespace(grid=Grid.from_dataarray(surf["terrain"]))   # line_of_sight reads the grid only
    sky = result["satellites"].load()
    on = True if progress else None
    with phase("navsim: line of sight", detail=f"{t.size:,} epochs", on=on):
        los, vis, up = flight_geometry(holder, sky, surf["surface"].values, t, xyz,
                                       sc.mission.start_time_utc.isoformat())
    with phase("navsim: Monte Carlo", detail=f"{runs:,} runs x {t.size:,} epochs, 2 filters", on=on):
        ds = simulate(t, xyz, los, vis, up, params=params, imu=load_vehicle(sc.vehicle), runs=runs, seed=seed)
    with phase("navsim: protection levels", on=on):
        add_protection_levels(ds, los, vis, params.sigma_uere_m, budget=integrity_budget(sc))
    ds.attrs.update({"scenario": sc.name, "source": source, "runs": runs, "seed": seed,
                     "start_time_utc": sc.mission.start_time_utc.isoformat(), "rate_hz": n.rate_hz})
    return NavsimResult(result, ds, source, float(n.surface_uncertainty_m), t, xyz, dop_threshold)


def write_morphing(sc: Scenario, r: NavsimResult, out_dir: Path) -> list[Path]:
    """The digital morphing map of the flight (issue 12 item 5): the coverage floor per epoch
    every ``navsim.morphing_step_s`` over the flight's box (``morphing.zarr``) and a GIF of the
    floor of the plan's DOP level under the moving vehicle (``morphing_<DOP><D>.gif``)."""
    from skyroute.stages.morphing import animate_floor, coverage_floor_series

    n = sc.navsim
    if n.morphing_step_s <= 0 or r.dop_threshold is None:
        return []
    surf = r.result["surface"].load()
    sky = r.result["satellites"].load()
    t0 = float(r.t_s[0])
    times = np.arange(t0, float(r.t_s[-1]) + 1e-9, n.morphing_step_s)
    m = n.morphing_margin_m
    lo, hi = r.xyz_m[:, :2].min(axis=0), r.xyz_m[:, :2].max(axis=0)
    c, half = (lo + hi) / 2.0, float(np.max(hi - lo)) / 2.0 + m        # a square box: a readable map
    g = r.result.scenario.grid
    x0, y0, x1, y1 = g.bounds
    box = (max(c[0] - half, x0), max(c[1] - half, y0), min(c[0] + half, x1), min(c[1] + half, y1))
    terrain = surf["terrain"]
    series = coverage_floor_series(surf["surface"], sky, thresholds=tuple(sc.gnss.dop_thresholds), dop=sc.gnss.dop_kind,
                                   floor_m=terrain + sc.constraints.min_altitude_agl_m,
                                   ceiling_m=surf.get("terrain_min", terrain) + sc.constraints.max_altitude_agl_m,
                                   mask_deg=sc.gnss.elevation_mask_deg, times=times, region_m=box)
    with phase("navsim: morphing map", detail=f"{times.size} epochs"), dask_tasks():
        series = series.compute()
    zarr_path = Path(out_dir) / "morphing.zarr"
    from skyroute.pipeline.outputs import remove_path

    remove_path(zarr_path)
    series.drop_vars([v for v in series.variables if series[v].dtype.kind in "OU"], errors="ignore").to_zarr(
        zarr_path, mode="w", consolidated=False)
    gif = Path(out_dir) / f"morphing_{sc.gnss.dop_kind}{r.dop_threshold:g}.gif"
    with phase("navsim: morphing GIF", detail=gif.name):
        animate_floor(series, r.dop_threshold, r.t_s, r.xyz_m, gif)
    return [zarr_path, gif]

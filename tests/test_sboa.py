"""Safety bubble in planning (seed 003 SBOA, issue 12 item 3): the per-level sigma bound against
the navigation filter on random geometries, the per-level radius, the brute-force bubble check,
and a synthetic plan with and without the bubble (distances by an all-cells brute force)."""

from __future__ import annotations

import csv
import warnings

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from skyroute.pipeline.errors import InputError
from skyroute.pipeline.settings import catalog_dir
from skyroute.stages.almanac import sky_geometry
from skyroute.stages.clearance import clearance_dataset
from skyroute.stages.environment import environment_risk_dataset
from skyroute.stages.grid import Grid
from skyroute.stages.navigation import los_from_az_el, navigation_error
from skyroute.stages.planning.outputs import CANDIDATE_COLUMNS, write_plan
from skyroute.stages.planning.strategic import plan_from_dataset, plan_levels, plan_to_dataset
from skyroute.stages.planning.validate import surface_clearance_m, validate_bubble
from skyroute.stages.sboa import check_dop_kind, level_radius_m, level_sigma_m
from skyroute.stages.vehicle import load_vehicle

X0, Y0 = 384000.0, 6670000.0
START = "2020-01-03T12:00:00Z"
THRESHOLDS = [3.0, 5.0]


def _pdop(u: np.ndarray) -> float:
    g = np.column_stack([-u, np.ones(len(u))])
    return float(np.sqrt(np.trace(np.linalg.inv(g.T @ g)[:3, :3])))


def test_level_sigma_bounds_the_filter_on_random_geometries():
    """The filter of STEP III (same prior, 60 s warm-up, 1 s updates at 0.5 s samples) on random
    static skies above 5 deg: its largest sigma_p after the warm-up stays below the bound of any
    level D >= its PDOP (the bound is computed once per PDOP, the worst case of that level)."""
    rng = np.random.default_rng(7)
    checked, worst = 0, 0.0
    t = np.concatenate([np.arange(0.0, 60.0, 1.0), 60.0 + np.arange(0.0, 120.0, 0.5)])
    while checked < 40:
        n = int(rng.integers(4, 13))
        u = los_from_az_el(rng.uniform(0, 360, n), rng.uniform(5, 90, n))
        with np.errstate(all="ignore"):
            try:
                p = _pdop(u)
            except np.linalg.LinAlgError:
                continue
        if not (np.isfinite(p) and p < 8):
            continue
        for uere in (1.0, 3.0):
            nav = navigation_error(t, np.broadcast_to(u, (t.size, n, 3)), np.ones((t.size, n), bool),
                                   gnss_sigma_m=uere, dt_s=1.0)
            s = float(nav["sigma_p_m"].values[t >= 60.0].max())
            b = level_sigma_m(p, uere_m=uere)
            assert s <= b, (n, p, uere, s, b)
            worst = max(worst, s / b)
        checked += 1
    assert worst > 0.5   # the bound is not vacuous


def test_level_sigma_below_snapshot_least_squares_and_radius_grows():
    """Closed-form check: a filter is never worse than a single-epoch least-squares fix,
    sigma <= UERE * PDOP; r_j grows with D_j and is r_p where the bubble is smaller."""
    sig = [level_sigma_m(d) for d in (1.5, 2.0, 3.0, 4.0, 6.0)]
    assert all(s <= 3.0 * d for s, d in zip(sig, (1.5, 2.0, 3.0, 4.0, 6.0), strict=True))
    assert np.all(np.diff(sig) > 0)
    r = [level_radius_m(d, 5.0, 3.0, 1.0) for d in (2.0, 3.0, 4.0)]
    assert np.all(np.diff(r) > 0) and r[0] > 5.0
    assert level_radius_m(2.0, 50.0, 3.0, 1.0) == 50.0
    assert level_radius_m(2.0, 1.0, 3.0, 1.0) == pytest.approx(3.0 * sig[1] + 1.0, abs=1e-12)
    with pytest.raises(InputError, match="PDOP or GDOP"):
        check_dop_kind("HDOP")
    check_dop_kind("GDOP")


def _grid() -> Grid:
    return Grid.from_bounds("EPSG:32635", X0, Y0, X0 + 240, Y0 + 160, 4.0)


def _surface(g: Grid) -> np.ndarray:
    s = np.zeros(g.shape)
    s[10:30, 25:35] = 150.0     # a tower (above the ceiling) between start and goal: fly around it
    return s


def _prism_distance(p: np.ndarray, g: Grid, s: np.ndarray) -> np.ndarray:
    """All-cells brute force: distance [m] of each point to the union of the prisms."""
    cx = g.x0 + (np.arange(g.nx) + 0.5) * g.resolution_m
    cy = g.y1 - (np.arange(g.ny) + 0.5) * g.resolution_m
    out = []
    for x, y, z in p:
        dx = np.maximum(np.abs(x - cx) - g.resolution_m / 2, 0)[None, :]
        dy = np.maximum(np.abs(y - cy) - g.resolution_m / 2, 0)[:, None]
        dz = np.maximum(z - s, 0)
        out.append(np.sqrt(dx**2 + dy**2 + dz**2).min())
    return np.array(out)


def test_validate_bubble_against_all_cells_brute_force():
    g = _grid()
    s = _surface(g)
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(X0 + 60, X0 + 180, 300), rng.uniform(Y0 + 20, Y0 + 150, 300),
                         rng.uniform(0, 170, 300)])
    ref = _prism_distance(p, g, s)
    d = surface_clearance_m(p, grid=g, surface_m=s, radius_m=12.0)
    near = ref <= 12.0
    assert np.allclose(d[near], ref[near], atol=1e-9) and np.isinf(d[~near]).all()
    assert near.any() and (~near).any()
    t = np.arange(p.shape[0], dtype=float)
    msgs = validate_bubble((t, p), grid=g, surface_m=s, radius_m=12.0)
    assert (len(msgs) == 1) == bool((ref < 12.0).any())
    assert f"{int((ref < 12.0).sum())} sample(s)" in msgs[0]
    far = p[ref > 12.0]
    assert validate_bubble((np.arange(len(far), dtype=float), far), grid=g, surface_m=s, radius_m=12.0) == []


_SKY: dict = {}


def _plans_inputs(g, s, veh, clearance_by_level=None, bubble=None):
    sd = g.dataarray(s, "surface", units="m")
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    surf = xr.Dataset({"terrain": t, "surface": sd})
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="no landing sites")
        env = environment_risk_dataset(g)
    if "sky" not in _SKY:
        lon, lat = g.to_lonlat(X0 + 120, Y0 + 80)
        with pytest.warns(UserWarning, match="unhealthy"):
            _SKY["sky"] = sky_geometry(catalog_dir() / "data" / "yuma_2020-01-03.txt",
                                       pd.date_range(pd.Timestamp(START), periods=6, freq="60s"), lat, lon)
    cov = xr.Dataset({"coverage_floor": (("threshold", "y", "x"), np.zeros((2, *g.shape)))},
                     coords={"threshold": THRESHOLDS, "y": sd["y"], "x": sd["x"]})
    clear = clearance_dataset(sd, veh.r_p_m, terrain=t, max_agl_m=80.0)
    return plan_levels(surf, env, None, clear, cov, _SKY["sky"], None, start_xy=(X0 + 60, Y0 + 100),
                          start_agl_m=30.0, goal_xy=(X0 + 200, Y0 + 100), goal_agl_m=30.0, start_time_utc=START,
                          planner="astar", weights=(1, 0, 0, 0), min_agl_m=0.0, max_agl_m=80.0, step_cells=2,
                          workers=1, clearance_by_level=clearance_by_level, bubble=bubble)


@pytest.fixture(scope="module")
def plans():
    g = _grid()
    s = _surface(g)
    sd = g.dataarray(s, "surface", units="m")
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    veh = load_vehicle("dji-m300-rtk")
    fixed = _plans_inputs(g, s, veh)
    radii = {d: level_radius_m(d, veh.r_p_m, 3.0, 1.0, imu=veh.imu) for d in THRESHOLDS}
    by_level = {d: clearance_dataset(sd, r, terrain=t, max_agl_m=80.0) for d, r in radii.items()}
    sboa = _plans_inputs(g, s, veh, clearance_by_level=by_level, bubble=(3.0, 1.0))
    return g, s, veh, radii, fixed, sboa


def test_sboa_plan_keeps_the_bubble_and_the_fixed_plan_does_not(plans):
    g, s, veh, radii, fixed, sboa = plans
    assert fixed.chosen is not None and sboa.chosen is not None, (fixed.reason, sboa.reason)
    for c in sboa.candidates:
        assert c.flyable, c.reasons
        assert c.clearance_radius_m == pytest.approx(radii[c.dop_threshold])
        need = np.maximum(veh.r_p_m, 3.0 * c.sigma_p_m + 1.0)
        d = _prism_distance(c.xyz_m, g, s)
        assert (d >= need - 1e-6).all(), float((d - need).min())
        assert (d >= c.clearance_radius_m - 1e-6).all()   # the planned radius itself
    f = fixed.chosen
    df = _prism_distance(f.xyz_m, g, s)
    assert (df >= veh.r_p_m - 1e-6).all()
    d_sboa = min(_prism_distance(c.xyz_m, g, s).min() for c in sboa.candidates)
    assert df.min() < min(radii.values()) <= d_sboa          # the fixed plan comes closer than r_j
    assert sboa.chosen.C_l > f.C_l                           # the detour costs length
    ds = plan_to_dataset(sboa, g.crs, "", START)
    assert np.allclose(ds["clearance_radius_m"].values, [radii[3.0], radii[5.0]])
    assert "clearance_radius_m" not in plan_to_dataset(fixed, g.crs, "", START)
    _, back = plan_from_dataset(ds)
    from skyroute.pipeline.outputs import plan_section

    assert plan_section(ds)["clearance_radius_m"] == pytest.approx(sboa.chosen.clearance_radius_m, abs=1e-3)
    assert "clearance_radius_m" not in plan_section(plan_to_dataset(fixed, g.crs, "", START))
    assert [c.clearance_radius_m for c in back] == pytest.approx([radii[3.0], radii[5.0]])


def test_candidates_csv_has_the_radius_column_only_with_sboa(plans, tmp_path):
    g, _, _, radii, fixed, sboa = plans
    for name, plan in (("fixed", fixed), ("sboa", sboa)):
        write_plan(plan.chosen, plan.candidates, g, tmp_path / name, START, "", figures=False)
    with open(tmp_path / "fixed" / "candidates.csv") as f:
        assert list(csv.DictReader(f).fieldnames) == list(CANDIDATE_COLUMNS)
    with open(tmp_path / "sboa" / "candidates.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["clearance_radius_m"]) for r in rows] == pytest.approx([radii[3.0], radii[5.0]], abs=0.005)


def test_bubble_recheck_rejects_a_plan_too_close(plans):
    """The fixed clearance with the STEP III bubble re-check at k = 5: the candidates that come
    closer than 5 sigma_p(t) + 1 m (brute force) are refused with the reason."""
    g, s, veh, radii, fixed, _ = plans
    f = fixed.chosen
    need = np.maximum(veh.r_p_m, 5.0 * f.sigma_p_m + 1.0)
    assert (_prism_distance(f.xyz_m, g, s) < need).any()
    msgs = validate_bubble(f, grid=g, surface_m=s, radius_m=need)
    assert len(msgs) == 1 and msgs[0].startswith("inside the safety bubble of the surface")
    plan = _plans_inputs(g, s, veh, bubble=(5.0, 1.0))
    assert plan.chosen is None
    assert all(any("inside the safety bubble" in r for r in c.reasons) for c in plan.candidates)


def test_settings_fixed_keeps_the_plan_settings_and_sboa_adds_its_own():
    """Default ``fixed``: the plan stage settings are the unchanged PlanSettings model (same cache
    key); ``sboa``: its own model carrying k, the surface uncertainty and the clearance settings."""
    from skyroute.pipeline.model import stable_hash
    from skyroute.pipeline.settings import load_scenario
    from skyroute.pipeline.stages_builtin import (
        PlanSboaSettings,
        PlanSettings,
        _clearance_settings,
        _plan_settings,
        _plan_settings_fixed,
    )

    sc = load_scenario("helsinki-medical")
    assert sc.constraints.clearance == "fixed"
    s = _plan_settings(sc)
    assert type(s) is PlanSettings and stable_hash(s) == stable_hash(_plan_settings_fixed(sc))
    sb = sc.model_copy(update={"constraints": sc.constraints.model_copy(update={"clearance": "sboa", "sboa_k": 2.0})})
    p = _plan_settings(sb)
    assert isinstance(p, PlanSboaSettings) and stable_hash(p) != stable_hash(s)
    assert p.sboa_k == 2.0 and p.surface_uncertainty_m == sc.navsim.surface_uncertainty_m
    assert p.clearance == _clearance_settings(sc)
    hd = sb.model_copy(update={"gnss": sb.gnss.model_copy(update={"dop_kind": "HDOP"})})
    with pytest.raises(InputError, match="PDOP or GDOP"):
        _plan_settings(hd)


@pytest.mark.slow
def test_helsinki_medical_with_the_bubble_flies_clear_of_it(cache):
    """The default scenario with ``constraints.clearance: sboa``: it flies, each level records
    its r_j, and the chosen trajectory keeps r_j and max(r_p, k sigma_p(t) + surface
    uncertainty) from every surface prism (all-cells brute force)."""
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario

    sc = load_scenario("helsinki-medical")
    sc = sc.model_copy(update={"constraints": sc.constraints.model_copy(update={"clearance": "sboa"})})
    r = run_scenario(sc, cache=cache, targets=["plan"])
    plan, surf = r.datasets["plan"], r.datasets["surface"]
    chosen, cands = plan_from_dataset(plan)
    assert chosen is not None and chosen.flyable, plan.attrs["reason"]
    veh = load_vehicle(sc.vehicle)
    k, su = sc.constraints.sboa_k, sc.navsim.surface_uncertainty_m
    radii = [level_radius_m(d, veh.r_p_m, k, su, imu=veh.imu, uere_m=sc.gnss.uere_m) for d in sc.gnss.dop_thresholds]
    assert [c.clearance_radius_m for c in cands] == pytest.approx(radii)
    g = Grid.from_dataarray(surf["surface"])
    s = surf["surface"].values
    x0, y0 = chosen.xyz_m[:, 0].min() - 60, chosen.xyz_m[:, 1].min() - 60   # cells within 60 m of the route
    x1, y1 = chosen.xyz_m[:, 0].max() + 60, chosen.xyz_m[:, 1].max() + 60
    cols = slice(max(int((x0 - g.x0) // g.resolution_m), 0), int((x1 - g.x0) // g.resolution_m) + 1)
    rows = slice(max(int((g.y1 - y1) // g.resolution_m), 0), int((g.y1 - y0) // g.resolution_m) + 1)
    sub = Grid(crs_wkt=g.crs_wkt, x0=g.x0 + cols.start * g.resolution_m, y1=g.y1 - rows.start * g.resolution_m,
               nx=s[rows, cols].shape[1], ny=s[rows, cols].shape[0], resolution_m=g.resolution_m)
    d = _prism_distance(chosen.xyz_m, sub, s[rows, cols])
    need = np.maximum(veh.r_p_m, k * chosen.sigma_p_m + su)
    assert (d >= need - 1e-6).all() and (d >= chosen.clearance_radius_m - 1e-6).all(), float(d.min())


def test_fly_params_refuse_a_bad_bubble():
    """The replay's safety bubble (``constraints.clearance: sboa`` in ``skyroute fly``) is its
    plan request's (issue 25: the request is the one home of the planning settings)."""
    from skyroute.stages.base import InputError
    from skyroute.stages.planning.request import PlanRequest
    from skyroute.stages.tactical.replay import FlyParams

    req = PlanRequest.of(start_xy=(0.0, 0.0), start_agl_m=30.0, goal_xy=(500.0, 0.0), goal_agl_m=30.0,
                         start_time_utc="2020-01-03T10:00:00+00:00", vehicle="dji-m300-rtk")
    assert FlyParams().bubble is None and FlyParams(request=req).bubble is None
    assert FlyParams(request=req.with_(bubble=(3.0, 1.0))).bubble == (3.0, 1.0)
    with pytest.raises(InputError, match=r"safety bubble k -1\.0 must be > 0"):
        FlyParams(request=req.with_(bubble=(-1.0, 0.0)))
    with pytest.raises(InputError, match=r"surface uncertainty -0\.5 m >= 0"):
        FlyParams(request=req.with_(bubble=(3.0, -0.5)))

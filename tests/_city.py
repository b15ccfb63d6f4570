"""A seeded synthetic city for the multi-resolution planner (issue 23): street blocks of
buildings of random heights (some towers above the altitude limit), no-fly discs, a risk map
that is higher over buildings and a landing-cost map, uniform wind.  Procedural, NOT real
data: shared by tests/test_multires.py and benchmarks/bench_city_scale.py.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from skyroute.stages.grid import Grid
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.vehicle import load_vehicle

X0, Y0 = 380000.0, 6670000.0     # EPSG:32635 lower-left corner [m]
PITCH_M, STREET_M = 80.0, 16.0   # block pitch and street width [m]
MAX_AGL_M = 80.0


def city_maps(size_m: tuple[float, float], res_m: float = 2.0, seed: int = 0) -> dict:
    """(ny, nx) maps on the grid of ``size_m`` = (east, north) [m]: ``grid``, ``clearance``
    (building height + 6 m over its footprint dilated by 4 m, 0 on streets) [m], ``risk`` (0.2
    over streets, 0.6 over buildings) [-], ``landing`` [-], ``nofly`` (bool discs)."""
    rng = np.random.default_rng(seed)
    g = Grid.from_bounds("EPSG:32635", X0, Y0, X0 + size_m[0], Y0 + size_m[1], res_m)
    ny, nx = g.shape
    x = (np.arange(nx) + 0.5) * res_m
    y = (np.arange(ny)[::-1] + 0.5) * res_m          # northing from the south edge
    bx, by = (x // PITCH_M).astype(int), (y // PITCH_M).astype(int)
    in_block_x = (x % PITCH_M) >= STREET_M
    in_block_y = (y % PITCH_M) >= STREET_M
    nbx, nby = bx.max() + 1, by.max() + 1
    h = rng.uniform(8.0, 45.0, size=(nby, nbx))
    h[rng.random((nby, nbx)) < 0.04] = 95.0           # towers above the 80 m AGL limit
    h[rng.random((nby, nbx)) < 0.08] = 0.0            # parks
    height = np.where(in_block_y[:, None] & in_block_x[None, :], h[by[:, None], bx[None, :]], 0.0)
    from scipy.ndimage import maximum_filter

    dil = int(round(4.0 / res_m))
    clearance = np.where(maximum_filter(height, size=2 * dil + 1) > 0, maximum_filter(height, size=2 * dil + 1) + 6.0,
                         0.0)
    risk = np.where(height > 0, 0.6, 0.2)
    landing = 0.1 + 0.4 * rng.random((nby, nbx))[by[:, None], bx[None, :]]
    nofly = np.zeros((ny, nx), bool)
    n_disc = max(1, int(size_m[0] * size_m[1] / 1.5e6))
    for _ in range(n_disc):
        cx, cy = rng.uniform(0.2, 0.8) * size_m[0], rng.uniform(0.2, 0.8) * size_m[1]
        rad = rng.uniform(60.0, 150.0)
        nofly |= (x[None, :] - cx) ** 2 + (y[:, None] - cy) ** 2 <= rad ** 2
    return {"grid": g, "clearance": clearance, "risk": risk, "landing": landing, "nofly": nofly,
            "x_m": x, "y_m": y}


def city_wind(maps: dict, seed: int = 0, step_m: float = 400.0) -> xr.Dataset:
    """A varying wind map like ``wind_on_grid``'s: u, v, w (z, y, x) [m/s] on ``step_m`` cells and
    heights 0 / 40 / 80 / 160 m above ground, 2-9 m/s, direction turning with height and place
    (seeded); it makes the energy term's heuristic bound loose, as a real wind map does."""
    rng = np.random.default_rng(seed + 1)
    g = maps["grid"]
    wg = Grid.from_bounds(g.crs, *g.bounds, resolution_m=step_m)
    z = np.array([0.0, 40.0, 80.0, 160.0])
    speed = np.array([2.0, 4.0, 6.0, 9.0])[:, None, None] * rng.uniform(0.7, 1.0, (1, wg.ny, wg.nx))
    ang = rng.uniform(0, 2 * np.pi) + np.array([0.0, 0.3, 0.6, 0.9])[:, None, None] + rng.normal(0, 0.4, (1, wg.ny, wg.nx))
    u, v = speed * np.cos(ang), speed * np.sin(ang)
    dims = ("z", "y", "x")
    ds = xr.Dataset({"u": (dims, u), "v": (dims, v), "w": (dims, np.zeros_like(u))},
                    coords={"z": z, "y": wg.y, "x": wg.x}, attrs={"horizontal_step_m": step_m})
    return ds.rio.write_crs(g.crs)


def street_point(maps: dict, fx: float, fy: float) -> tuple[float, float]:
    """Map (x, y) [m] of the street crossing nearest the fraction (fx, fy) of the AOI, outside
    the no-fly discs."""
    g = maps["grid"]
    sx, sy = g.nx * g.resolution_m, g.ny * g.resolution_m
    best = None
    for k in range(40):
        for dx in range(-k, k + 1):
            for dy in (-k, k) if abs(dx) != k else range(-k, k + 1):
                ex = (round(fx * sx / PITCH_M) + dx) * PITCH_M + STREET_M / 2
                ey = (round(fy * sy / PITCH_M) + dy) * PITCH_M + STREET_M / 2
                if not (0 < ex < sx and 0 < ey < sy):
                    continue
                c, r = int(ex / g.resolution_m), g.ny - 1 - int(ey / g.resolution_m)
                if not maps["nofly"][r, c] and maps["clearance"][r, c] == 0:
                    best = (X0 + ex, Y0 + ey)
                    break
            if best:
                break
        if best:
            break
    return best


def city_problem(size_m: tuple[float, float], start_f: tuple[float, float], goal_f: tuple[float, float],
                 res_m: float = 2.0, seed: int = 0, alt_agl_m: float = 30.0, wind="map",
                 weights=(1.0, 1.0, 1.0, 1.0), maps: dict | None = None):
    """(PlanningProblem, maps) of a mission between the street crossings nearest the AOI
    fractions ``start_f`` and ``goal_f``, at ``alt_agl_m`` above the flat 0 m ground; ``wind``:
    ``"map"`` (:func:`city_wind`) or what ``build_problem`` takes."""
    maps = maps or city_maps(size_m, res_m, seed)
    g = maps["grid"]
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    ds = xr.Dataset({"terrain": t, "surface": t})
    s = street_point(maps, *start_f)
    e = street_point(maps, *goal_f)
    if isinstance(wind, str) and wind == "map":
        wind = city_wind(maps, seed)
    pr = build_problem(ds, maps["clearance"], None, maps["risk"], maps["landing"], wind, load_vehicle("dji-m300-rtk"),
                       weights, (*s, alt_agl_m), (*e, alt_agl_m), 0.0, MAX_AGL_M, None, nofly=maps["nofly"],
                       label="synthetic city")
    return pr, maps

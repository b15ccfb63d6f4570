"""Numerical potential field planner (seed 004 III-B): wave vs BFS / Dijkstra / scikit-fmm, no
local minima, conservative bitmap vs an exact prism oracle, incremental update vs a full
recompute, and an end-to-end plan whose brute-force clearance is >= r_p."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
import xarray as xr
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from skyroute.stages.clearance import clearance_floor
from skyroute.stages.grid import Grid
from skyroute.stages.planning import potential as P
from skyroute.stages.planning.potential_kernels import OFFS
from skyroute.stages.planning.problem import build_problem
from skyroute.stages.planning.step1 import plan_step1
from skyroute.stages.vehicle import load_vehicle

VEH = load_vehicle("dji-m300-rtk")
R_P = 5.0


def _random_free(rng, shape, p_blocked=0.3):
    return rng.random(shape) > p_blocked


def _box_free(free, a, dk, di, dj):
    """For flat source voxels ``a``: every voxel of the box spanned by the move is free (the
    wave's no-corner-cutting rule)."""
    k, i, j = np.unravel_index(a, free.shape)
    ok = np.ones(a.size, bool)
    for x in (0, 1):
        for y in (0, 1):
            for z in (0, 1):
                ok &= free[k + x * dk, i + y * di, j + z * dj]
    return ok


def _graph(free, steps, weight):
    """Independent 26-neighbour graph (scipy sparse) with the wave's edge costs."""
    nz, ny, nx = free.shape
    idx = np.arange(free.size).reshape(free.shape)
    rows, cols, vals = [], [], []
    w = weight.ravel()
    for o, (dk, di, dj) in enumerate(OFFS):
        a = idx[max(0, -dk):nz - max(0, dk), max(0, -di):ny - max(0, di), max(0, -dj):nx - max(0, dj)].ravel()
        b = idx[max(0, dk):nz + min(0, dk), max(0, di):ny + min(0, di), max(0, dj):nx + min(0, dj)].ravel()
        ok = _box_free(free, a, dk, di, dj)
        rows.append(a[ok])
        cols.append(b[ok])
        vals.append(steps[o] * 0.5 * (w[a[ok]] + w[b[ok]]))
    return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(free.size, free.size)).tocsr()


def _bfs(free, seed):
    nz, ny, nx = free.shape
    d = np.full(free.shape, np.inf)
    k0 = np.unravel_index(seed, free.shape)
    d[k0] = 0
    q = deque([k0])
    while q:
        k, i, j = q.popleft()
        for dk, di, dj in OFFS:
            n = (k + dk, i + di, j + dj)
            if (0 <= n[0] < nz and 0 <= n[1] < ny and 0 <= n[2] < nx and d[n] == np.inf
                    and all(free[k + x * dk, i + y * di, j + z * dj] for x in (0, 1) for y in (0, 1) for z in (0, 1))):
                d[n] = d[k, i, j] + 1
                q.append(n)
    return d


def _local_minima(U, free, goal_flat):
    """Free reached voxels (goal excluded) with no 26-neighbour of strictly lower U."""
    nz, ny, nx = U.shape
    pad = np.pad(np.where(free, U, np.inf), 1, constant_values=np.inf)
    best = np.full(U.shape, np.inf)
    for dk, di, dj in OFFS:
        best = np.minimum(best, pad[1 + dk:1 + dk + nz, 1 + di:1 + di + ny, 1 + dj:1 + dj + nx])
    bad = free & np.isfinite(U) & ~(best < U)
    bad.ravel()[goal_flat] = False
    return np.argwhere(bad)


@pytest.mark.parametrize("seed", range(4))
def test_wave_unit_steps_is_the_26_neighbour_bfs(seed):
    rng = np.random.default_rng(seed)
    free = _random_free(rng, (5, 9, 11), 0.45)
    s = int(rng.choice(np.flatnonzero(free)))
    U, parent = P.wave_propagation(free, [s])
    np.testing.assert_array_equal(U, _bfs(free, s))
    assert (parent[np.isfinite(U)] >= 0).sum() == np.isfinite(U).sum() - 1


@pytest.mark.parametrize("seed", range(4))
def test_wave_weighted_equals_scipy_dijkstra_and_has_no_local_minima(seed):
    rng = np.random.default_rng(10 + seed)
    free = _random_free(rng, (6, 10, 9), 0.35)
    steps = np.sqrt(((OFFS * np.array([1.3 * 2.5, 2.0, 2.0])) ** 2).sum(axis=1))   # anisotropic, vertical weight
    weight = np.where(rng.random(free.shape) < 0.3, 1.0, 8.0).astype(np.float32)
    s = int(rng.choice(np.flatnonzero(free)))
    U, _ = P.wave_propagation(free, [s], steps_m=steps, weight=weight)
    ref = dijkstra(_graph(free, steps, weight), indices=s).reshape(free.shape)
    np.testing.assert_allclose(U, ref, rtol=1e-12, atol=1e-9)
    assert _local_minima(U, free, s).size == 0


def test_wave_vs_scikit_fmm():
    """Euclidean 26-neighbour wave vs the eikonal solution (scikit-fmm, speed 1) around a box
    obstacle.  The 26-neighbour metric overestimates the Euclidean length of a free straight
    line by at most max over directions of chamfer/euclid = (computed below, ~1.13); FMM's own
    error near the source and the obstacle corners stays within 1.5 voxels."""
    skfmm = pytest.importorskip("skfmm")
    n, h = 40, 2.0
    free = np.ones((n, n, n), bool)
    free[10:30, 5:25, 18:22] = False          # a wall
    src = (20, 15, 5)
    steps = np.sqrt(((OFFS * h) ** 2).sum(axis=1))
    U, _ = P.wave_propagation(free, [np.ravel_multi_index(src, free.shape)], steps_m=steps)
    phi = np.ones(free.shape)
    phi[src] = -1.0
    phi = np.ma.MaskedArray(phi, ~free)
    try:
        T = skfmm.travel_time(phi, np.ones(free.shape), dx=h, order=2)
    except ValueError as exc:              # scikit-fmm's "negative discriminant" on some masks
        if "discriminant" not in str(exc):
            raise
        T = skfmm.travel_time(phi, np.ones(free.shape), dx=h, order=1)
    T = np.ma.filled(T, np.inf)
    g = np.array([(a, b, c) for a in range(30) for b in range(a + 1) for c in range(b + 1)][1:], float)
    chamfer = (g[:, 0] - g[:, 1]) + (g[:, 1] - g[:, 2]) * 2**0.5 + g[:, 2] * 3**0.5
    ratio = float((chamfer / np.linalg.norm(g, axis=1)).max())
    assert 1.12 < ratio < 1.14
    ok = free & np.isfinite(T)
    assert np.isfinite(U[ok]).all()
    assert np.all(U[ok] >= T[ok] - 1.5 * h)                     # never shorter than the geodesic
    assert np.all(U[ok] <= ratio * T[ok] + 1.5 * h)             # at most the metric's overestimate
    assert np.median(U[ok] / np.maximum(T[ok], h) - 1) < 0.10   # measured 0.080 here


# --------------------------------------------------------------------------- synthetic city


def _city(seed=0, nx=60, ny=40, res=2.0):
    rng = np.random.default_rng(seed)
    g = Grid.from_bounds("EPSG:32635", 0, 0, nx * res, ny * res, res)
    surf = np.zeros(g.shape)
    for _ in range(7):
        r, c = rng.integers(2, ny - 8), rng.integers(10, nx - 16)
        surf[r:r + rng.integers(3, 8), c:c + rng.integers(3, 10)] = rng.uniform(8, 30)
    t = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    ds = xr.Dataset({"terrain": t, "surface": g.dataarray(surf, "surface", units="m")})
    clear = clearance_floor(ds["surface"], R_P, "cell").values
    return g, ds, surf, clear


def _prism_distance(points, surf, res):
    """Brute force: least 3-D distance [m] from each point to the cells' prisms (closed boxes
    from -inf up to the surface height), independent of skyroute."""
    ny, nx = surf.shape
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    x0, x1 = (jj * res).ravel(), ((jj + 1) * res).ravel()
    y1 = (ny * res - ii * res).ravel()
    y0 = y1 - res
    top = surf.ravel()
    out = np.empty(len(points))
    for n, (x, y, z) in enumerate(points):
        dx = np.maximum(np.maximum(x0 - x, x - x1), 0)
        dy = np.maximum(np.maximum(y0 - y, y - y1), 0)
        dz = np.maximum(z - top, 0)
        out[n] = np.sqrt(dx * dx + dy * dy + dz * dz).min()
    return out


def _problem(ds, clear, start=(6.0, 40.0, 12.0), goal=(114.0, 40.0, 12.0), max_agl=40.0):
    return build_problem(ds, clear, None, 0.0, 0.0, (0, 0, 0), VEH, (1, 0, 0, 0), start, goal, 0.0, max_agl)


def test_bitmap_is_conservative_against_exact_prisms():
    g, ds, surf, clear = _city(1)
    pr = _problem(ds, clear)
    vm = P.occupancy_bitmap(pr, voxel_m=4.0, dz_m=1.5)
    assert vm.block == 2
    rng = np.random.default_rng(2)
    kij = np.argwhere(vm.free)
    kij = kij[rng.choice(len(kij), 1500, replace=False)]
    u = rng.random((len(kij), 3))
    u[:200] = np.round(u[:200])            # box corners and faces included (closed voxels)
    pts = np.stack([vm.x0_m + (kij[:, 2] + u[:, 0]) * vm.voxel_m, vm.y1_m - (kij[:, 1] + u[:, 1]) * vm.voxel_m,
                    vm.z0_m + (kij[:, 0] + u[:, 2]) * vm.dz_m], axis=1)
    d = _prism_distance(pts, surf, g.resolution_m)
    assert d.min() >= R_P - 1e-9
    assert pts[:, 2].max() <= 40.0 + 1e-9
    # strictly inside: also a valid state of the problem (its nearest-cell lookup)
    inner = (u > 1e-3).all(axis=1) & (u < 1 - 1e-3).all(axis=1)
    assert pr.state_valid(pts[inner]).all()
    # and not trivially: a good share of the voxels just above the floor are free
    assert vm.free.mean() > 0.5


def test_plan_end_to_end_keeps_the_exact_clearance_and_beats_astar_on_it():
    g, ds, surf, clear = _city(3)
    pr = _problem(ds, clear)
    r = P.plan_potential(pr)
    assert r["reason"] == "" and r["valid"]
    wp = r["waypoints"]
    assert np.allclose(wp[0], pr.start_xyz) and np.allclose(wp[-1], pr.goal_xyz)
    assert pr.path_costs(wp)["valid"]
    pf = r["field"]
    assert _local_minima(pf.potential_m, pf.vmap.free, np.ravel_multi_index(pf.goal, pf.vmap.shape)).size == 0
    # the gradient motion ends at the goal voxel
    assert r["voxel_path"][-1] == np.ravel_multi_index(pf.goal, pf.vmap.shape)
    t = np.linspace(0, 1, 60)[:, None]
    dense = np.concatenate([a + t * (b - a) for a, b in zip(wp[:-1], wp[1:], strict=True)])
    d = _prism_distance(dense, surf, g.resolution_m)
    assert d.min() >= R_P - 1e-9
    s1 = plan_step1(pr, planner="potential", time_budget_s=30.0)   # wall-clock caps: generous under load
    assert s1.solved and np.allclose(s1.waypoints, wp)
    a1 = plan_step1(pr, planner="astar", time_budget_s=30.0)
    da = _prism_distance(np.concatenate([a + t * (b - a) for a, b in zip(a1.waypoints[:-1], a1.waypoints[1:],
                                                                         strict=True)]), surf, g.resolution_m)
    assert d.mean() > da.mean()


def test_update_potential_equals_full_recompute():
    g, ds, surf, clear = _city(4)
    pr = _problem(ds, clear)
    vm = P.occupancy_bitmap(pr)
    s = P.entry_voxel(pr, vm, pr.start_xyz)
    gl = P.entry_voxel(pr, vm, pr.goal_xyz)
    pf = P.potential_field(vm, gl, [s], vertical_weight=2.0)
    free2 = vm.free.copy()
    free2[:14, 15:22, 28:33] = False            # a new building (or a dense traffic zone) mid-way
    obst2 = vm.obstacle.copy()
    obst2[:14, 15:22, 28:33] = True
    up = P.update_potential(pf, free2, obst2)
    vm2 = P.VoxelMap(vm.x0_m, vm.y1_m, vm.z0_m, vm.voxel_m, vm.dz_m, vm.block, free2, obst2, vm.floor_m, vm.ceiling_m)
    np.testing.assert_allclose(up.clearance_m, P.clearance_map(vm2), atol=1e-5)
    skel = P.skeleton(vm2, P.clearance_map(vm2))
    assert np.array_equal(up.skeleton & ~np.isin(np.arange(skel.size), up.connections).reshape(skel.shape), skel
                          & ~np.isin(np.arange(skel.size), up.connections).reshape(skel.shape))
    U, _ = P.wave_propagation(free2, [np.ravel_multi_index(gl, vm.shape)], steps_m=pf.steps_m,
                              weight=up.weight())
    np.testing.assert_allclose(up.potential_m, U, rtol=1e-12, atol=1e-9)
    assert not np.array_equal(U[np.isfinite(U)], pf.potential_m[np.isfinite(U)])   # the change mattered
    assert up.timings_s["affected_voxels"] < vm.free.sum()
    from skyroute.stages.base import InputError

    with pytest.raises(InputError, match="whole field"):
        P.update_potential(P.potential_field(vm, gl, [s], until=s), free2, obst2)


def test_minimum_jerk_closed_form():
    T = 4.0
    t = np.linspace(0, T, 401)
    p = P.minimum_jerk([0, 0, 0], [10, -4, 2], T, t)
    assert np.allclose(p[0], 0) and np.allclose(p[-1], [10, -4, 2])
    v = np.gradient(p[:, 0], t)
    assert abs(v[0]) < 1e-3 and abs(v[-1]) < 1e-3
    assert v.max() == pytest.approx(1.875 * 10 / T, rel=1e-3)    # peak speed 15/8 * distance / T


def test_errors_say_how_to_fix():
    from skyroute.stages.base import InputError

    g, ds, surf, clear = _city(0)
    pr = _problem(ds, clear)
    with pytest.raises(InputError, match="whole multiple"):
        P.occupancy_bitmap(pr, voxel_m=3.0)
    with pytest.raises(InputError, match="free voxel"):
        P.wave_propagation(np.zeros((2, 2, 2), bool), [0])


@pytest.mark.parametrize("shape", [(6, 12, 14), (14, 12, 6)])   # both memory layouts of the kernel
def test_wave_stopped_at_a_target_keeps_every_lower_value_exact(shape):
    rng = np.random.default_rng(7)
    free = _random_free(rng, shape, 0.3)
    s = int(np.flatnonzero(free)[0])
    steps = np.sqrt(((OFFS * np.array([2.0, 2.0, 2.0])) ** 2).sum(axis=1))
    full, _ = P.wave_propagation(free, [s], steps_m=steps)
    reach = np.flatnonzero(np.isfinite(full))
    t = int(reach[np.argsort(full.ravel()[reach])[reach.size // 2]])     # a voxel of median potential
    part, _ = P.wave_propagation(free, [s], steps_m=steps, target=t)
    assert np.isfinite(full.ravel()[t])
    fin = np.isfinite(part)
    np.testing.assert_allclose(part[fin], full[fin], rtol=1e-12)
    assert np.all(fin[full <= full.ravel()[t]])               # everything below the target is there
    assert fin.sum() < 0.8 * reach.size                        # and the wave did stop early
    assert _local_minima(part, free, s).size == 0


def test_potential_is_a_known_planner_everywhere():
    from skyroute.pipeline.settings import PLANNERS as SETTINGS_PLANNERS
    from skyroute.pipeline.settings import parse_planner
    from skyroute.stages.planning.step1 import PLANNERS

    assert "potential" in PLANNERS and "potential" in SETTINGS_PLANNERS
    assert parse_planner({"name": "potential"}).name == "potential"


def test_cropped_bitmap_is_the_same_voxels_as_the_whole_one():
    g, ds, surf, clear = _city(5)
    pr = _problem(ds, clear)
    full = P.occupancy_bitmap(pr)
    crop = P.occupancy_bitmap(pr, bounds_m=(21.0, 13.0, 77.0, 61.0))   # snapped outward to cells
    assert crop.x0_m == 20.0 and crop.y1_m == 62.0 and crop.shape[1:] == (25, 29)
    kz = np.round((crop.z - full.z0_m) / full.dz_m - 0.5).astype(int)   # same level centres
    assert np.allclose(full.z[kz], crop.z)
    i0, j0 = round((full.y1_m - crop.y1_m) / full.voxel_m), round((crop.x0_m - full.x0_m) / full.voxel_m)
    sub = full.free[kz][:, i0:i0 + crop.shape[1], j0:j0 + crop.shape[2]]
    np.testing.assert_array_equal(crop.free, sub)


@pytest.mark.parametrize("walls", [(True, True, True, True), (False, True, False, True), (False, False, False, False),
                                   (True, False, False, True)])
def test_compiled_edt_equals_scipy(walls):
    """The compiled separable EDT (with the AOI walls) against scipy's distance_transform_edt on
    the padded array, anisotropic voxels; sparse, dense and empty obstacle sets."""
    rng = np.random.default_rng(sum(walls))
    for shape, p in (((7, 19, 23), 0.03), ((4, 31, 9), 0.4), ((5, 6, 8), 0.0), ((1, 12, 12), 0.1)):
        ob = rng.random(shape) < p
        vm = P.VoxelMap(0.0, 0.0, 0.0, 2.0, 1.3, 1, ~ob, ob, np.zeros(shape[1:]), np.zeros(shape[1:]))
        a, b = P._edt(ob, vm, walls), P._edt_scipy(ob, vm, walls)
        assert a.dtype == np.float32 and a.shape == shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)


def test_ridge_kernel_against_numpy_definition():
    """The skeleton's ridge test against a numpy transcription of its definition: a free voxel
    with D >= min_d and, along one of the 13 lines, D >= both neighbours and > one of them
    (neighbours that are blocked or outside count as -1)."""
    rng = np.random.default_rng(5)
    for _ in range(12):
        sh = tuple(int(v) for v in rng.integers(1, 9, 3))
        free = rng.random(sh) > 0.3
        D = rng.integers(0, 4, sh).astype(np.float32)
        pad_d = np.pad(np.where(free, D, -1.0), 1, constant_values=-1.0)
        nz, ny, nx = sh
        c = pad_d[1:-1, 1:-1, 1:-1]
        want = np.zeros(sh, bool)
        for dk, di, dj in OFFS[:13]:
            a = pad_d[1 + dk:1 + dk + nz, 1 + di:1 + di + ny, 1 + dj:1 + dj + nx]
            b = pad_d[1 - dk:1 - dk + nz, 1 - di:1 - di + ny, 1 - dj:1 - dj + nx]
            want |= (c >= a) & (c >= b) & ((c > a) | (c > b))
        want &= free & (D >= 1.0)
        vm = P.VoxelMap(0.0, 0.0, 0.0, 1.0, 1.0, 1, free, ~free, np.zeros(sh[1:]), np.zeros(sh[1:]))
        assert np.array_equal(P.skeleton(vm, D, 1.0), want)


def _serial_wave(free, weight, steps, seeds, U=None, parent=None):
    """Independent plain-Python reference of the wave's values and parents: a serial Dijkstra
    with buckets of width q = the least edge cost, settled in increasing order, a bucket's
    voxels by increasing flat index, each relaxing its 26 neighbours in offset order, the first
    strict improvement setting the parent.  ``U`` / ``parent`` (flat): initial upper bounds
    and their parents (default: 0 at the seeds, inf elsewhere)."""
    shape = free.shape
    f, w = free.ravel(), weight.ravel().astype(np.float32)
    q = steps.min() * float(w[f].min())
    if U is None:
        U = np.full(free.size, np.inf)
        U[seeds] = 0.0
        parent = np.full(free.size, -1, np.int8)
    U, parent = U.copy(), parent.copy()
    settled = np.zeros(free.size, bool)
    buckets: dict[int, set] = {}
    for s in seeds:
        buckets.setdefault(int(np.floor(U[s] / q)), set()).add(int(s))
    while buckets:
        b = min(buckets)
        for v in sorted(buckets.pop(b)):
            if settled[v]:
                continue
            settled[v] = True
            k, i, j = np.unravel_index(v, shape)
            for o, (dk, di, dj) in enumerate(OFFS):
                n = (k + dk, i + di, j + dj)
                if not all(0 <= n[a] < shape[a] for a in range(3)):
                    continue
                u = int(np.ravel_multi_index(n, shape))
                if settled[u] or not all(free[k + x * dk, i + y * di, j + z * dj]
                                         for x in (0, 1) for y in (0, 1) for z in (0, 1)):
                    continue
                c = U[v] + steps[o] * 0.5 * (w[v] + w[u])
                if c < U[u]:
                    U[u] = c
                    parent[u] = 25 - o
                    buckets.setdefault(max(int(np.floor(c / q)), b + 1), set()).add(u)
    return U.reshape(shape), parent.reshape(shape)


@pytest.mark.parametrize("seed", range(6))
def test_wave_values_and_parents_equal_a_serial_bucket_dijkstra(seed):
    """Bit for bit, parents (tie rule) included, on bitmaps with inner voxels (fast path),
    border and obstacle voxels, unit steps (many ties) and the planner's anisotropic steps with
    skeleton-like weights 1 / 8 or continuous weights."""
    rng = np.random.default_rng(100 + seed)
    free = _random_free(rng, (11, 9, 8), 0.08 if seed % 2 else 0.25)
    seeds = rng.choice(np.flatnonzero(free), 1 + seed // 3, replace=False)
    if seed < 2:
        steps, weight = np.ones(26), np.ones(free.shape)
    else:       # two weights (the planner's; packed in the kernel's state byte) or many
        steps = np.linalg.norm(OFFS * np.array([2.0 * 3.73, 2.0, 2.0]), axis=1)
        weight = (np.where(rng.random(free.shape) < 0.2, 1.0, 8.0) if seed < 4
                  else rng.uniform(1.0, 5.0, free.shape))
    U, parent = P.wave_propagation(free, seeds, steps_m=steps, weight=weight)
    U0, parent0 = _serial_wave(free, weight, steps, seeds)
    np.testing.assert_array_equal(U, U0)
    np.testing.assert_array_equal(parent, parent0)



@pytest.mark.parametrize("seed", range(6))
def test_wave_from_upper_bounds_equals_the_serial_reference(seed):
    """The incremental update's use of the kernel: a whole field with a block reset to inf,
    many seeds at their values, the rest as upper bounds with their parents; values and
    parents bit for bit against the serial reference."""
    from skyroute.stages.planning.potential_kernels import wave_kernel

    rng = np.random.default_rng(200 + seed)
    free = _random_free(rng, (11, 9, 8), 0.1 if seed % 2 else 0.25)
    steps = np.ones(26) if seed < 2 else np.linalg.norm(OFFS * np.array([2.0 * 3.73, 2.0, 2.0]), axis=1)
    weight = np.ones(free.shape) if seed < 2 else np.where(rng.random(free.shape) < 0.2, 1.0, 8.0)
    g = int(rng.choice(np.flatnonzero(free)))
    U0, parent0 = P.wave_propagation(free, [g], steps_m=steps, weight=weight)
    U1, parent1 = U0.ravel().copy(), parent0.ravel().copy()
    U1[rng.random(free.size) < 0.3] = np.inf
    parent1[~np.isfinite(U1)] = -1
    fin = np.flatnonzero(np.isfinite(U1))
    seeds = rng.choice(fin, max(1, fin.size // 4), replace=False)
    U, parent = U1.copy(), parent1.copy()
    n = wave_kernel(free.ravel().view(np.uint8), weight.ravel().astype(np.float32), *free.shape, steps, seeds, U,
                    parent, np.zeros(1, np.int8))
    Ur, parentr = _serial_wave(free, weight, steps, seeds, U1, parent1)
    assert n > 0
    np.testing.assert_array_equal(U, Ur.ravel())
    np.testing.assert_array_equal(parent, parentr.ravel())
    assert (U <= U1).all() and (U >= U0.ravel()).all()     # only lowered, never below the true potential


@pytest.mark.parametrize("seed", range(3))
def test_affected_voxels_are_those_whose_parent_chain_meets_a_change(seed):
    """affected_kernel against walking every voxel's parent chain in Python."""
    from skyroute.stages.planning.potential_kernels import affected_kernel

    rng = np.random.default_rng(300 + seed)
    free = _random_free(rng, (7, 9, 10), 0.2)
    _, parent = P.wave_propagation(free, rng.choice(np.flatnonzero(free), 2, replace=False))
    changed = (rng.random(free.shape) < 0.03).astype(np.uint8)
    out = np.empty(free.size, np.uint8)
    affected_kernel(parent.ravel(), changed.ravel(), *free.shape, out)
    ref = np.zeros(free.size, np.uint8)
    for v in range(free.size):
        kij = np.array(np.unravel_index(v, free.shape))
        while True:
            if changed[tuple(kij)]:
                ref[v] = 1
                break
            p = parent[tuple(kij)]
            if p < 0:
                break
            kij = kij + OFFS[p]
    assert 0 < ref.sum() < free.size
    np.testing.assert_array_equal(out, ref)

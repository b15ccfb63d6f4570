"""The memoised DOP-floor kernel (``coverage._floor_epoch_kernel``) gives floors bit-identical to
the direct kernel it replaced (``coverage._reference_floor_epoch_kernel``, kept callable).

References: the direct kernel itself, on (1) property-generated columns (hypothesis: random
satellite sets and geometries, including singular ones, visibility heights with ties, +inf
and NaN, random thresholds and DOP kinds, running maxima already folded, strided views),
(2) a city of random towers whose columns overflow the kernel's memo, (3) the real coverage
inputs of two shipped scenarios (helsinki-medical: GPS + Galileo over the mission window,
the scenario's thresholds; Rotterdam-Delfshaven LoD2 with GPS), per epoch and through
``coverage_maps`` (numpy and dask runners).  Equality is ``np.array_equal`` (NaN where NaN),
never a tolerance.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skyroute.stages import coverage as cv
from skyroute.stages.dop import los_rows
from skyroute.stages.grid import Grid
from skyroute.stages.occlusion import visibility_heights_numpy
from skyroute.stages.orbits import epoch_directions

CATALOG_DATA = Path(__file__).resolve().parents[1] / "catalogs" / "data"


def both(h, g, thr, kind, out0):
    """(reference floors, memoised floors) folded into copies of ``out0``."""
    ref, new = out0.copy(), out0.copy()
    cv._reference_floor_epoch_kernel(h, g, thr, kind, ref)
    cv._floor_epoch_kernel(h, g, thr, kind, new)
    return ref, new


def assert_same(ref, new):
    assert ref.dtype == new.dtype
    bad = ~((ref == new) | (np.isnan(ref) & np.isnan(new)))
    assert not bad.any(), f"{int(bad.sum())} floors differ, e.g. {ref[bad][:4]} vs {new[bad][:4]}"
    assert np.array_equal(ref, new, equal_nan=True)


# ------------------------------------------------------------------------------------------
# (1) property-generated columns
# ------------------------------------------------------------------------------------------

@st.composite
def columns(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(0, 16))
    ny, nx = draw(st.integers(1, 7)), draw(st.integers(1, 7))
    geometry = draw(st.sampled_from(["random", "one_elevation", "duplicates", "planar"]))
    az = rng.uniform(0.0, 360.0, n)
    el = rng.uniform(5.0, 89.0, n)
    if geometry == "one_elevation":   # 4+ satellites on one cone: height and clock inseparable
        el[:] = el[0] if n else 0.0
    elif geometry == "duplicates" and n > 1:
        k = rng.integers(1, n)
        az[k:] = az[:n - k]
        el[k:] = el[:n - k]
    elif geometry == "planar" and n:
        el[: max(n - 1, 1)] = 30.0
    g = np.ascontiguousarray(los_rows(az, el))
    # heights: a few levels (ties = groups of satellites at one breakpoint), +inf, NaN
    n_levels = draw(st.integers(1, 6))
    levels = np.round(rng.uniform(0.0, 40.0, n_levels), draw(st.sampled_from([0, 1, 3])))
    pick = levels[rng.integers(0, n_levels, (n, ny, nx))]
    if draw(st.booleans()):   # a shared ground level: whole columns in one group
        ground = rng.random((ny, nx)) < 0.5
        pick = np.where(ground[None] & (rng.random((n, ny, nx)) < 0.8), levels.min(), pick)
    u = rng.random((n, ny, nx))
    p_inf, p_nan = draw(st.sampled_from([0.0, 0.1, 0.4])), draw(st.sampled_from([0.0, 0.1]))
    pick = np.where(u < p_inf, np.inf, pick)
    pick = np.where((u >= p_inf) & (u < p_inf + p_nan), np.nan, pick)
    h = pick.astype(np.float32)   # the visibility scan's dtype
    # the two signatures of the stage: the numpy runner (contiguous heights, float64 floors)
    # and the dask runner (the core of an overlapped block: a strided view, float32 floors)
    dask_like = draw(st.booleans())
    if dask_like:
        big = np.full((n, ny + 2, 2 * nx + 1), 7.0, np.float32)
        big[:, 1:ny + 1, 1::2] = h
        h = big[:, 1:ny + 1, 1::2]
    kind = draw(st.integers(0, 4))
    thr = np.unique(np.round(rng.uniform(0.6, 8.0, draw(st.integers(1, 4))), 2))
    if draw(st.booleans()) and n >= 4:   # thresholds at the DOP of some column exactly
        prof = cv.column_dop_profile(np.asarray(h[:, 0, 0], np.float64), az, el, mask_deg=0.0)
        vals = prof[cv.DOP_KINDS[kind]]
        vals = vals[np.isfinite(vals)]
        if vals.size:
            v = float(vals[rng.integers(0, vals.size)])
            thr = np.unique(np.r_[thr, v, np.nextafter(v, np.inf)])
    out_dtype = np.float32 if dask_like else np.float64
    if draw(st.booleans()):   # a running maximum already folded from earlier epochs
        out0 = rng.choice(np.r_[-np.inf, np.inf, levels], (thr.size, ny, nx)).astype(out_dtype)
    else:
        out0 = np.full((thr.size, ny, nx), -np.inf, out_dtype)
    return h, g, np.ascontiguousarray(thr, np.float64), kind, out0


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(columns())
def test_memoised_floors_equal_reference_on_random_columns(case):
    h, g, thr, kind, out0 = case
    assert_same(*both(h, g, thr, kind, out0))


def test_many_columns_overflow_the_memo_and_many_satellites():
    # continuous random heights: every breakpoint its own group, prefixes mostly distinct, so
    # the memo (cv._MEMO_NODES nodes) is cleared several times in one call; and more
    # satellites than a group mask holds (the direct kernel is used)
    rng = np.random.default_rng(3)
    n, ny, nx = 16, 120, 160
    g = np.ascontiguousarray(los_rows(rng.uniform(0, 360, n), rng.uniform(5, 85, n)))
    h = rng.uniform(0.0, 30.0, (n, ny, nx)).astype(np.float32)
    h[:, ::7] = 2.0   # some open-sky rows
    thr = np.array([1.5, 2.0, 3.0, 6.0])
    for kind in range(5):
        assert_same(*both(h, g, thr, kind, np.full((thr.size, ny, nx), -np.inf)))
    n = cv._MEMO_MAX_SAT + 2
    g = np.ascontiguousarray(los_rows(rng.uniform(0, 360, n), rng.uniform(5, 85, n)))
    h = np.round(rng.uniform(0.0, 30.0, (n, 9, 11)), 0).astype(np.float32)
    assert_same(*both(h, g, np.array([1.0, 1.5]), 1, np.full((2, 9, 11), -np.inf)))


def test_towers_city_through_the_scan():
    # a random city of towers, the real visibility scan, 12 satellites, every epoch folded
    rng = np.random.default_rng(11)
    surf = np.zeros((90, 110), np.float32)
    for _ in range(60):
        i, j = rng.integers(0, 80, 2)
        surf[i:i + rng.integers(2, 10), j:j + rng.integers(2, 10)] = rng.uniform(5, 60)
    thr = np.array([2.0, 3.0, 4.0])
    ref = np.full((3,) + surf.shape, -np.inf)
    new = ref.copy()
    for _ in range(4):
        az, el = rng.uniform(0, 360, 12), rng.uniform(8, 80, 12)
        h = np.ascontiguousarray(visibility_heights_numpy(surf, az, el, 2.0))
        g = np.ascontiguousarray(los_rows(az, el))
        cv._reference_floor_epoch_kernel(h, g, thr, 1, ref)
        cv._floor_epoch_kernel(h, g, thr, 1, new)
    assert np.isfinite(ref).mean() > 0.5   # a meaningful comparison, not all "never"
    assert_same(ref, new)


# ------------------------------------------------------------------------------------------
# (3) shipped scenarios: their real coverage inputs
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def helsinki_inputs(tmp_path_factory):
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario

    sc = load_scenario("helsinki-medical")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # an unhealthy PRN excluded
        res = run_scenario(sc, cache=Cache(tmp_path_factory.mktemp("cache")),
                           targets=["surface", "satellites"])
        surface = res["surface"]["surface"].load()
        sat = res["satellites"].load()
    return surface, sat, sc


def _floors_per_epoch(surf, az, el, thr, kind, mask):
    s2 = np.ascontiguousarray(surf.values, np.float32)
    cell = Grid.from_dataarray(surf).resolution_m
    ref = np.full((thr.size,) + s2.shape, -np.inf)
    new = ref.copy()
    for a, e in epoch_directions(cv._grid_azimuth(az, surf), el, mask):
        h = np.ascontiguousarray(visibility_heights_numpy(s2, a, e, cell))
        g = np.ascontiguousarray(los_rows(a, e))
        cv._reference_floor_epoch_kernel(h, g, thr, kind, ref)
        cv._floor_epoch_kernel(h, g, thr, kind, new)
    return ref, new


def test_helsinki_medical_real_inputs(helsinki_inputs, monkeypatch):
    surface, sat, sc = helsinki_inputs
    thr = np.unique(np.asarray(sc.gnss.dop_thresholds, float))
    kind = cv.dop_kind_index(sc.gnss.dop_kind)
    mask = sc.gnss.elevation_mask_deg
    az, el = sat["az_deg"].values, sat["el_deg"].values
    crop = surface.isel(y=slice(300, 480), x=slice(150, 330))
    ref, new = _floors_per_epoch(crop, az, el, thr, kind, mask)
    assert az.shape[0] >= 5 and np.isfinite(ref).any()
    assert_same(ref, new)
    # the stage's public function, numpy and dask runners (cores of overlapped blocks):
    # memoised kernel vs the reference patched in
    kw = dict(thresholds=sc.gnss.dop_thresholds, dop=sc.gnss.dop_kind, mask_deg=mask)
    got = [cv.coverage_maps(crop, az, el, **kw)["coverage_floor"].values,
           cv.coverage_maps(crop, az, el, chunks=70, **kw)["coverage_floor"].values]
    monkeypatch.setattr(cv, "_floor_epoch_kernel", cv._reference_floor_epoch_kernel)
    want = cv.coverage_maps(crop, az, el, **kw)["coverage_floor"].values
    for arr in got:
        assert np.array_equal(arr, want, equal_nan=True)


def test_rotterdam_lod2_real_inputs():
    from skyroute.stages.almanac import sky_geometry
    from skyroute.stages.surface import build_surface

    city = CATALOG_DATA / "rotterdam_delfshaven_lod2.city.json"
    if not city.is_file():
        pytest.skip(f"{city} missing")
    grid = Grid.from_bounds("EPSG:28992", 91100.0, 435700.0, 91400.0, 435940.0, 2.0)
    surf = build_surface(grid, buildings_path=city, buildings_format="cityjson")["surface"]
    lon, lat = grid.to_lonlat(91250.0, 435820.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        sky = sky_geometry(CATALOG_DATA / "yuma_2020-01-03.txt",
                           cv.window_times("2020-01-03T08:00", window_min=10.0), lat, lon, 0.0)
    thr = np.array([2.0, 2.5, 3.0, 4.0, 6.0])
    for kind in (1, 2):   # PDOP, HDOP
        ref, new = _floors_per_epoch(surf, sky["az_deg"].values, sky["el_deg"].values, thr,
                                     kind, 5.0)
        assert np.isfinite(ref).any()
        assert_same(ref, new)

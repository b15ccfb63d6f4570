"""One DOP convention and one DOP algebra (skyroute.stages.dop), and the overlapped-block runner
(skyroute.stages.overlap) shared by occlusion and coverage.

References: a numpy brute force ``inv(G^T G)`` of the geometry matrix; scipy's maximum filter
on the whole array for the overlapped blocks.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import dask.array as da
import numpy as np
import pytest
import xarray as xr

from skyroute.stages import coverage as cv
from skyroute.stages.dop import DOP_KINDS, dop, dop_table
from skyroute.stages.grid import Grid

CATALOG_DATA = Path(__file__).resolve().parents[1] / "catalogs" / "data"


def brute_dop(az_deg: np.ndarray, el_deg: np.ndarray) -> np.ndarray:
    """(5,) GDOP..TDOP from ``numpy.linalg.inv(G^T G)``, rows [-e, -n, -u, 1] (seed 003)."""
    az, el = np.deg2rad(az_deg), np.deg2rad(el_deg)
    g = np.stack([-np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), -np.sin(el),
                  np.ones_like(az)], axis=1)
    q = np.diag(np.linalg.inv(g.T @ g))
    return np.sqrt([q.sum(), q[:3].sum(), q[:2].sum(), q[2], q[3]])


def flat(n: int = 6) -> xr.DataArray:
    g = Grid.from_bounds("EPSG:32631", 600000.0, 5700000.0, 600000.0 + 2 * n, 5700000.0 + 2 * n, 2.0)
    return g.dataarray(np.full(g.shape, 3.0, np.float32), "surface", units="m",
                       vertical_datum="EGM96")


def all_paths(az: np.ndarray, el: np.ndarray) -> dict[str, np.ndarray]:
    """(5,) DOPs of one epoch from every public path: the dop module (numpy and xarray) and
    the coverage module (open sky, column profile, a section above a flat surface)."""
    ds = dop(xr.DataArray(az[None], dims=("time", "sat")),
             xr.DataArray(el[None], dims=("time", "sat")), axis="sat")
    prof = cv.column_dop_profile(np.zeros(az.size), az, el, mask_deg=0.0)
    sec = cv.dop_section(flat(), az[None], el[None], [10.0], mask_deg=0.0)
    return {
        "dop": np.array([dop(az, el)[k.lower()] for k in DOP_KINDS]),
        "dop_xarray": np.array([float(ds[k.lower()][0]) for k in DOP_KINDS]),
        "open_sky_dop": cv.open_sky_dop(az[None], el[None], mask_deg=0.0)[0],
        "column_dop_profile": np.array([prof[k][-1] for k in DOP_KINDS]),
        "dop_section": np.array([float(sec[k.lower()].values[0, 0, 2, 3]) for k in DOP_KINDS]),
    }


def test_no_fix_is_inf_in_every_path():
    """3 satellites, and 4 at one elevation (height and clock inseparable): +inf everywhere,
    never NaN; coverage: every cell unflyable; NaN only below the surface (no data)."""
    three = (np.array([10.0, 130.0, 250.0]), np.array([20.0, 45.0, 70.0]))
    ring = (np.array([0.0, 90.0, 180.0, 270.0]), np.full(4, 10.0))
    for az, el in (three, ring):
        for path, v in all_paths(az, el).items():
            assert np.all(np.isposinf(v)), (path, az.size, v)
        ds = cv.coverage_maps(flat(), az[None], el[None], thresholds=(6.0,), mask_deg=0.0)
        assert ds["unflyable"].values.all() and np.isposinf(ds["open_sky_dop"].values).all()
    sec = cv.dop_section(flat(), three[0][None], three[1][None], [1.0, 10.0], mask_deg=0.0)
    assert np.isnan(sec["pdop"].values[0, 0]).all()      # 1 m: below the 3 m surface
    assert np.isposinf(sec["pdop"].values[0, 1]).all()   # 10 m: 3 satellites, no fix
    # a NaN satellite is absent, not "no fix": 3 + 1 NaN is still 3 satellites
    got = dop_table(np.r_[three[0], np.nan], np.r_[three[1], 30.0])
    assert np.isposinf(got).all()


def test_both_paths_identical_and_match_brute_force():
    """4..20 satellites: every path gives the same DOP bit for bit (the float32 section to
    float32 rounding), within 1e-9 of inv(G^T G)."""
    rng = np.random.default_rng(21)
    for n in (4, 5, 7, 12, 20):
        for _ in range(4):
            az = rng.uniform(0, 360, n)
            el = rng.uniform(5, 89, n)
            got = all_paths(az, el)
            ref = brute_dop(az, el)
            assert np.all(np.isfinite(got["dop"]))
            np.testing.assert_allclose(got["dop"], ref, rtol=1e-9)
            for path in ("dop_xarray", "open_sky_dop", "column_dop_profile"):
                np.testing.assert_array_equal(got[path], got["dop"], err_msg=path)
            np.testing.assert_array_equal(got["dop_section"],
                                          got["dop"].astype(np.float32).astype(np.float64))


def test_satellites_stage_and_sky_cli_no_fix():
    """sky_geometry (the satellites stage): +inf exactly where fewer than 4 satellites are
    above the mask; ``skyroute sky`` says "no fix" (JSON: null)."""
    from click.testing import CliRunner

    from skyroute.pipeline.cli_gnss import sky_command
    from skyroute.stages.almanac import sky_geometry
    from skyroute.stages.orbits import window_times

    alm = CATALOG_DATA / "yuma_2020-01-03.txt"
    t = window_times("2020-01-03T00:00", window_min=600.0, step_min=30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        ds = sky_geometry(alm, t, 60.17, 24.94, 0.0, mask_deg=45.0)
    few = ds["n_visible"].values < 4
    assert few.any() and (~few).any()
    for k in ("gdop", "pdop", "hdop", "vdop", "tdop"):
        v = ds[k].values
        assert np.isposinf(v[few]).all() and np.isfinite(v[~few]).all(), k
    k = int(np.flatnonzero(few)[0])
    args = ["--almanac", str(alm), "--time", str(t[k]) + "Z", "--lat", "60.17", "--lon", "24.94",
            "--mask-deg", "45"]
    res = CliRunner().invoke(sky_command, [*args, "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output[res.output.index("{"):])
    assert doc["n_visible"] < 4 and all(v is None for v in doc["dop"].values())
    res = CliRunner().invoke(sky_command, args)
    assert res.exit_code == 0 and "no fix" in res.output


@pytest.mark.parametrize("chunks", [(5, 7), (13, 40), (40, 3), (64, 64)])
def test_overlap_map_equals_whole_array(chunks):
    """A running max over a (2 d + 1)^2 window needs a halo of d cells: overlapped blocks
    (too-small blocks merged) give scipy's filter on the whole array exactly."""
    from scipy.ndimage import maximum_filter

    from skyroute.stages.overlap import ensure_min_chunks, overlap_map

    rng = np.random.default_rng(1)
    a = rng.uniform(0, 100, (64, 80))
    d = 9
    arr = da.from_array(a, chunks=chunks)
    merged, dy, dx = ensure_min_chunks(arr, d)
    for c, h in zip(merged.chunks, (dy, dx), strict=True):
        assert (len(c) == 1 and h == 0) or (min(c) >= d and h == d)
    origins = []

    def fn(block, origin, core):
        origins.append(origin)
        return maximum_filter(block, size=2 * d + 1, mode="constant", cval=-np.inf)[core][None]

    got = overlap_map(arr, d, fn, ((1,),), np.float64).compute(scheduler="sync")
    ref = maximum_filter(a, size=2 * d + 1, mode="constant", cval=-np.inf)
    np.testing.assert_array_equal(got[0], ref)
    assert (0, 0) in origins and all(r >= 0 and c >= 0 for r, c in origins)

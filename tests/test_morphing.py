"""Digital morphing map (stages/morphing.py): the coverage floor per epoch and its animation.

References: the window floor of stages/coverage.py (max over epochs, exact identity), the
closed-form shadow of a wall (h - d tan(el)) with DOPs from an independent numpy inversion,
and the DOP volume (DOP < D exactly above the floor)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from skyroute.stages import coverage as cv
from skyroute.stages.base import InputError
from skyroute.stages.grid import Grid
from skyroute.stages.morphing import (
    animate_floor,
    coverage_floor_series,
    epoch_sky,
    floor_under_vehicle,
)

CATALOG_DATA = Path(__file__).resolve().parents[1] / "catalogs" / "data"


def _sky(az: np.ndarray, el: np.ndarray, step_s: float = 60.0) -> xr.Dataset:
    t = np.datetime64("2020-01-03T08:00:00", "ns") + (np.arange(az.shape[0]) * step_s * 1e9).astype(
        "timedelta64[ns]")
    return xr.Dataset({"az_deg": (("time", "sat"), az), "el_deg": (("time", "sat"), el)},
                      coords={"time": t, "sat": [f"S{i:02d}" for i in range(az.shape[1])]})


def _yuma_sky(surf: xr.DataArray, window_min: float = 10.0) -> xr.Dataset:
    from skyroute.stages.almanac import sky_geometry

    g = Grid.from_dataarray(surf)
    xmin, ymin, xmax, ymax = g.bounds
    lon, lat = g.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # one unhealthy PRN excluded
        return sky_geometry(CATALOG_DATA / "yuma_2020-01-03.txt",
                            cv.window_times("2020-01-03T08:00", window_min), lat, lon, 0.0)


def _towers(seed: int = 3, n: int = 60) -> xr.DataArray:
    """Synthetic downtown: 2 m cells, towers 10..120 m on flat ground."""
    rng = np.random.default_rng(seed)
    h = np.zeros((n, n), np.float32)
    for _ in range(14):
        w, length = rng.integers(2, 9, 2)
        i, j = rng.integers(0, n - 9, 2)
        h[i:i + w, j:j + length] = max(float(h[i:i + w, j:j + length].max()), rng.uniform(10, 120))
    g = Grid.from_bounds("EPSG:28992", 91100.0, 435700.0, 91100.0 + 2 * n, 435700.0 + 2 * n, 2.0)
    return g.dataarray(h, "surface", units="m", vertical_datum="NAP")


def _assert_identity(series: xr.Dataset, window: xr.Dataset) -> None:
    fmax = series["coverage_floor"].max("time", skipna=False).transpose("threshold", "y", "x")
    assert np.array_equal(fmax.values, window["coverage_floor"].values, equal_nan=True)
    assert np.array_equal(series["unflyable"].any("time").transpose("threshold", "y", "x").values,
                          window["unflyable"].values)


# ------------------------------------------------------------------------------------------
# the window floor is the max over epochs of the per-epoch floors (exact)
# ------------------------------------------------------------------------------------------

def test_max_over_epochs_is_the_window_floor_towers():
    surf = _towers()
    sky = _yuma_sky(surf)
    rng = np.random.default_rng(1)
    floor_m = surf + rng.uniform(0, 20, surf.shape).astype(np.float32)  # raster limits too
    kw = dict(thresholds=(2.5, 3.0, 4.0, 6.0), floor_m=floor_m, ceiling_m=95.0)
    window = cv.coverage_maps(surf, sky["az_deg"], sky["el_deg"], **kw)
    series = coverage_floor_series(surf, sky, **kw)
    assert isinstance(series["coverage_floor"].data, type(series["unflyable"].data))  # lazy
    assert series["coverage_floor"].chunks[0] == (1,) * sky.sizes["time"]
    series = series.load()
    _assert_identity(series, window)
    # the floor does change with time (otherwise the identity would be trivial)
    f = series["coverage_floor"].values
    moved = np.nanmax(np.abs(f - f[:1]), axis=(1, 2, 3))
    assert moved.max() > 5.0
    assert series["unflyable"].values.any() and not series["unflyable"].values.all()
    # per epoch: the floor respects the limits
    ok = np.isfinite(f)
    lim = np.broadcast_to(floor_m.values, f.shape)
    assert np.all(f[ok] >= lim[ok]) and np.all(f[ok] <= 95.0)


def test_max_over_epochs_is_the_window_floor_rotterdam_blocks(tmp_path):
    # a real shipped map (Rotterdam LoD2 CityJSON), computed in 4 overlapped blocks, written
    # to zarr lazily and read back
    from skyroute.stages.surface import build_surface

    g = Grid.from_bounds("EPSG:28992", 91100.0, 435700.0, 91300.0, 435880.0, 2.0)
    surf = build_surface(g, buildings_path=CATALOG_DATA / "rotterdam_delfshaven_lod2.city.json",
                         buildings_format="cityjson")["surface"]
    sky = _yuma_sky(surf)
    thr = (2.0, 3.0, 4.0)
    # a 25 deg mask keeps the shadow halo (~27 cells) below the block size
    window = cv.coverage_maps(surf, sky["az_deg"], sky["el_deg"], thresholds=thr, mask_deg=25.0)
    series = coverage_floor_series(surf, sky, thr, chunks=(48, 52), mask_deg=25.0)
    assert len(series["coverage_floor"].chunks[2]) == 2
    assert len(series["coverage_floor"].chunks[3]) == 2
    assert series.rio.crs == surf.rio.crs
    series.to_zarr(tmp_path / "floor.zarr", mode="w", consolidated=False)
    back = xr.open_zarr(tmp_path / "floor.zarr", consolidated=False).load()
    _assert_identity(back, window)
    assert back["coverage_floor"].attrs["units"] == "m"
    assert np.array_equal(back["t_s"].values, np.arange(11) * 60.0)


# ------------------------------------------------------------------------------------------
# closed form: one wall, four fixed satellites on its far side and one moving in elevation
# ------------------------------------------------------------------------------------------

WALL_COL, WALL_H, CELL = 10, 40.0, 2.0
FIXED = [(90.0, 75.0), (30.0, 35.0), (150.0, 35.0), (90.0, 15.0)]  # (az, el) [deg], east side


def _ref_pdop(azel: list[tuple[float, float]]) -> float:
    a = np.radians([p[0] for p in azel])
    e = np.radians([p[1] for p in azel])
    g = np.c_[np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e), np.ones(a.size)]
    q = np.linalg.inv(g.T @ g)
    return float(math.sqrt(q[0, 0] + q[1, 1] + q[2, 2]))


def _wall_case(els=(15.0, 22.0, 30.0, 40.0, 50.0, 62.0)):
    # UTM 31N centred on its central meridian: grid azimuth = true azimuth
    g = Grid.from_bounds("EPSG:32631", 500000.0 - 60, 5700000.0, 500000.0 + 60, 5700040.0, CELL)
    h = np.zeros(g.shape, np.float32)
    h[:, WALL_COL] = WALL_H
    surf = g.dataarray(h, "surface", units="m", vertical_datum="EGM96")
    n = len(els)
    az = np.array([[p[0] for p in FIXED] + [270.0]] * n)
    el = np.array([[p[1] for p in FIXED] + [e] for e in els])
    return surf, _sky(az, el), np.asarray(els)


def test_floor_behind_a_wall_follows_h_minus_d_tan_el():
    surf, sky, els = _wall_case()
    p4 = _ref_pdop(FIXED)
    p5 = [_ref_pdop(FIXED + [(270.0, e)]) for e in els]
    assert max(p5) < p4  # D between them: the floor is where the moving satellite appears
    d = 0.5 * (max(p5) + p4)
    series = coverage_floor_series(surf, sky, (d,)).load()
    f = series["coverage_floor"].values[:, 0]
    row = surf.shape[0] // 2
    for t, e in enumerate(els):
        for k in (1, 2, 5, 9, 20, 35):
            # the nearest point of cell WALL_COL + k is (k - 1) cells from the wall's east face
            exp = max(WALL_H - (k - 1) * CELL * math.tan(math.radians(e)), 0.0)
            assert f[t, row, WALL_COL + k] == pytest.approx(exp, abs=0.01), (e, k)
    # below the moving satellite's shadow edge the floor is the ground; the whole map moves
    assert np.all(np.diff(f[:, row, WALL_COL + 5]) < 0)


def test_dop_volume_is_below_d_exactly_above_the_floor():
    surf, sky, els = _wall_case()
    levels = [0.0, 5.0, 12.5, 20.0, 30.0, 45.0]
    d = 0.5 * (max(_ref_pdop(FIXED + [(270.0, e)]) for e in els) + _ref_pdop(FIXED))
    s = coverage_floor_series(surf, sky, (d, 6.0), levels_m=levels).load()
    vol = s["dop_volume"].values  # (time, z, y, x)
    ref = cv.dop_volume(surf, sky["az_deg"], sky["el_deg"], levels, reduce=None).values
    assert np.array_equal(vol, ref, equal_nan=True)  # the section kernel, same visibility
    floor = s["coverage_floor"].values[:, 0]  # (time, y, x)
    z = np.asarray(levels)[None, :, None, None]
    above_ground = z >= surf.values[None, None]
    below_d = vol < d
    expect = z >= floor[:, None]  # NaN floor: never
    assert np.array_equal(below_d[np.broadcast_to(above_ground, vol.shape)],
                          expect[np.broadcast_to(above_ground, vol.shape)])
    # open sky away from the wall: the 5-satellite PDOP of the independent reference
    assert vol[2, 0, 5, 50] == pytest.approx(_ref_pdop(FIXED + [(270.0, els[2])]), rel=1e-5)


# ------------------------------------------------------------------------------------------
# epochs and the vehicle
# ------------------------------------------------------------------------------------------

def test_epoch_sky_interpolates_and_refuses_extrapolation():
    az = np.array([[350.0, 100.0, np.nan], [10.0, 110.0, 40.0]])
    el = np.array([[20.0, 50.0, np.nan], [30.0, 40.0, 10.0]])
    sky = _sky(az, el)
    ep = epoch_sky(sky, [0.0, 15.0, 60.0])
    assert np.array_equal(ep["az_deg"].values[[0, 2]], az, equal_nan=True)
    assert ep["az_deg"].values[1, 0] == pytest.approx(355.0)  # the short way round north
    assert ep["el_deg"].values[1, :2] == pytest.approx([22.5, 47.5])
    assert np.isnan(ep["el_deg"].values[1, 2])  # absent at a neighbour: absent
    assert ep["t_s"].values.tolist() == [0.0, 15.0, 60.0]
    same = epoch_sky(sky, sky["time"].values)
    assert np.array_equal(same["el_deg"].values, el, equal_nan=True)
    with pytest.raises(InputError, match="span of sky"):
        epoch_sky(sky, [61.0])
    one = epoch_sky(sky.isel(time=[1]), [0.0])  # a single epoch
    assert np.array_equal(one["az_deg"].values[0], az[1])


def test_floor_under_vehicle():
    surf, sky, els = _wall_case()
    d = 0.5 * (max(_ref_pdop(FIXED + [(270.0, e)]) for e in els) + _ref_pdop(FIXED))
    s = coverage_floor_series(surf, sky, (d,))
    # the vehicle flies east along the middle row at 30 m, over the epochs 60..240 s
    x0 = float(surf["x"].values[WALL_COL + 3])
    y0 = float(surf["y"].values[10])
    t = np.array([60.0, 240.0])
    xyz = np.array([[x0, y0, 30.0], [x0 + 60.0, y0, 30.0]])
    u = floor_under_vehicle(s, d, t, xyz)
    assert u["t_s"].values.tolist() == [60.0, 120.0, 180.0, 240.0]
    cols = WALL_COL + 3 + np.array([0, 10, 20, 30])
    exp = [max(WALL_H - (c - WALL_COL - 1) * CELL * math.tan(math.radians(e)), 0.0)
           for c, e in zip(cols, els[1:5], strict=True)]
    assert u["floor_m"].values == pytest.approx(exp, abs=0.01)
    assert u["margin_m"].values == pytest.approx(30.0 - np.asarray(exp), abs=0.01)


# ------------------------------------------------------------------------------------------
# the animation
# ------------------------------------------------------------------------------------------

def test_animation_gif_frames(tmp_path):
    from PIL import Image, ImageSequence

    surf, sky, els = _wall_case()
    s = coverage_floor_series(surf, sky, (3.0, 6.0), times=np.arange(0.0, 301.0, 30.0))
    t = np.array([0.0, 300.0])
    xs = surf["x"].values
    xyz = np.array([[xs[WALL_COL + 2], 5700030.0, 25.0], [xs[-3], 5700010.0, 35.0]])
    out = animate_floor(s, 6.0, t, xyz, tmp_path / "floor.gif", max_frames=5, dpi=60,
                        frame_png=tmp_path / "frame.png")
    assert out.stat().st_size < 400_000
    with Image.open(out) as im:
        assert im.n_frames == 5  # 11 epochs in the flight, subsampled to 5
        frames = [np.asarray(f.convert("RGB"), dtype=np.int16) for f in ImageSequence.Iterator(im)]
    # the map is drawn: pixels of the viridis colour bands cover a good part of every frame,
    # and the floor map itself changes from frame to frame (the satellite rises)
    import matplotlib

    pal = matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255

    def on_map(f):  # a GIF frame has at most 256 colours: compare those with the palette
        colours, inv = np.unique(f.reshape(-1, 3), axis=0, return_inverse=True)
        d2 = ((colours[:, None, :] - pal[None, :, :]) ** 2).sum(-1).min(1)
        return (d2 < 15.0 ** 2)[inv.ravel()].reshape(f.shape[:2])

    masks = [on_map(f) for f in frames]
    for f, m in zip(frames, masks, strict=True):
        assert m.mean() > 0.08, m.mean()
        assert len(np.unique(f[m], axis=0)) >= 5  # several colour bands
    for (a, ma), (b, mb) in zip(zip(frames, masks, strict=True), list(zip(frames, masks, strict=True))[1:],
                                strict=False):
        changed = ma & mb & (np.abs(a - b).sum(-1) > 30)
        assert changed.mean() > 0.005, changed.mean()
    with Image.open(tmp_path / "frame.png") as png:
        assert png.size == frames[0].shape[1::-1]
    with pytest.raises(InputError, match="no epoch"):
        animate_floor(s, 6.0, t + 1000.0, xyz, tmp_path / "x.gif")
    with pytest.raises(InputError, match="not in the series"):
        animate_floor(s, 4.0, t, xyz, tmp_path / "x.gif")


def test_messages_say_how_to_fix():
    surf, sky, _ = _wall_case()
    with pytest.raises(InputError, match="can never be reached"):
        coverage_floor_series(surf, sky, (1.0,))
    with pytest.raises(InputError, match="az_deg and el_deg"):
        coverage_floor_series(surf, sky.drop_vars("el_deg"), (3.0,))
    s = coverage_floor_series(surf, sky, (3.0,))
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        floor_under_vehicle(s, 3.0, [0.0, 60.0], [[0.0, 0.0], [1.0, 1.0]])
    with pytest.raises(InputError, match="strictly increasing"):
        floor_under_vehicle(s, 3.0, [60.0, 0.0], np.zeros((2, 3)))


def test_region_equals_the_whole_map_cut():
    # seed 003's control volume: a box of the map, computed with the halo, is the whole map's
    # series cut to the box (values bit-identical), also at the map edge
    surf = _towers()
    sky = _yuma_sky(surf, window_min=4.0)
    floor_m = surf + np.float32(3.0)
    kw = dict(thresholds=(3.0, 5.0), floor_m=floor_m, ceiling_m=100.0, levels_m=[20.0, 60.0])
    full = coverage_floor_series(surf, sky, **kw).load()
    x, y = surf["x"].values, surf["y"].values
    for box, (rs, cs) in [((x[20] - 1, y[40] - 1, x[35] + 1, y[25] + 1), (slice(25, 41), slice(20, 36))),
                          ((x[0] - 50, y[-1] - 50, x[9] + 1, y[50] + 1), (slice(50, 60), slice(0, 10)))]:
        part = coverage_floor_series(surf, sky, region_m=box, **kw).load()
        cut = full.isel(y=rs, x=cs)
        assert part.sizes["y"] == rs.stop - rs.start and part.sizes["x"] == cs.stop - cs.start
        for name in ("coverage_floor", "unflyable", "dop_volume"):
            assert np.array_equal(part[name].values, cut[name].values, equal_nan=True), name
        assert np.array_equal(part["x"].values, cut["x"].values)
    f = full["coverage_floor"].values
    assert np.nanmax(np.abs(f - f[:1])) > 5.0  # epochs differ: no task was shared by mistake
    with pytest.raises(InputError, match="does not overlap"):
        coverage_floor_series(surf, sky, (3.0,), region_m=(0.0, 0.0, 10.0, 10.0))

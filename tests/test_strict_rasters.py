"""Geodata read strictly (issue 34): DSM / DEM rasters whose header says something the reader
used to ignore or misread -- a vertical unit in feet, rows stored bottom-up, GCP-only
georeferencing, a truncated or corrupt file, a folder / FIFO / device, heights that are no heights,
a window larger than ``--max-memory`` -- are converted and read right, or refused with one clear
error naming the file and the fix, the same in ``skyroute inspect`` and in the stages."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pyproj
import pytest
import rasterio
import rasterio.windows
import yaml
from affine import Affine
from click.testing import CliRunner
from pyproj import CRS

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import DataError, InputError, ScenarioError
from skyroute.pipeline.settings import catalog_dir, load_scenario
from skyroute.stages.grid import Grid, read_window, read_window_holes
from skyroute.stages.surface import dsm_on_grid, terrain_from_dem

US_FT = 1200.0 / 3937.0            # US survey foot [m], by definition
FT = 0.3048                        # international foot [m]
X0, Y1, PX = 383000.0, 3797000.0, 10.0    # top-left corner [m] (EPSG:32611) and pixel side [m]
N = 40                                    # pixels per side of the small rasters
UTM11 = CRS.from_epsg(32611)


def _heights(n: int = N) -> np.ndarray:
    rng = np.random.default_rng(34)
    return (300.0 + 50.0 * rng.random((n, n))).astype(np.float32)


def _write(path: Path, a: np.ndarray, *, crs=None, transform=None, **kw) -> Path:
    crs = rasterio.crs.CRS.from_epsg(32611) if crs is None else crs
    transform = Affine(PX, 0, X0, 0, -PX, Y1) if transform is None else transform
    prof = dict(driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=str(a.dtype), crs=crs,
                transform=transform, **kw)
    with rasterio.open(path, "w", **prof) as d:
        d.write(a, 1)
    return path


def _grid() -> Grid:
    """A 20 x 20 cell grid of 10 m inside the small rasters (5 px from their edges)."""
    return Grid.from_bounds(UTM11, X0 + 50, Y1 - 350, X0 + 350, Y1 - 50, 10.0)


def _under(win, a: np.ndarray) -> np.ndarray:
    """The pixels of ``a`` (written with :func:`_write`'s default transform) a window holds."""
    r0, c0 = round((Y1 - win.transform.f) / PX), round((win.transform.c - X0) / PX)
    return a[r0:r0 + win.values.shape[0], c0:c0 + win.values.shape[1]].astype(np.float64)


def _inspect(*args):
    res = CliRunner().invoke(main, ["inspect", *map(str, args)])
    return res.exit_code, res.output


def _one_error(code: int, out: str) -> str:
    """The one ``error:`` line of a refused command (exit 2, no traceback)."""
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in out, out
    return errors[0]


# ------------------------------------------------------------------ 2. declared vertical units
def test_dem_and_dsm_in_us_survey_feet_are_converted_to_metres(tmp_path):
    a = _heights()
    wkt = pyproj.CRS("EPSG:32611+6360").to_wkt()          # UTM 11N + NAVD88 height (ftUS)
    ft = _write(tmp_path / "ftus.tif", a, crs=rasterio.crs.CRS.from_wkt(wkt))
    m = _write(tmp_path / "m.tif", (a.astype(np.float64) * US_FT))   # the same heights in metres, by hand
    g = _grid()
    dem_ft, dem_m = terrain_from_dem(ft, g), terrain_from_dem(m, g)
    np.testing.assert_allclose(dem_ft.terrain, dem_m.terrain, rtol=1e-6)
    np.testing.assert_allclose(dem_ft.terrain_min, dem_m.terrain_min, rtol=1e-6)
    # hand check: the pixel under cell (0, 0)'s centre is a sample of its lattice squares
    assert dem_ft.terrain.max() == pytest.approx(float(a[5:36, 5:36].max()) * US_FT, rel=1e-6)
    assert dem_ft.terrain.max() < 350 * US_FT + 1e-3     # not read as metres (300..350)
    dsm_ft, dsm_m = dsm_on_grid(ft, g, derive_ground=False), dsm_on_grid(m, g, derive_ground=False)
    np.testing.assert_allclose(dsm_ft.surface, dsm_m.surface, rtol=1e-6)
    # the same window the stages read, converted
    win = read_window(ft, g, what="terrain DEM", margin_px=0)
    np.testing.assert_allclose(win.values, _under(win, a) * US_FT, rtol=1e-7)


def test_international_feet_band_scale_and_inspect_show_the_conversion(tmp_path):
    a = _heights()
    ft = _write(tmp_path / "ft.tif", a, crs=rasterio.crs.CRS.from_wkt(pyproj.CRS("EPSG:32611+8228").to_wkt()))
    win = read_window(ft, _grid(), what="terrain DEM", margin_px=0)
    np.testing.assert_allclose(win.values, _under(win, a) * FT, rtol=1e-7)
    # int16 decimetres: band scale 0.1
    dm = _write(tmp_path / "dm.tif", np.round(a * 10).astype(np.int16))
    with rasterio.open(dm, "r+") as d:
        d.scales = (0.1,)
    win = read_window(dm, _grid(), what="terrain DEM", margin_px=0)
    np.testing.assert_allclose(win.values, _under(win, np.round(a * 10)) * 0.1, rtol=1e-7)
    code, out = _inspect(tmp_path / "ft.tif")
    assert code == 0, out
    assert "vertical unit" in out and "foot" in out and "x 0.3048 to metres" in out
    lo, hi = float(a.min()) * FT, float(a.max()) * FT
    assert f"{lo:.2f} .. {hi:.2f} m" in out


def test_a_vertical_unit_that_cannot_be_converted_is_refused(tmp_path):
    p = _write(tmp_path / "odd.tif", _heights())
    with rasterio.open(p, "r+") as d:
        d.units = ("fathoms of ale",)
    with pytest.raises(DataError, match=r"odd\.tif: its band unit is 'fathoms of ale'.*convert the heights to metres"):
        terrain_from_dem(p, _grid())
    line = _one_error(*_inspect(p))
    assert "fathoms of ale" in line and "odd.tif" in line


# ------------------------------------------------------------------ 3. bottom-up rasters
def test_a_bottom_up_dem_is_read_flipped_like_its_top_down_twin(tmp_path):
    a = _heights()
    td = _write(tmp_path / "td.tif", a)
    bu = _write(tmp_path / "bu.tif", a[::-1].copy(), transform=Affine(PX, 0, X0, 0, PX, Y1 - N * PX))
    with rasterio.open(bu) as s:
        assert s.transform.e > 0                     # stored bottom-up indeed
    g = _grid()
    t_td, t_bu = terrain_from_dem(td, g), terrain_from_dem(bu, g)
    np.testing.assert_array_equal(t_bu.terrain, t_td.terrain)
    np.testing.assert_array_equal(t_bu.terrain_min, t_td.terrain_min)
    np.testing.assert_array_equal(dsm_on_grid(bu, g).surface, dsm_on_grid(td, g).surface)
    code, out = _inspect(bu)
    assert code == 0, out
    assert f"y {Y1 - N * PX:.1f}..{Y1:.1f}" in out and "bottom-up" in out
    assert f"{float(a.min()):.2f} .. {float(a.max()):.2f} m" in out


# ------------------------------------------------------------------ 4. truncated / corrupt files
def _tiled(tmp_path: Path) -> Path:
    a = (np.random.default_rng(0).random((512, 512)) * 50 + 100).astype(np.float32)
    return _write(tmp_path / "tiled.tif", a, transform=Affine(1, 0, X0, 0, -1, Y1), tiled=True, blockxsize=128,
                  blockysize=128, compress="deflate")


@pytest.mark.parametrize("damage", ["truncated", "corrupt-tile", "truncated-header"])
def test_a_truncated_or_corrupt_geotiff_is_one_data_error_naming_the_fix(tmp_path, damage):
    b = _tiled(tmp_path).read_bytes()
    bad = tmp_path / f"{damage}.tif"
    if damage == "truncated":
        bad.write_bytes(b[: len(b) // 2])
    elif damage == "truncated-header":
        bad.write_bytes(b[:200])
    else:
        c = bytearray(b)
        mid = len(b) // 2
        c[mid:mid + 4000] = bytes((i * 197 + 89) % 256 for i in range(4000))
        bad.write_bytes(bytes(c))
    g = Grid.from_bounds(UTM11, X0 + 10, Y1 - 500, X0 + 500, Y1 - 10, 10.0)
    for read in (lambda: terrain_from_dem(bad, g), lambda: dsm_on_grid(bad, g)):
        with pytest.raises(DataError, match=rf"{damage}\.tif: it is truncated or corrupt .*re-download it.*gdal_translate"):
            read()
    line = _one_error(*_inspect(bad))
    assert "truncated or corrupt" in line and bad.name in line


# ------------------------------------------------------------------ 5. GCP-only rasters
def test_a_gcp_only_raster_says_it_must_be_warped(tmp_path):
    from rasterio.control import GroundControlPoint as Gcp

    gcps = [Gcp(0, 0, X0, Y1), Gcp(0, N, X0 + 400, Y1), Gcp(N, 0, X0, Y1 - 400), Gcp(N, N, X0 + 400, Y1 - 400)]
    p = tmp_path / "gcp.tif"
    with rasterio.open(p, "w", driver="GTiff", width=N, height=N, count=1, dtype="float32", gcps=gcps,
                       crs="EPSG:32611") as d:
        d.write(_heights(), 1)
    with pytest.raises(DataError, match=r"gcp\.tif is georeferenced by 4 ground control points.*gdalwarp"):
        terrain_from_dem(p, _grid())
    line = _one_error(*_inspect(p))
    assert "ground control points" in line and "gdalwarp" in line and "no CRS" not in line


# ------------------------------------------------------------------ 6. a folder / FIFO / device
def _scenario(tmp_path: Path, dem: str | Path, **extra) -> Path:
    shutil.copy(catalog_dir() / "data" / "yuma_2020-01-03.txt", tmp_path / "yuma.txt")
    raw = {"name": "strict-dem",
           "aoi": {"crs": "EPSG:32611", "bounds": [X0 + 60, Y1 - 360, X0 + 360, Y1 - 60], "resolution_m": 30.0},
           "data": {"terrain": {"path": str(dem), "vertical_datum": "EGM96 geoid"}, "risk_default_level": 1,
                    "almanacs": ["yuma.txt"], **extra},
           "mission": {"start": {"x": X0 + 100, "y": Y1 - 300, "alt_agl_m": 60},
                       "goal": {"x": X0 + 300, "y": Y1 - 100, "alt_agl_m": 60},
                       "start_time_utc": "2020-01-03T18:00:00Z"},
           "constraints": {"min_altitude_agl_m": 10, "max_altitude_agl_m": 80}}
    y = tmp_path / "strict.yaml"
    y.write_text(yaml.safe_dump(raw))
    return y


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_a_folder_fifo_or_device_as_data_file_says_what_it_is(tmp_path, kind):
    if kind == "folder":
        p, said = tmp_path / "dem.tif", "is a folder; give a file"
        p.mkdir()
    elif kind == "fifo":
        p, said = tmp_path / "dem.tif", "is a FIFO (named pipe), not a regular file"
        os.mkfifo(p)
    else:
        p, said = Path("/dev/zero"), "is a device, not a regular file"
    with pytest.raises(ScenarioError) as exc:
        load_scenario(_scenario(tmp_path, p))
    assert f"data.terrain.path: data file {p} {said}" in str(exc.value)
    assert "not found" not in str(exc.value)
    with pytest.raises(DataError, match=f"{p} {said.split(';')[0]}".replace("(", r"\(").replace(")", r"\)")):
        read_window(p, _grid(), what="terrain DEM")
    code, out = _inspect(_scenario(tmp_path, p))
    assert code == 2 and said.split(";")[0] in out and "Traceback" not in out


# ------------------------------------------------------------------ 7. one height check for inspect and plan
@pytest.mark.parametrize("bad", [1e30, -9527.0])
def test_inspect_refuses_the_heights_plan_refuses_with_the_same_words(tmp_path, bad):
    a = _heights().astype(np.float64)
    a[10:12, 10:12] = bad
    p = _write(tmp_path / "bad.tif", a.astype(np.float32))
    with pytest.raises(DataError) as exc:
        terrain_from_dem(p, _grid())
    assert f"{np.float32(bad):g}" in str(exc.value) and "not a height in metres" in str(exc.value)
    line = _one_error(*_inspect(_scenario(tmp_path, p)))
    assert line.endswith(str(exc.value).split(":", 1)[1].strip()), (line, str(exc.value))
    line = _one_error(*_inspect(p))
    assert "not a height in metres" in line and f"{np.float32(bad):g}" in line


# ------------------------------------------------------------------ 8. a window larger than --max-memory
def _sparse_dsm(tmp_path: Path) -> Path:
    """200 000 x 200 000 px float32 at 1 m (160 GB of pixels), sparse: one block written, a few
    hundred kB on disk; everything else NoData."""
    p = tmp_path / "huge_dsm.tif"
    prof = dict(driver="GTiff", width=200_000, height=200_000, count=1, dtype="float32", crs="EPSG:32611",
                transform=Affine(1, 0, X0 - 100_000, 0, -1, Y1 + 100_000), tiled=True, blockxsize=1024,
                blockysize=1024, sparse_ok=True, BIGTIFF="YES", nodata=-9999, compress="deflate")
    with rasterio.open(p, "w", **prof) as d:
        d.write(np.full((1, 1024, 1024), 5, np.float32), window=rasterio.windows.Window(0, 0, 1024, 1024))
    assert p.stat().st_size < 5e6
    return p


def test_a_huge_sparse_dsm_is_refused_against_max_memory_before_the_read(tmp_path, monkeypatch):
    from skyroute.pipeline import budget

    p = _sparse_dsm(tmp_path)
    g = _grid()
    # the window grows over the NoData region (the whole raster) until it passes the limit
    budget.set_max_memory(64 << 20)
    try:
        with pytest.raises(InputError, match=r"huge_dsm\.tif: reading a window of [0-9,]+ x [0-9,]+ px to know the "
                           r"whole rim of its NoData regions.*more than --max-memory \(64 MiB\).*gdal_translate"):
            read_window_holes(p, g, what="surface DSM")
        with pytest.raises(InputError, match="more than --max-memory"):
            dsm_on_grid(p, g)
        # an AOI whose own window is too large: refused before the first read
        big = Grid.from_bounds(UTM11, X0, Y1 - 4000, X0 + 4000, Y1, 10.0)
        with pytest.raises(InputError, match=r"reading a window of 4,0[0-9]{2} x 4,0[0-9]{2} px over the AOI needs "
                           r"about 7[0-9]{2} MiB"):
            read_window(p, big, what="surface DSM")
    finally:
        budget.set_max_memory(None)
    # the file alone (no AOI, no overviews): not scanned whole, said, in a second
    code, out = _inspect(p, "--max-memory", "1G")
    assert code == 0 and "heights and NoData not inspected: the raster is 200,002 x 200,002 px" in out
    # the CLI: inspect and plan refuse with the same words (one error line, no traceback)
    y = _scenario(tmp_path, _write(tmp_path / "dem.tif", _heights()),
                  surface={"path": str(p), "vertical_datum": "EGM96 geoid"})
    line = _one_error(*_inspect(y, "--max-memory", "100M"))
    assert "huge_dsm.tif" in line and "more than --max-memory (100 MiB)" in line
    res = CliRunner().invoke(main, ["plan", str(y), "--max-memory", "600M", "--out", str(tmp_path / "out"),
                                    "--cache-dir", str(tmp_path / "cache"), "-q"])
    line = _one_error(res.exit_code, res.output)
    assert "huge_dsm.tif" in line and "more than --max-memory (600 MiB)" in line

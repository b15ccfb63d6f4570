"""Generate ``rotterdam_dsm_0p5m.tif``: a digital surface model rasterised from real LoD2 data.

Source: ``catalogs/data/rotterdam_delfshaven_lod2.city.json`` (CityJSON 1.0 LoD2, 853 buildings of
Rotterdam-Delfshaven; cityjson/cjio @ 94119b4c, municipal open data of Rotterdam republished by
TU Delft; see catalogs/data/ATTRIBUTION.md).

Window: x 91180..91430 m, y 435680..435930 m (250 m x 250 m, holding the district's tallest
building, 41.16 m) in EPSG:28992 (Amersfoort / RD New),
500 x 500 cells of 0.5 m, north-up.  Heights [m] in NAP (Normaal Amsterdams Peil, the source's
vertical datum).

Each cell is the exact maximum over the cell's closed square of the buildings' roof faces
(:func:`skyroute.stages.surface.cityjson_buildings`: face vertices, edge crossings and interior
corners) and of the ground (each building's ``TerrainHeight`` interpolated linearly on the
Delaunay triangles of the building vertices, maximum over the cell; the file has no TINRelief):
``skyroute.stages.surface.build_surface``'s ``surface`` computed in float64, rounded *up* to
float32 so the stored value is never below it.

GeoTIFF: float32, DEFLATE with the floating-point predictor, 256 x 256 tiles, no NoData (every
cell is valid), tags ``VERTICAL_DATUM=NAP`` and ``SOURCE``.  Run from the repository root::

    python tests/data/make_rotterdam_dsm.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "rotterdam_dsm_0p5m.tif"
CRS = "EPSG:28992"
BOUNDS = (91180.0, 435680.0, 91430.0, 435930.0)  # xmin, ymin, xmax, ymax [m]
RESOLUTION_M = 0.5
VERTICAL_DATUM = "NAP"


def source_path() -> Path:
    from skyroute.pipeline.settings import catalog_dir

    return catalog_dir() / "data" / "rotterdam_delfshaven_lod2.city.json"


def compute() -> tuple[np.ndarray, object]:
    """(surface [m] as float32 rounded up, grid) of the fixture window."""
    from skyroute.stages.grid import Grid
    from skyroute.stages.surface import cityjson_buildings, terrain_from_points

    grid = Grid.from_bounds(CRS, *BOUNDS, RESOLUTION_M)
    br, ground = cityjson_buildings(source_path(), grid)
    terrain = terrain_from_points(ground, grid, br.terrain)
    surface = np.where(br.index >= 0, np.fmax(terrain, br.top), terrain)
    s32 = surface.astype(np.float32)
    s32 = np.where(s32.astype(np.float64) < surface, np.nextafter(s32, np.float32(np.inf)), s32)
    return s32.astype(np.float32), grid


def main() -> None:
    import rasterio

    dsm, grid = compute()
    profile = {"driver": "GTiff", "width": grid.nx, "height": grid.ny, "count": 1, "dtype": "float32",
               "crs": CRS, "transform": grid.transform, "compress": "deflate", "predictor": 3,
               "zlevel": 9, "tiled": True, "blockxsize": 256, "blockysize": 256}
    with rasterio.open(OUT, "w", **profile) as dst:
        dst.write(dsm, 1)
        dst.update_tags(VERTICAL_DATUM=VERTICAL_DATUM, UNITS="m",
                        SOURCE="rotterdam_delfshaven_lod2.city.json (cityjson/cjio @ 94119b4c), exact "
                               "face-over-cell maxima, tests/data/make_rotterdam_dsm.py")
        dst.set_band_description(1, "surface height [m, NAP]")
    print(f"wrote {OUT} ({OUT.stat().st_size / 1024:.0f} KiB), {grid.nx} x {grid.ny} cells of {RESOLUTION_M} m, "
          f"heights {dsm.min():.2f} .. {dsm.max():.2f} m NAP")


if __name__ == "__main__":
    main()

"""A generated city of towers (issue 22's fixture): a 1 m DSM GeoTIFF of square towers on a street
grid, no landing sites, and a scenario YAML that flies a potential-field plan down its streets
below the roofs (satellites hidden by the towers), as a new user would give it
(``data.surface``).  Shared by tests/test_tactical_escape.py and benchmarks/bench_encounters.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

X0, Y0 = 386000.0, 6671000.0          # EPSG:32635 (Helsinki's UTM zone), lower-left corner [m]
SIZE_X, SIZE_Y = 600.0, 400.0         # [m]
BLOCK, STREET = 40.0, 30.0            # tower footprint and street width [m]
CATALOG = Path(__file__).resolve().parents[1] / "catalogs"


def tower_heights(seed: int = 7) -> np.ndarray:
    """Heights [m] of the towers, one per block (rows south -> north, columns west -> east)."""
    rng = np.random.default_rng(seed)
    nby = int(SIZE_Y // (BLOCK + STREET))
    nbx = int(SIZE_X // (BLOCK + STREET))
    return rng.uniform(25.0, 70.0, size=(nby, nbx)).round(1)


def write_dsm(path: Path, seed: int = 7) -> Path:
    """The 1 m DSM: ground 0 m (EGM96 heights), towers of :func:`tower_heights` with their
    lower-left corners at ``STREET + k (BLOCK + STREET)`` from the AOI's corner."""
    import rasterio
    from rasterio.transform import from_origin

    nx, ny = int(SIZE_X), int(SIZE_Y)
    z = np.zeros((ny, nx), np.float32)
    h = tower_heights(seed)
    pitch = BLOCK + STREET
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            x0 = STREET + j * pitch
            y0 = STREET + i * pitch
            r0, r1 = int(ny - (y0 + BLOCK)), int(ny - y0)
            z[r0:r1, int(x0):int(x0 + BLOCK)] = h[i, j]
    with rasterio.open(path, "w", driver="GTiff", width=nx, height=ny, count=1, dtype="float32", crs="EPSG:32635",
                       transform=from_origin(X0, Y0 + SIZE_Y, 1.0, 1.0), nodata=-9999.0) as dst:
        dst.write(z, 1)
    return path


def street_y(k: int = 2) -> float:
    """The centre line [m, map y] of the ``k``-th east-west street."""
    return Y0 + STREET / 2 + k * (BLOCK + STREET)


def write_scenario(folder: Path, *, planner: str = "astar", alt_agl_m: float = 20.0, name: str = "towers-city",
                   events: list | None = None) -> Path:
    """DSM + scenario YAML in ``folder``; returns the YAML path.  The mission flies along an
    east-west street at ``alt_agl_m`` (below every roof), GPS + Galileo almanacs as shipped."""
    import yaml

    folder.mkdir(parents=True, exist_ok=True)
    write_dsm(folder / "towers_dsm.tif")
    y = street_y(2)
    sc = {
        "name": name,
        "description": "A generated city of towers (tests/_towers.py): 1 m DSM, no landing sites.",
        "aoi": {"crs": "EPSG:32635", "bounds": [X0, Y0, X0 + SIZE_X, Y0 + SIZE_Y], "resolution_m": 2.0},
        "data": {"surface": {"path": "towers_dsm.tif", "vertical_datum": "EGM96"},
                 "almanacs": [str(CATALOG / "data" / "yuma_2020-01-03.txt"),
                              str(CATALOG / "data" / "alm_gal_ed259.txt")]},
        "mission": {"start": {"x": X0 + 15.0, "y": y, "alt_agl_m": alt_agl_m},
                    "goal": {"x": X0 + SIZE_X - 15.0, "y": y, "alt_agl_m": alt_agl_m},
                    "start_time_utc": "2020-01-03T10:00:00Z"},
        "vehicle": "dji-m300-rtk",
        "constraints": {"min_altitude_agl_m": 0, "max_altitude_agl_m": 80},
        "gnss": {"elevation_mask_deg": 5, "dop_kind": "PDOP", "dop_thresholds": [2, 3, 4], "window_min": 10,
                 "step_min": 1},
        "planner": {"name": planner, "weights": [1, 1, 1, 1], "seed": 0},
        "tactical": {"t_rep_s": 5.0, "tick_s": 0.1, "seed": 0},
    }
    if events:
        sc["events"] = events
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(sc, sort_keys=False))
    return path

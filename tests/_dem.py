"""The README's bring-your-own-DEM example as test fixtures: its scenario YAML, read from
``catalogs/README.md`` (so a test plans what the README tells a user to write), and the DEM it
names, a 4 x 4 km window of the shipped SRTM DEM.  Shared by tests/test_own_city.py,
tests/test_outputs_never_destroy.py and tests/test_cache_force_and_keys.py."""

from __future__ import annotations

import re
from pathlib import Path

from skyroute.pipeline.settings import catalog_dir

DATA = catalog_dir() / "data"
#: The window of the shipped SRTM DEM the example's AOI lies in: (left, bottom, right, top) [m, EPSG:32611].
DEM_WINDOW = (382500, 3793500, 386500, 3797500)


def readme_scenarios() -> dict[str, str]:
    """The YAML blocks of catalogs/README.md's "Bring your own city", by scenario name."""
    text = (catalog_dir() / "README.md").read_text()
    sec = text.split("## Bring your own city", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```yaml\n(.*?)```", sec, re.S)
    return {re.search(r"^name: (\S+)", b, re.M).group(1): b for b in blocks}


def dem_scenario(dem_path: str = "dem.tif") -> str:
    """The README's ``my-mountains-dem`` YAML, its ``data.terrain.path`` set to ``dem_path``."""
    return readme_scenarios()["my-mountains-dem"].replace("path: dem.tif", f"path: {dem_path}")


def write_dem_window(out: Path) -> Path:
    """The shipped SRTM DEM over :data:`DEM_WINDOW`, as it is (its own pixels, dtype and CRS), at ``out``."""
    import rasterio
    import rasterio.windows

    with rasterio.open(DATA / "srtm_bigtujunga30m_utm11.tif") as src:
        w = rasterio.windows.from_bounds(*DEM_WINDOW, src.transform).round_offsets().round_lengths()
        a = src.read(1, window=w)
        prof = {"driver": "GTiff", "width": a.shape[1], "height": a.shape[0], "count": 1, "dtype": a.dtype,
                "crs": src.crs, "transform": src.window_transform(w)}
    with rasterio.open(out, "w", **prof) as dst:
        dst.write(a, 1)
    return out

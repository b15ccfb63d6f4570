"""`verify_dataset`: every problem of a stage output, listed (xcube style), never the first only.

The runner verifies each stage's output before caching it, so a malformed dataset is never
trusted by a later stage or run.
"""

from __future__ import annotations

import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr

from skyroute.pipeline.errors import SkyrouteError

#: variable-name fragments that mark an altitude/height: these must state their vertical datum
HEIGHT_WORDS = ("surface", "terrain", "altitude", "floor", "ceiling", "height")


class DatasetError(SkyrouteError):
    """A dataset breaks skyroute's conventions; ``problems`` lists every one."""

    def __init__(self, what: str, problems: list[str]):
        self.problems = list(problems)
        super().__init__(f"{what}: {len(problems)} problem(s): " + "; ".join(problems))


def verify_dataset(ds: xr.Dataset) -> list[str]:
    """Every convention ``ds`` breaks (empty list = fine):

    * each numeric or boolean data variable has a CF ``units`` attribute;
    * rasters (dims ``y``, ``x``) have x ascending, y descending, equal square steps, and a CRS;
    * height-like variables in metres (names with surface/terrain/altitude/floor/ceiling/height)
      state a ``vertical_datum`` (on the variable or the dataset) unless they are AGL/relative;
    * ``time`` coordinates are datetime64 (UTC by skyroute's convention).
    """
    problems: list[str] = []
    for name, var in ds.data_vars.items():
        if "units" not in var.attrs and var.dtype.kind not in "OUST":  # text needs no units
            problems.append(f"{name}: no 'units' attribute")
        units = var.attrs.get("units")
        rel = any(w in str(var.attrs.get("long_name", "")).lower() for w in ("above ground", "agl", "relative"))
        if (units == "m" and any(w in str(name) for w in HEIGHT_WORDS) and "agl" not in str(name).lower()
                and not rel and "vertical_datum" not in var.attrs and "vertical_datum" not in ds.attrs):
            problems.append(f"{name}: a height in metres without a 'vertical_datum' attribute")
    if "x" in ds.dims and "y" in ds.dims:
        x = np.asarray(ds["x"].values, float)
        y = np.asarray(ds["y"].values, float)
        if x.size > 1 and not np.all(np.diff(x) > 0):
            problems.append("x: coordinates must increase (west to east)")
        if y.size > 1 and not np.all(np.diff(y) < 0):
            problems.append("y: coordinates must decrease (north-up raster)")
        if x.size > 1 and y.size > 1:
            dx, dy = np.abs(np.diff(x)), np.abs(np.diff(y))
            if not (np.allclose(dx, dx[0]) and np.allclose(dy, dy[0]) and np.isclose(dx[0], dy[0])):
                problems.append("x/y: cells must be square with a constant step")
        try:
            crs = ds.rio.crs
        except Exception:  # rioxarray raises on conflicting CRS definitions
            crs = None
        if crs is None:
            problems.append("no CRS: write one with ds.rio.write_crs('EPSG:...')")
    if "time" in ds.coords and not np.issubdtype(ds["time"].dtype, np.datetime64):
        problems.append(f"time: coordinate must be datetime64 (UTC), not {ds['time'].dtype}")
    return problems

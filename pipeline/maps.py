"""Environment map outputs: GeoTIFFs of every layer and a PNG panel like seed 000 Fig. 1."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skyroute.pipeline.graph import RunResult
from skyroute.stages.figures import add_map_furniture, image_extent

#: Figures show at most this many cells along a side: a larger map is reduced for display by the
#: max over k x k blocks (no-fly, risk, heights and floors: the worst of the block is shown).
DISPLAY_MAX_CELLS = 2000


def display_view(obj, max_cells: int | None = None):
    """``obj`` (a Dataset or DataArray on (y, x), numpy or dask) as a figure shows it: unchanged up to
    ``max_cells`` (default :data:`DISPLAY_MAX_CELLS`) cells a side, else the max over k x k blocks
    (``coarsen``, lazy on dask, the last partial block dropped) so that a city-scale map is never
    drawn (nor loaded) whole; returns ``(view, k)``."""
    if max_cells is None:
        max_cells = DISPLAY_MAX_CELLS
    if "y" not in obj.dims or "x" not in obj.dims:
        return obj, 1
    k = int(np.ceil(max(obj.sizes["y"], obj.sizes["x"]) / max_cells))
    if k <= 1:
        return obj, 1
    return obj.coarsen(y=k, x=k, boundary="trim").max(), k


def display_grid(grid, view, k: int):
    """The grid a figure draws ``view`` (a :func:`display_view` result of a map on ``grid``,
    block side ``k``) on: ``grid`` itself when ``k == 1``, else the view's coarser grid."""
    from skyroute.stages.gridspec import Grid

    return grid if k == 1 else Grid.from_dataarray(view)


def write_raster_chunked(da, path: Path, **kwargs) -> Path:
    """``da`` to a tiled GeoTIFF; a dask-backed raster is written chunk by chunk (never whole in memory)."""
    import threading

    if da.chunks is not None:
        da.rio.to_raster(path, tiled=True, lock=threading.Lock(), **kwargs)
    else:
        da.rio.to_raster(path, **kwargs)
    return path


def plot_maps_panel(result: RunResult, path: Path, wind_height_agl_m: float = 50.0) -> Path:
    """Risk levels, landing cost, wind arrows over buildings, no-fly and one traffic slice."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.grid import Grid
    from skyroute.stages.landing import plot_landing_cost
    from skyroute.stages.risk import plot_risk_levels

    sc = result.scenario
    surface, k = display_view(result["surface"][["surface", "terrain"]])
    surface = surface.load()
    env = display_view(result["environment"])[0].load() if "environment" in result.datasets else None
    clear = display_view(result["clearance"][["nofly", "min_altitude_m"]])[0].load() \
        if "clearance" in result.datasets else None
    fig, axes = plt.subplots(2, 3, figsize=(17, 11), dpi=90)
    axes = axes.ravel()
    if env is not None:
        plot_risk_levels(env, ax=axes[0])
        plot_landing_cost(env, ax=axes[1])
    # wind arrows over the buildings
    ax = axes[2]
    ext = image_extent(surface["surface"])
    height = (surface["surface"] - surface["terrain"]).values
    im = ax.imshow(height, extent=ext, cmap="Greys", interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8, label="building height above ground [m]")
    if "wind" in result.datasets:
        w = result["wind"].sel(z=wind_height_agl_m, method="nearest").load()
        X, Y = np.meshgrid(w["x"].values, w["y"].values)
        step = max(1, int(np.ceil(max(X.shape) / 14)))
        sl = (slice(None, None, step), slice(None, None, step))
        spacing_m = step * float(abs(w["x"].values[1] - w["x"].values[0])) if w.sizes["x"] > 1 else 100.0
        vmax = max(float(w["speed"].max()), 1e-3)
        q = ax.quiver(X[sl], Y[sl], w["u"].values[sl], w["v"].values[sl], w["speed"].values[sl], cmap="plasma",
                      angles="xy", scale_units="xy", scale=vmax / (0.9 * spacing_m), width=0.006)
        ax.quiverkey(q, 0.75, 1.025, 10, "10 m/s", labelpos="E")
        ax.set_title(f"wind at {float(w['z']):g} m AGL ({result['wind'].attrs.get('profile', '')})",
                     pad=16)   # above the 10 m/s key
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_aspect("equal")
    # no-fly cells (dilated by r_p) and the wind no-fly mask
    ax = axes[3]
    nofly = np.zeros(surface["surface"].shape, dtype=float)
    if clear is not None:
        nofly = np.where(clear["nofly"].values, 1.0, 0.0)
    ax.imshow(height > 0, extent=ext, cmap="Greys", alpha=0.35, interpolation="nearest")
    ax.imshow(np.ma.masked_equal(nofly, 0), extent=ext, cmap="autumn", interpolation="nearest", vmin=0, vmax=1)
    n_wind = 0
    if "wind" in result.datasets:
        n_wind = int(result["wind"]["wind_nofly"].any().values)
    ax.set_title(f"no-fly cells (dilated by r_p), {int(nofly.sum())} {'cells' if k == 1 else f'{k} x {k} blocks'}; "
                 f"wind no-fly: {'yes' if n_wind else 'none'}")
    ax.set_aspect("equal")
    # one occupancy slice of the known traffic
    ax = axes[4]
    ax.imshow(height > 0, extent=ext, cmap="Greys", alpha=0.35, interpolation="nearest")
    if "traffic" in result.datasets:
        from skyroute.stages.traffic import TrafficOccupancy

        occ = TrafficOccupancy.from_dataset(result["traffic"].load())
        grid = Grid.from_dataarray(surface["surface"])
        coarse = Grid.from_bounds(grid.crs, *grid.bounds, max(grid.resolution_m, 4.0))
        k = occ.n_slices // 2
        z = float(np.median(result["traffic"]["start"].values[:, 2]))
        sl_da = occ.occupancy_slice(coarse, k, z)
        ax.imshow(np.ma.masked_equal(sl_da.values.astype(float), 0), extent=image_extent(sl_da), cmap="cool",
                  interpolation="nearest", vmin=0, vmax=1)
        ax.set_title(sl_da.attrs.get("long_name", "occupancy"), fontsize=9)
    else:
        ax.set_title("no known traffic in this scenario")
    ax.set_aspect("equal")
    # clearance floor above ground
    ax = axes[5]
    if clear is not None:
        fl = clear["min_altitude_m"].values - surface["terrain"].values
        im = ax.imshow(fl, extent=ext, cmap="magma", interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8, label="lowest allowed altitude [m AGL]")
        ax.set_title(f"obstacle clearance floor, r_p = {result['clearance'].attrs.get('radius_m', '?')} m")
    ax.set_aspect("equal")
    for a in axes:
        for (name, mk) in (("start", "wo"), ("goal", "r*")):
            x, y = sc.point_xy(getattr(sc.mission, name))
            a.plot(x, y, mk, ms=9, mec="k")
        a.ticklabel_format(useOffset=False, style="plain")
        a.tick_params(labelsize=7)
        a.locator_params(axis="x", nbins=4)   # 7-digit UTM eastings on a narrow panel
        add_map_furniture(a)
    shown = "" if k == 1 else f"; shown as the max over {k} x {k} cells"
    fig.suptitle(f"{sc.name}: environment maps ({sc.grid.crs.name}, {sc.grid.resolution_m:g} m cells{shown})")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_map_geotiffs(result: RunResult, out_dir: Path) -> list[Path]:
    """One GeoTIFF per 2-D layer of the environment, clearance and surface datasets."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    layers = [("surface", "surface"), ("surface", "terrain"), ("environment", "risk_level"),
              ("environment", "risk_cost"), ("environment", "landing_distance_m"), ("environment", "landing_cost"),
              ("environment", "nofly"), ("clearance", "min_altitude_m"), ("clearance", "obstacle_floor_m")]
    crs = result["surface"]["surface"].rio.crs
    for stage, var in layers:
        if stage in result.datasets and var in result[stage]:
            da = result[stage][var]
            if da.dtype == bool:
                da = da.astype("uint8")
            da = da.rio.write_crs(crs)
            written.append(write_raster_chunked(da, out_dir / f"{var}.tif", compress="deflate"))
    return written

"""Environment map outputs: GeoTIFFs of every layer and a PNG panel like seed 000 Fig. 1."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skyroute.pipeline.graph import RunResult
from skyroute.stages.figures import image_extent

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
    """Risk levels, landing cost, wind arrows over the buildings (or the terrain), no-fly cells,
    one traffic slice and the clearance floor of ``result``'s maps (:func:`maps_figure`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages.grid import Grid

    sc = result.scenario
    surface, k = display_view(result["surface"][["surface", "terrain"]])
    surface = surface.load()
    env = display_view(result["environment"])[0].load() if "environment" in result.datasets else None
    clear = None
    if "clearance" in result.datasets:
        clear = display_view(result["clearance"][["nofly", "min_altitude_m"]])[0].load()
        clear.attrs = dict(result["clearance"].attrs)
    wind = None
    if "wind" in result.datasets:
        w = result["wind"].sel(z=wind_height_agl_m, method="nearest").load()
        wind = (w, str(result["wind"].attrs.get("profile", "")), bool(result["wind"]["wind_nofly"].any().values))
    traffic = None
    if "traffic" in result.datasets:
        from skyroute.stages.traffic import TrafficOccupancy

        occ = TrafficOccupancy.from_dataset(result["traffic"].load())
        grid = Grid.from_dataarray(surface["surface"])
        coarse = Grid.from_bounds(grid.crs, *grid.bounds, max(grid.resolution_m, 4.0))
        z = float(np.median(result["traffic"]["start"].values[:, 2]))
        traffic = occ.occupancy_slice(coarse, occ.n_slices // 2, z)
    fig = maps_figure(surface, env=env, clear=clear, wind=wind, traffic=traffic,
                      start_xy=sc.point_xy(sc.mission.start), goal_xy=sc.point_xy(sc.mission.goal),
                      title=f"{sc.name}: environment maps ({sc.grid.crs.name}, {sc.grid.resolution_m:g} m cells"
                            f"{'' if k == 1 else f'; shown as the max over {k} x {k} cells'})", block=k)
    fig.savefig(path)
    plt.close(fig)
    return path


def _hillshade(z: np.ndarray, res_m: float) -> np.ndarray:
    """A 0..1 hill shade of the heights ``z`` [m] on ``res_m`` [m] cells (light from the north-west)."""
    dy, dx = np.gradient(np.nan_to_num(np.asarray(z, float)), res_m)
    return 0.5 + 0.5 * (-dx + dy) / np.sqrt(2 + dx**2 + dy**2 + 1e-9)


def _context(ax, height: np.ndarray, terrain: np.ndarray, ext, res_m: float) -> None:
    """The map under an overlay: the buildings' footprints in grey, or, without buildings, the
    terrain's hill shade (a terrain scenario shows its terrain on every panel)."""
    from skyroute.stages.figures import value_range

    if np.nanmax(height, initial=0.0) > 0:
        ax.imshow(np.ma.masked_equal((height > 0).astype(float), 0), extent=ext, cmap="Greys", vmin=0, vmax=2.5,
                  interpolation="nearest")
    elif value_range(terrain) is not None:
        ax.imshow(_hillshade(terrain, res_m), extent=ext, cmap="gray", vmin=-0.3, vmax=1.3, interpolation="nearest")


def maps_figure(surface, *, env=None, clear=None, wind=None, traffic=None, start_xy=None, goal_xy=None,
                title: str = "", block: int = 1):
    """The six-panel environment figure (3 rows x 2 columns, readable at a page's width).

    Parameters
    ----------
    surface : xarray.Dataset
        ``surface`` and ``terrain`` [m] on (y, x) (as displayed: :func:`display_view`).
    env : xarray.Dataset, optional
        The environment stage: ``risk_level``, ``landing_cost`` (and the landing sites
        ``site_x`` / ``site_y``).
    clear : xarray.Dataset, optional
        ``nofly`` and ``min_altitude_m`` [m]; attribute ``radius_m`` (r_p [m]).
    wind : (xarray.Dataset, str, bool), optional
        One height of the wind field (``u``, ``v``, ``speed`` [m/s], scalar ``z`` [m AGL]), the
        profile name and whether any wind no-fly cell exists.
    traffic : xarray.DataArray, optional
        One occupancy slice of the known traffic (``long_name`` attribute).
    start_xy, goal_xy : (float, float), optional
        The mission's start and goal [m, map CRS].
    title : str
        The figure title.
    block : int
        Cells per displayed block side (1: full resolution).

    A layer that does not vary (no landing sites, no buildings, no no-fly cell, no traffic, a
    flat floor) gets a note on its panel instead of a colour bar of a made-up range; without
    buildings the wind panel shows the terrain heights and the others the terrain's hill shade.
    """
    import textwrap

    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from skyroute.stages import figures as F
    from skyroute.stages.risk import plot_risk_levels

    ext = image_extent(surface["surface"])
    xs = np.asarray(surface["x"].values, float)
    res_m = float(abs(xs[1] - xs[0])) if xs.size > 1 else 1.0
    terrain = np.asarray(surface["terrain"].values, float)
    height = np.asarray(surface["surface"].values, float) - terrain
    datum = str(surface.attrs.get("vertical_datum", "") or surface["surface"].attrs.get("vertical_datum", ""))
    ny, nx = height.shape
    aspect = min(max(ny / max(nx, 1), 0.35), 1.6)
    panel_w = 6.2
    fig, axes = plt.subplots(3, 2, figsize=(2 * panel_w + 0.6, 3 * (panel_w * 0.72 * aspect + 1.3) + 0.9), dpi=90,
                             layout="constrained")
    axes = axes.ravel()
    has_sites = False
    for a in axes:
        a.set_xlim(ext[0], ext[1])
        a.set_ylim(ext[2], ext[3])
    # 0: ground risk levels (a categorical legend: a uniform map says "(none)" for the others)
    ax = axes[0]
    if env is not None:
        plot_risk_levels(env, ax=ax)
    else:
        F.add_note(ax, "no environment stage: no ground risk map")
        ax.set_title("ground risk level")
    # 1: landing cost, or a note when there is no landing site (the cost is then 1 everywhere)
    ax = axes[1]
    ax.set_title("landing-site cost")
    if env is not None and "landing_cost" in env:
        lc = np.asarray(env["landing_cost"].values, float)
        sx = np.asarray(env["site_x"].values, float) if "site_x" in env.coords else np.zeros(0)
        sy = np.asarray(env["site_y"].values, float) if "site_y" in env.coords else np.zeros(0)
        inside = (sx >= ext[0]) & (sx <= ext[1]) & (sy >= ext[2]) & (sy <= ext[3])
        if sx.size == 0 or F.value_range(lc) is None:
            _context(ax, height, terrain, ext, res_m)
            u = F.uniform_value(lc)
            F.add_note(ax, "no landing sites in this scenario" + ("" if u is None else f":\nlanding cost {u:g} everywhere"))
        else:
            im = ax.imshow(lc, cmap="viridis", vmin=0, vmax=1, extent=ext, interpolation="nearest")
            F.side_colorbar(fig, ax, im, "landing cost [-]")
            ax.plot(sx[inside], sy[inside], "*", color="red", ms=8, ls="none", label="landing site")
            has_sites = bool(inside.any())
    # 2: wind arrows over the buildings, or over the terrain when there are none
    ax = axes[2]
    if np.nanmax(height, initial=0.0) > 0:
        im = ax.imshow(height, extent=ext, cmap="Greys", interpolation="nearest")
        F.side_colorbar(fig, ax, im, "building height above ground [m]")
        over = "buildings"
    else:
        im = ax.imshow(terrain, extent=ext, cmap="terrain", interpolation="nearest")
        ax.imshow(_hillshade(terrain, res_m), extent=ext, cmap="gray", alpha=0.3, interpolation="nearest")
        lab = "terrain height [m]" + (f"\n{textwrap.shorten(datum, 40)}" if datum else "")
        F.colorbar_or_note(fig, ax, im, terrain, lab, "no buildings; flat ground", shrink=0.85)
        over = "terrain"
    if wind is not None:
        w, profile, _ = wind
        X, Y = np.meshgrid(w["x"].values, w["y"].values)
        step = max(1, int(np.ceil(max(X.shape) / 14)))
        sl = (slice(None, None, step), slice(None, None, step))
        spacing_m = step * float(abs(w["x"].values[1] - w["x"].values[0])) if w.sizes["x"] > 1 else 100.0
        vmax = max(float(w["speed"].max()), 1e-3)
        q = ax.quiver(X[sl], Y[sl], w["u"].values[sl], w["v"].values[sl], w["speed"].values[sl], cmap="plasma",
                      angles="xy", scale_units="xy", scale=vmax / (0.9 * spacing_m), width=0.006)
        ax.quiverkey(q, 0.80, 1.025, 10, "10 m/s", labelpos="E")
        ax.set_title(f"wind at {float(w['z']):g} m AGL ({profile})\nover the {over}", fontsize=10,
                     pad=16)   # above the 10 m/s key
    else:
        ax.set_title(f"{over} (no wind stage)")
    # 3: no-fly cells (dilated by r_p) and the wind no-fly mask
    ax = axes[3]
    _context(ax, height, terrain, ext, res_m)
    n_nofly = 0
    if clear is not None:
        nofly = np.where(np.asarray(clear["nofly"].values, bool), 1.0, 0.0)
        n_nofly = int(nofly.sum())
        if n_nofly:
            ax.imshow(np.ma.masked_equal(nofly, 0), extent=ext, cmap="autumn", interpolation="nearest", vmin=0, vmax=1)
    wind_nofly = wind is not None and wind[2]
    unit = "cells" if block == 1 else f"{block} x {block} blocks"
    ax.set_title(f"no-fly cells (dilated by r_p): {n_nofly} {unit}\nwind no-fly: {'yes' if wind_nofly else 'none'}",
                 fontsize=10)
    if not n_nofly:
        F.add_note(ax, "no no-fly cells in this scenario" + ("" if wind_nofly else "\n(and no wind no-fly)"))
    # 4: one occupancy slice of the known traffic
    ax = axes[4]
    _context(ax, height, terrain, ext, res_m)
    if traffic is not None:
        occ = np.asarray(traffic.values, float)
        if occ.any():
            ax.imshow(np.ma.masked_equal(occ, 0), extent=image_extent(traffic), cmap="cool", interpolation="nearest",
                      vmin=0, vmax=1)
        else:
            F.add_note(ax, "no traffic in this slice")
        ax.set_title("\n".join(textwrap.wrap(str(traffic.attrs.get("long_name", "traffic occupancy")), 60)[:2]),
                     fontsize=9)
    else:
        ax.set_title("known traffic")
        F.add_note(ax, "no known traffic in this scenario")
    # 5: the clearance floor above ground
    ax = axes[5]
    if clear is not None:
        fl = np.asarray(clear["min_altitude_m"].values, float) - terrain
        im = ax.imshow(fl, extent=ext, cmap="magma", interpolation="nearest")
        u = F.uniform_value(fl)
        F.colorbar_or_note(fig, ax, im, fl, "lowest allowed altitude [m AGL]",
                         f"clearance floor {u:g} m AGL everywhere" if u is not None else "no clearance floor",
                         shrink=0.85)
        ax.set_title(f"obstacle clearance floor\nr_p = {clear.attrs.get('radius_m', '?')} m", fontsize=10)
    else:
        ax.set_title("obstacle clearance floor")
        F.add_note(ax, "no clearance stage")
    for a in axes:
        if start_xy is not None:
            a.plot(*start_xy, **F.START_STYLE, label="start")
        if goal_xy is not None:
            a.plot(*goal_xy, **F.GOAL_STYLE, label="goal")
        a.set_xlim(ext[0], ext[1])
        a.set_ylim(ext[2], ext[3])
        a.set_aspect("equal")
        a.ticklabel_format(useOffset=False, style="plain")
        a.tick_params(labelsize=7)
        a.locator_params(axis="x", nbins=4)   # 7-digit UTM eastings on a narrow panel
        F.add_map_furniture(a)
    handles = [Line2D([], [], **F.START_STYLE, label="start"), Line2D([], [], **F.GOAL_STYLE, label="goal")]
    if has_sites:
        handles.append(Line2D([], [], marker="*", color="red", ms=8, ls="none", label="landing site"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=9)
    if title:
        fig.suptitle(title)
    # the colour bars are insets beside their maps, which the constrained layout does not see:
    # room between and around the panels for them (and their labels), then a larger canvas if
    # anything still leaves it
    fig.get_layout_engine().set(w_pad=0.1, wspace=0.12)
    F.grow_until_unclipped(fig)
    return fig


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

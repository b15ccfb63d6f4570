"""Outputs of ``skyroute coverage``: one GeoTIFF per DOP threshold and a PNG overview.

The lead's click command builds the coverage Dataset
(:func:`skyroute.stages.coverage.coverage_maps`) and calls :func:`write_coverage_outputs`.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr

from skyroute.pipeline.errors import InputError
from skyroute.stages.figures import add_map_furniture, grow_until_unclipped, image_extent


def _threshold_label(value: float) -> str:
    return f"{value:g}".replace(".", "p")


def _window_text(ds: xr.Dataset) -> str:
    start, end = ds.attrs.get("window_start"), ds.attrs.get("window_end")
    n = ds.attrs.get("n_epochs")
    if start and end:
        return f"{str(start)[:16]} .. {str(end)[:16]} UTC, {n} epochs, worst case"
    return f"{n} epoch(s), worst case" if n else "worst case over the window"


def write_coverage_outputs(ds: xr.Dataset, out_dir: Path) -> list[Path]:
    """Write ``coverage_<KIND>_<D>.tif`` (float32, NaN nodata = unflyable or no data, heights
    [m] in the surface's vertical datum) for every threshold D and ``coverage_<KIND>.png``
    (one panel per threshold, unflyable cells grey) into ``out_dir``; return the paths."""
    if "coverage_floor" not in ds or "threshold" not in ds["coverage_floor"].dims:
        raise InputError("expected the Dataset of skyroute.stages.coverage.coverage_maps "
                         "(variable coverage_floor on (threshold, y, x))")
    if ds.rio.crs is None:
        raise InputError("coverage Dataset carries no CRS; build it from a surface with a CRS")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    from skyroute.pipeline.maps import display_view, write_raster_chunked

    kind = str(ds.attrs.get("dop_kind", "DOP"))
    floor = ds["coverage_floor"].astype(np.float32)    # lazy when ds is: written chunk by chunk
    unfly = ds["unflyable"] if "unflyable" in ds else xr.zeros_like(floor, dtype=bool)
    paths: list[Path] = []
    for thr in floor["threshold"].values:
        layer = floor.sel(threshold=thr).drop_vars("threshold")
        layer = layer.rio.write_crs(ds.rio.crs).rio.write_nodata(np.nan, encoded=False)
        layer.attrs = {"long_name": f"altitude above which {kind} < {thr:g}", "units": "m",
                       "dop_kind": kind, "threshold": float(thr),
                       "vertical_datum": str(floor.attrs.get("vertical_datum", "")),
                       "window": _window_text(ds), "nodata_meaning": "unflyable or no surface data"}
        path = out_dir / f"coverage_{kind}_{_threshold_label(float(thr))}.tif"
        paths.append(write_raster_chunked(layer, path, dtype="float32", compress="deflate"))
    (fv, k), (uv, _) = display_view(floor), display_view(unfly)
    pct = 100 * np.asarray(unfly.mean(("y", "x")).values, float)     # of the cells, not of the blocks shown
    paths.append(_figure(fv.load(), uv.load(), kind, _window_text(ds), out_dir / f"coverage_{kind}.png", k, pct))
    return paths


def plot_coverage(ds: xr.Dataset, path: Path) -> Path:
    """``path``: the PNG of the coverage floors of ``ds`` (one panel per threshold D_j, unflyable
    cells grey), as ``skyroute coverage`` draws it."""
    from skyroute.pipeline.maps import display_view

    floor = ds["coverage_floor"].astype(np.float32)
    unfly = ds["unflyable"] if "unflyable" in ds else xr.zeros_like(floor, dtype=bool)
    (fv, k), (uv, _) = display_view(floor), display_view(unfly)
    pct = 100 * np.asarray(unfly.mean(("y", "x")).values, float)
    return _figure(fv.load(), uv.load(), str(ds.attrs.get("dop_kind", "DOP")), _window_text(ds), Path(path), k, pct)


def _figure(floor: xr.DataArray, unfly: xr.DataArray, kind: str, window: str, path: Path, k: int = 1,
            unflyable_pct=None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    thr = floor["threshold"].values
    n = len(thr)
    extent = image_extent(floor)
    vals = floor.values
    finite = vals[np.isfinite(vals)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n + 0.8, 4.2), squeeze=False, layout="constrained")
    im = None
    for ax, j in zip(axes[0], range(n), strict=True):
        im = ax.imshow(vals[j], extent=extent, origin="upper", vmin=vmin, vmax=vmax,
                       cmap="viridis", interpolation="nearest")
        bad = np.asarray(unfly.values[j], dtype=bool)
        if bad.any():
            ax.imshow(np.where(bad, 1.0, np.nan), extent=extent, origin="upper",
                      cmap=ListedColormap(["0.55"]), vmin=0, vmax=1, interpolation="nearest")
        pct = 100 * bad.mean() if unflyable_pct is None else unflyable_pct[j]
        ax.set_title(f"{kind} < {thr[j]:g}  ({pct:.1f}% unflyable)")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.tick_params(labelsize=7)
        ax.locator_params(axis="x", nbins=4)   # 7-digit UTM eastings on a narrow panel
        add_map_furniture(ax)
    datum = "\n".join(textwrap.wrap(str(floor.attrs.get("vertical_datum", "")), 36)[:2])
    fig.colorbar(im, ax=axes[0].tolist(), label="coverage floor [m]" + (f"\n{datum}" if datum else ""),
                 shrink=0.85)
    title = f"GNSS coverage maps, {kind}; {window}; grey = unflyable"
    if k > 1:
        title += f"; shown as the max over {k} x {k} cells"
    fig.suptitle("\n".join(textwrap.wrap(title, max(40, int(11 * (4.2 * n + 0.8))))))   # one narrow panel: wrap
    grow_until_unclipped(fig)   # a long suptitle over few narrow panels
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

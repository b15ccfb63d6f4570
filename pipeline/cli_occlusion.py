"""``skyroute visibility-height``: visibility height of one satellite direction as a GeoTIFF."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from skyroute.pipeline.cli import FiniteFloat
from skyroute.pipeline.errors import CRSError, DataError, SkyrouteError


@click.command("visibility-height")
@click.option("--surface", "surface_path", required=True,
              type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Surface model GeoTIFF (terrain + buildings) [m], one band, north-up, "
                   "projected CRS in metres.  Nodata cells are holes.")
@click.option("--az-deg", type=FiniteFloat(), required=True,
              help="Satellite azimuth [deg], clockwise from the raster's GRID north (the +y "
                   "axis of its CRS), not true north: convert true azimuths with "
                   "skyroute.stages.occlusion.grid_azimuth_deg.")
@click.option("--el-deg", type=FiniteFloat(), required=True,
              help="Satellite elevation above the horizon [deg], in (0, 90].")
@click.option("--out", "out_path", required=True,
              type=click.Path(dir_okay=False, path_type=Path),
              help="Output GeoTIFF: float32 visibility height [m] on the same grid and CRS.")
@click.option("--fill-nan/--no-fill-nan", default=False, show_default=True,
              help="Fill nodata holes of the surface with the nearest valid height (else "
                   "holes are an error).")
def visibility_height_command(surface_path: Path, az_deg: float, el_deg: float, out_path: Path,
                              fill_nan: bool) -> None:
    """Write the visibility height of one satellite direction: the lowest altitude [m] at each
    cell from which the satellite is in line of sight (cells are flat-topped prisms)."""
    import rioxarray

    from skyroute.pipeline.outfolder import check_replaceable, write_single_file
    from skyroute.stages.base import note_input
    from skyroute.stages.occlusion import visibility_height

    note_input(surface_path)
    check_replaceable(out_path, "--out")   # before any work: never the surface itself, nor a user's file
    try:
        da = rioxarray.open_rasterio(surface_path, masked=True)
    except Exception as exc:  # rasterio raises several error types
        raise DataError(f"cannot read surface {surface_path}: {exc}") from exc
    if da.sizes.get("band", 1) != 1:
        raise DataError(f"{surface_path} has {da.sizes['band']} bands; give a one-band surface")
    if "band" in da.dims:
        da = da.squeeze("band", drop=True)
    crs = da.rio.crs
    if crs is None or not crs.is_projected:
        raise CRSError(f"{surface_path} is in {'no CRS' if crs is None else repr(crs.to_string())}, not a "
                       "projected CRS in metres: reproject it first, e.g. `gdalwarp -t_srs EPSG:326NN "
                       f"{surface_path.name} out.tif` with its UTM zone")
    da = da.astype(np.float32)
    vh = visibility_height(da, az_deg, el_deg, azimuth="grid",
                           fill_nan="nearest" if fill_nan else None)
    vh = vh.drop_vars([c for c in ("azimuth_deg", "grid_azimuth_deg", "elevation_deg")
                       if c in vh.coords])
    try:
        write_single_file(out_path, lambda tmp: vh.rio.to_raster(tmp, dtype="float32"))
    except SkyrouteError:
        raise
    except Exception as exc:
        raise DataError(f"cannot write {out_path}: {exc}") from exc
    click.echo(f"wrote {out_path}: visibility height az={az_deg:g} deg (grid) el={el_deg:g} deg, "
               f"{float(vh.min()):.1f}..{float(vh.max()):.1f} m")

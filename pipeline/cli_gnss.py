"""``skyroute sky``: visible GNSS satellites and DOP at one place and time, from almanacs."""

from __future__ import annotations

import datetime as _dt
import json
import warnings

import click
import numpy as np

from skyroute.pipeline.cli import FiniteFloat
from skyroute.pipeline.errors import InputError


def _parse_time(text: str) -> np.datetime64:
    """UTC ``datetime64[ns]`` from ISO 8601 (``Z``/offset honoured, naive = UTC)."""
    try:
        t = _dt.datetime.fromisoformat(text.strip())
    except ValueError:
        raise InputError(f"--time {text!r} is not ISO 8601; write e.g. 2020-01-01T12:00:00Z") from None
    if t.tzinfo is not None:
        t = t.astimezone(_dt.UTC).replace(tzinfo=None)
    return np.datetime64(t, "ns")


@click.command("sky")
@click.option("--almanac", "almanacs", multiple=True, required=True,
              type=click.Path(dir_okay=False),
              help="Almanac file: YUMA, SEM or RINEX 2/3 navigation. Repeat to combine "
                   "constellations (e.g. GPS + Galileo).")
@click.option("--time", "time_text", required=True, metavar="ISO8601",
              help="Epoch in UTC, e.g. 2020-01-01T12:00:00Z (a naive time is taken as UTC).")
@click.option("--lat", "lat_deg", type=FiniteFloat(), metavar="DEG", required=True, help="Geodetic latitude [deg], WGS 84.")
@click.option("--lon", "lon_deg", type=FiniteFloat(), metavar="DEG", required=True, help="Longitude [deg], WGS 84.")
@click.option("--height", "height_m", type=FiniteFloat(), metavar="M", default=0.0, show_default=True,
              help="Ellipsoidal height [m].")
@click.option("--mask-deg", type=FiniteFloat(), metavar="DEG", default=5.0, show_default=True,
              help="Elevation mask [deg], 0..60.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of a table.")
def sky_command(almanacs: tuple[str, ...], time_text: str, lat_deg: float, lon_deg: float,
                height_m: float, mask_deg: float, as_json: bool) -> None:
    """List the satellites visible above the elevation mask at one place and time, with their
    azimuth/elevation and ECEF position, and the GDOP/PDOP/HDOP/VDOP/TDOP of that geometry.

    \b
    Example:
      skyroute sky --almanac yuma.txt --almanac alm_gal_ed259.txt \\
          --time 2020-01-03T12:00:00Z --lat 60.17 --lon 24.94 --height 30
    """
    from skyroute.stages.almanac import sky_geometry

    t = _parse_time(time_text)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = sky_geometry(list(almanacs), [t], lat_deg, lon_deg, height_m, mask_deg=mask_deg)
    notes = [str(w.message) for w in caught]
    g = ds.isel(time=0)
    vis = g.where(g["above_mask"], drop=True).sortby("el_deg", ascending=False)
    sats = [{"id": str(s), "az_deg": round(float(vis["az_deg"].sel(sat=s)), 3),
             "el_deg": round(float(vis["el_deg"].sel(sat=s)), 3),
             "kind": str(ds["kind"].sel(sat=s).item()) if "kind" in ds else "almanac",
             "ecef_m": [round(float(vis[v].sel(sat=s)), 1) for v in ("x_ecef", "y_ecef", "z_ecef")]}
            for s in vis["sat"].values]
    # +inf = no fix (stages.dop convention): JSON null, "no fix" in the table
    dops = {k.upper(): (None if not np.isfinite(float(g[k])) else round(float(g[k]), 3))
            for k in ("gdop", "pdop", "hdop", "vdop", "tdop")}
    if as_json:
        click.echo(json.dumps({"time_utc": str(np.datetime_as_string(t, unit="s")) + "Z",
                               "site": {"lat_deg": lat_deg, "lon_deg": lon_deg, "height_m": height_m},
                               "mask_deg": mask_deg, "almanacs": list(almanacs),
                               "n_visible": len(sats), "satellites": sats, "dop": dops,
                               "warnings": notes}, indent=2))
        return
    for n in notes:
        click.echo(f"warning: {n}", err=True)
    click.echo(f"{np.datetime_as_string(t, unit='s')}Z  lat {lat_deg:.5f}  lon {lon_deg:.5f}  "
               f"h {height_m:.1f} m  mask {mask_deg:g} deg: {len(sats)} satellites visible")
    click.echo(f"{'sat':<5}{'az_deg':>9}{'el_deg':>9}{'x_ecef_m':>15}{'y_ecef_m':>15}{'z_ecef_m':>15}")
    for s in sats:
        x, y, z = s["ecef_m"]
        flag = "  (standard constellation, idealised)" if s["kind"] == "standard" else ""
        click.echo(f"{s['id']:<5}{s['az_deg']:9.2f}{s['el_deg']:9.2f}{x:15.1f}{y:15.1f}{z:15.1f}{flag}")
    if any(v is None for v in dops.values()):
        click.echo("DOP: no fix (fewer than 4 satellites above the mask, or a singular geometry)")
    else:
        click.echo("  ".join(f"{k} {v:.2f}" for k, v in dops.items()))

"""Heights in WGS 84: geoid models (EGM96, EGM2008) and the scenario's vertical datum.

The maps keep heights in the surface model's vertical datum (``vertical_datum``): EGM96 for
SRTM, a national datum for lidar, or a flat *local ground* at 0 m for OSM-only cities.  ASTM
F3548 operational intents need WGS 84 ellipsoidal heights (``reference: W84``), Google Earth's
KML ``absolute`` altitudes and QGroundControl's home altitude are heights above mean sea level
(EGM96).  This module converts between them:

``h_ellipsoid = H_geoid + N(lon, lat)``, ``N`` the geoid undulation of the model, bilinear in
the model's grid (EGM96: the NGA 15' grid ``egm96_15.gtx``; EGM2008: ``egm08_25.gtx``), read
through PROJ's ``vgridshift`` with the grid file given by its **full path**.

Offline safety: ``pyproj.Transformer.from_crs("EPSG:4326+5773", "EPSG:4979")`` needs
``us_nga_egm96_15.tif`` from PROJ's network CDN; without it pyproj silently falls back to a
"ballpark" operation that leaves the height unchanged (N = 0, an error of up to 107 m).  Here a
grid is looked up on disk only (:func:`find_geoid_grid`: ``$SKYROUTE_GEOID_DIR``, then the
system's PROJ folders ``$PROJ_DATA`` / ``$PROJ_LIB``, pyproj's data folder, ``/usr/share/proj``,
``/usr/local/share/proj`` (Debian / Ubuntu ship ``egm96_15.gtx`` in the ``proj-data``
package), then the EGM96 grid shipped with skyroute, :data:`SHIPPED_EGM96`: the same NGA 15'
nodes as ``egm96_15.gtx``, bit for bit, as a compressed GeoTIFF, so EGM96 works on a fresh
machine) and a missing grid is an error that says how to get it, never a zero.
``SKYROUTE_GEOID_SYSTEM_DIRS=none`` skips the system's PROJ folders (a fresh machine's lookup,
for checks).  :func:`pyproj_skips_geoid` detects pyproj's silent fallback.

Local ground: a surface model on flat local ground (OSM-only cities) has heights above the
ground; ``data.ground: {height_m, vertical_datum}`` says where that 0 m lies
(:class:`HeightReference`).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skyroute.stages.base import DataError, InputError

__all__ = ["GEOID_GRIDS", "SHIPPED_EGM96", "HeightReference", "datum_kind", "find_geoid_grid", "geoid_undulation_m",
           "height_reference", "pyproj_skips_geoid", "to_ellipsoidal_m", "from_ellipsoidal_m"]

#: grid file names per geoid model (the first found is used)
GEOID_GRIDS: dict[str, tuple[str, ...]] = {
    "EGM96": ("egm96_15.gtx", "us_nga_egm96_15.tif", "egm96_15.tif"),
    "EGM2008": ("egm08_25.gtx", "us_nga_egm08_25.tif"),
}
#: the EGM96 15' grid shipped in the package (public domain, NGA; ``catalogs/data/ATTRIBUTION.md``):
#: the nodes of PROJ's ``egm96_15.gtx`` as a lossless DEFLATE GeoTIFF, found when no other folder has one
#: (``skyroute.stages`` and ``skyroute.catalogs`` are sibling folders, installed or in the clone)
SHIPPED_EGM96 = Path(__file__).resolve().parent.parent / "catalogs" / "data" / "egm96_15.tif"
#: ``$SKYROUTE_GEOID_SYSTEM_DIRS`` values that skip the system's PROJ folders
_NO_SYSTEM_DIRS = ("none", "0", "no", "off", "false")
#: the vertical CRS (EPSG) of each model, for :func:`pyproj_skips_geoid`
_EPSG_VERTICAL = {"EGM96": 5773, "EGM2008": 3855}
LOCAL_GROUND_PREFIX = "local ground"


def datum_kind(vertical_datum: str) -> str | None:
    """``"EGM96"``, ``"EGM2008"``, ``"ellipsoid"`` (WGS 84 ellipsoidal heights), ``"local"``
    (flat local ground of an OSM-only surface) or None (a datum this module cannot convert,
    e.g. NAP or N2000) for a ``vertical_datum`` text."""
    t = " ".join(str(vertical_datum).lower().replace("-", " ").split())
    if t.startswith(LOCAL_GROUND_PREFIX):
        return "local"
    if "egm96" in t or "egm 96" in t:
        return "EGM96"
    if "egm2008" in t or "egm 2008" in t or "egm08" in t:
        return "EGM2008"
    if "ellipsoid" in t and ("wgs 84" in t or "wgs84" in t or t == "ellipsoid" or "ellipsoidal" in t):
        return "ellipsoid"
    return None


def _search_dirs(extra: Sequence[Path | str] | None) -> list[Path]:
    """Folders tried for a grid, in order: ``extra``, ``$SKYROUTE_GEOID_DIR``, the system's PROJ
    folders (unless ``$SKYROUTE_GEOID_SYSTEM_DIRS`` is ``none``), the shipped grid's folder."""
    dirs: list[Path] = [Path(d) for d in (extra or ())]
    system = os.environ.get("SKYROUTE_GEOID_SYSTEM_DIRS", "").strip().lower() not in _NO_SYSTEM_DIRS
    for var in ("SKYROUTE_GEOID_DIR", "PROJ_DATA", "PROJ_LIB") if system else ("SKYROUTE_GEOID_DIR",):
        v = os.environ.get(var)
        if v:
            dirs.extend(Path(p) for p in v.split(os.pathsep) if p)
    if system:
        try:
            import pyproj

            dirs.append(Path(pyproj.datadir.get_data_dir()))
        except Exception:  # noqa: BLE001 - a broken pyproj data dir only removes one candidate
            pass
        dirs += [Path("/usr/share/proj"), Path("/usr/local/share/proj")]
    dirs.append(SHIPPED_EGM96.parent)   # skyroute/stages/.. = skyroute/catalogs (installed or in the clone)
    return dirs


def find_geoid_grid(model: str = "EGM96", search_dirs: Sequence[Path | str] | None = None) -> Path:
    """Path of the grid file of geoid ``model`` (``"EGM96"`` or ``"EGM2008"``) on this machine.

    ``search_dirs``: folders tried first (then the ones of the module docstring).  DataError
    (what to install) when no folder holds it; PROJ's network grids are never used."""
    if model not in GEOID_GRIDS:
        raise InputError(f"unknown geoid model {model!r}; use one of {', '.join(GEOID_GRIDS)}")
    tried = _search_dirs(search_dirs)
    for d in tried:
        for name in GEOID_GRIDS[model]:
            p = d / name
            if p.is_file():
                return p
    hint = (f"skyroute's own grid {SHIPPED_EGM96.name} is missing from its catalogs/data folder (reinstall "
            "skyroute); on Debian / Ubuntu: apt-get install proj-data (it ships /usr/share/proj/egm96_15.gtx)"
            if model == "EGM96" else "download egm08_25.gtx (PROJ-data / OSGeo) to a folder")
    raise DataError(f"{model} geoid heights need the grid {' or '.join(GEOID_GRIDS[model])}, found in none of "
                    f"{', '.join(str(d) for d in dict.fromkeys(tried))}; {hint}, or set SKYROUTE_GEOID_DIR to the "
                    "folder holding it (PROJ's network grids are not reachable offline, and pyproj would then "
                    "skip the geoid silently: refusing instead)")


@functools.lru_cache(maxsize=4)
def _transformer(grid: str):
    from pyproj import Transformer
    from pyproj.exceptions import ProjError

    pipe = ("+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            f"+step +proj=vgridshift +grids={grid} +multiplier=1 "
            "+step +proj=unitconvert +xy_in=rad +xy_out=deg")
    try:
        return Transformer.from_pipeline(pipe)
    except ProjError as exc:
        raise DataError(f"cannot read the geoid grid {grid}: {exc}") from None


def geoid_undulation_m(lon_deg, lat_deg, model: str = "EGM96",
                       search_dirs: Sequence[Path | str] | None = None) -> np.ndarray:
    """Geoid undulation N [m] of ``model`` at WGS 84 ``lon_deg, lat_deg`` [deg] (arrays
    broadcast): ellipsoidal height = geoid height + N.  Bilinear in the model's grid."""
    grid = find_geoid_grid(model, search_dirs)
    lon, lat = np.broadcast_arrays(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
    if not (np.all(np.isfinite(lon)) and np.all(np.isfinite(lat)) and np.all(np.abs(lat) <= 90)):
        raise InputError("geoid_undulation_m: longitudes and latitudes must be finite, |lat| <= 90 deg")
    _, _, n = _transformer(str(grid)).transform(lon.ravel(), lat.ravel(), np.zeros(lon.size))
    n = np.asarray(n, float).reshape(lon.shape)
    if not np.all(np.isfinite(n)) or np.any(np.abs(n) > 200):
        raise DataError(f"the geoid grid {grid} gave no value at some points (outside its extent?)")
    return n


def pyproj_skips_geoid(model: str = "EGM96") -> bool:
    """True when pyproj's own ``EPSG:4326+<model> -> EPSG:4979`` transformation would skip
    the geoid (its best operation needs a grid that is not available, so it falls back to a
    ballpark one with N = 0), the silent failure this module avoids."""
    import warnings

    from pyproj.transformer import TransformerGroup

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # "Best transformation is not available": the point
        tg = TransformerGroup(f"EPSG:4326+{_EPSG_VERTICAL[model]}", "EPSG:4979", always_xy=True)
    return not tg.best_available


def to_ellipsoidal_m(lon_deg, lat_deg, height_m, vertical_datum: str,
                     search_dirs: Sequence[Path | str] | None = None) -> np.ndarray:
    """WGS 84 ellipsoidal heights [m] of ``height_m`` given in ``vertical_datum`` (EGM96,
    EGM2008 or WGS 84 ellipsoid; InputError for any other datum)."""
    kind = datum_kind(vertical_datum)
    h = np.asarray(height_m, float)
    if kind == "ellipsoid":
        return h + 0.0
    if kind in GEOID_GRIDS:
        return h + geoid_undulation_m(lon_deg, lat_deg, kind, search_dirs)
    raise InputError(f"heights in the vertical datum {vertical_datum!r} cannot be converted to WGS 84: give them "
                     "in 'EGM96 geoid', 'EGM2008 geoid' or 'WGS 84 ellipsoid' (for a scenario: data.ground)")


def from_ellipsoidal_m(lon_deg, lat_deg, h_ellipsoidal_m, vertical_datum: str,
                       search_dirs: Sequence[Path | str] | None = None) -> np.ndarray:
    """Inverse of :func:`to_ellipsoidal_m`: heights [m] in ``vertical_datum``."""
    zero = to_ellipsoidal_m(lon_deg, lat_deg, np.zeros_like(np.asarray(h_ellipsoidal_m, float)), vertical_datum,
                            search_dirs)
    return np.asarray(h_ellipsoidal_m, float) - zero


@dataclass(frozen=True)
class HeightReference:
    """How a height of the surface model's datum becomes an absolute height: ``z + offset_m``
    is a height in ``datum`` (``offset_m`` = ``data.ground.height_m`` for local ground, 0
    otherwise); ``search_dirs``: extra folders for the geoid grids."""

    surface_datum: str
    datum: str
    offset_m: float = 0.0
    search_dirs: tuple[str, ...] = ()

    def ellipsoidal_m(self, lon_deg, lat_deg, z_m) -> np.ndarray:
        """WGS 84 ellipsoidal heights [m] of surface-datum heights ``z_m``."""
        return to_ellipsoidal_m(lon_deg, lat_deg, np.asarray(z_m, float) + self.offset_m, self.datum,
                                self.search_dirs)

    def egm96_m(self, lon_deg, lat_deg, z_m) -> np.ndarray:
        """Heights above mean sea level [m] (EGM96 geoid, Google Earth's and MAVLink's AMSL)."""
        z = np.asarray(z_m, float) + self.offset_m
        if datum_kind(self.datum) == "EGM96":
            return z + 0.0
        h = to_ellipsoidal_m(lon_deg, lat_deg, z, self.datum, self.search_dirs)
        return from_ellipsoidal_m(lon_deg, lat_deg, h, "EGM96 geoid", self.search_dirs)


def height_reference(surface_datum: str, ground_height_m: float | None = None, ground_datum: str | None = None,
                     search_dirs: Sequence[Path | str] = ()) -> HeightReference:
    """The :class:`HeightReference` of a surface model in ``surface_datum``.

    ``ground_height_m`` [m], ``ground_datum``: the scenario's ``data.ground`` (where the surface
    model's 0 m lies): required when the surface datum is local ground or one this module
    cannot convert (InputError naming ``data.ground`` otherwise); when given it always applies."""
    dirs = tuple(str(d) for d in search_dirs)
    if ground_height_m is not None:
        if ground_datum is None or datum_kind(ground_datum) not in ("EGM96", "EGM2008", "ellipsoid"):
            raise InputError(f"data.ground.vertical_datum {ground_datum!r}: use 'EGM96 geoid', 'EGM2008 geoid' or "
                             "'WGS 84 ellipsoid'")
        if not np.isfinite(ground_height_m):
            raise InputError("data.ground.height_m must be a finite number [m]")
        return HeightReference(surface_datum, ground_datum, float(ground_height_m), dirs)
    kind = datum_kind(surface_datum)
    if kind == "local":
        raise InputError(f"the surface model's heights are above a flat local ground ({surface_datum!r}): absolute "
                         "(WGS 84) heights need the scenario setting data.ground: {height_m: <height of the ground "
                         "[m]>, vertical_datum: 'EGM96 geoid'} (or 'EGM2008 geoid' / 'WGS 84 ellipsoid')")
    if kind is None:
        raise InputError(f"the surface model's vertical datum {surface_datum!r} has no conversion to WGS 84 here; "
                         "set data.ground: {height_m: <height of the datum's 0 m>, vertical_datum: 'EGM96 geoid'} "
                         "(or 'EGM2008 geoid' / 'WGS 84 ellipsoid')")
    return HeightReference(surface_datum, surface_datum, 0.0, dirs)

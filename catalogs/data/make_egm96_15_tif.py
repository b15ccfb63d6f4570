"""Generate ``egm96_15.tif`` (the EGM96 geoid undulations on NGA's 15' grid, shipped so that
absolute heights work without ``proj-data``) from PROJ's ``egm96_15.gtx``.

Run ``python catalogs/data/make_egm96_15_tif.py [SOURCE.gtx]`` (default
``/usr/share/proj/egm96_15.gtx``, Debian / Ubuntu package ``proj-data``).  The conversion is
lossless: the same 721 x 1440 float32 nodes (lat -90..90, lon -180..179.75 deg, 0.25 deg
apart), stored as a DEFLATE (floating-point predictor) GeoTIFF in PROJ's grid layout
(``PixelIsPoint``, ``TYPE=VERTICAL_OFFSET_GEOGRAPHIC_TO_VERTICAL``), which PROJ's ``vgridshift``
reads like the ``.gtx`` (same nodes, same bilinear interpolation, same longitude wrap).  The
script checks the written values bit for bit against the source.

Source: EGM96, NGA / NASA (public domain), as distributed by PROJ (``egm96_15.gtx``, derived
from NGA's ``WW15MGH.GRD``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import Affine

OUT = Path(__file__).with_name("egm96_15.tif")


def main(src: str = "/usr/share/proj/egm96_15.gtx") -> None:
    with rasterio.open(src) as s:
        a = s.read(1)
        tr = s.transform
        crs = s.crs
    assert a.shape == (721, 1440) and a.dtype == np.float32 and np.isfinite(a).all()
    assert tr == Affine(0.25, 0.0, -180.125, 0.0, -0.25, 90.125), tr
    profile = dict(driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype="float32", crs=crs,
                   transform=tr, compress="deflate", predictor=3, zlevel=9, tiled=True, blockxsize=256,
                   blockysize=256, interleave="band")
    with rasterio.open(OUT, "w", **profile) as d:
        d.update_tags(AREA_OR_POINT="Point", TYPE="VERTICAL_OFFSET_GEOGRAPHIC_TO_VERTICAL",
                      area_of_use="World", grid_name="egm96_15",
                      target_crs_epsg_code="5773",
                      DESCRIPTION="EGM96 geoid undulation (NGA 15' grid), heights above the WGS 84 ellipsoid [m]",
                      source="egm96_15.gtx (PROJ), from NGA WW15MGH.GRD; public domain")
        d.update_tags(1, UNITTYPE="metre")
        d.set_band_description(1, "geoid_undulation")
        d.write(a, 1)
    with rasterio.open(OUT) as d:
        b = d.read(1)
        assert d.tags().get("AREA_OR_POINT") == "Point" and d.transform == tr
    assert b.dtype == a.dtype and b.tobytes() == a.tobytes(), "the GeoTIFF differs from the source"
    print(f"{OUT}: {OUT.stat().st_size / 1e6:.2f} MB, identical to {src}")


if __name__ == "__main__":
    main(*sys.argv[1:2])

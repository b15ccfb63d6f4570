"""Geoid heights and the scenario's height reference (stages/geoid.py)."""

from __future__ import annotations

import numpy as np
import pytest

from skyroute.stages import geoid
from skyroute.stages.base import DataError, InputError

# NGA's EGM96 test data: earth-info.nga.mil/GandG/wgs84/gravitymod/egm96/readme.txt (the
# "input.dat" points and the geoid heights of "outintpt.dat" computed by NGA's INTPT.F from the
# 15' grid WW15MGH.GRD); the same six values are quoted e.g. by GNU Octave's geoid tests.
NGA_EGM96 = [  # lat [deg], lon [deg, 0..360], N [m]
    (38.6281550, 269.7791550, -31.628),   # Illinois
    (-14.6212170, 305.0211140, -2.969),   # Brazil
    (46.8743190, 102.4487290, -43.575),   # Mongolia
    (-23.6174460, 133.8747120, 15.871),   # Australia
    (38.6254730, 359.9995000, 50.066),    # Spain (near the prime meridian, from the west)
    (-0.4667440, 0.0023000, 17.329),      # Gulf of Guinea (from the east)
]


def _have_egm96() -> bool:
    try:
        geoid.find_geoid_grid("EGM96")
        return True
    except DataError:
        return False


needs_egm96 = pytest.mark.skipif(not _have_egm96(), reason="egm96_15.gtx not installed (apt-get install proj-data)")


@needs_egm96
def test_egm96_undulation_matches_nga_test_points():
    lat = np.array([p[0] for p in NGA_EGM96])
    lon = np.array([p[1] for p in NGA_EGM96])
    lon = np.where(lon > 180, lon - 360, lon)
    n = geoid.geoid_undulation_m(lon, lat, "EGM96")
    ref = np.array([p[2] for p in NGA_EGM96])
    assert np.max(np.abs(n - ref)) < 0.1   # bilinear on the 15' grid: a few cm here, limit asked < 1 m


@needs_egm96
def test_ellipsoidal_round_trip_and_reference():
    lon, lat = 24.94, 60.17   # Helsinki
    n = geoid.geoid_undulation_m(lon, lat)
    assert 15.0 < float(n) < 20.0   # EGM96 N in southern Finland is ~17-18 m
    h = geoid.to_ellipsoidal_m(lon, lat, 30.0, "EGM96 geoid")
    assert float(h) == pytest.approx(30.0 + float(n), abs=1e-9)
    assert float(geoid.from_ellipsoidal_m(lon, lat, h, "EGM96 geoid")) == pytest.approx(30.0, abs=1e-9)
    assert float(geoid.to_ellipsoidal_m(lon, lat, 30.0, "WGS 84 ellipsoid")) == 30.0
    ref = geoid.height_reference("local ground (flat terrain, heights above ground level)", 12.0, "EGM96 geoid")
    assert float(ref.ellipsoidal_m(lon, lat, 50.0)) == pytest.approx(62.0 + float(n), abs=1e-9)
    assert float(ref.egm96_m(lon, lat, 50.0)) == pytest.approx(62.0, abs=1e-12)
    ell = geoid.height_reference("local ground", 80.0, "WGS 84 ellipsoid")
    assert float(ell.egm96_m(lon, lat, 0.0)) == pytest.approx(80.0 - float(n), abs=1e-9)


def test_missing_grid_is_refused_not_zero(monkeypatch, tmp_path):
    """Without the grid on disk: a DataError saying what to install, never N = 0 (which is
    what pyproj's own transformation does when its network grid is unreachable)."""
    monkeypatch.setattr(geoid, "_search_dirs", lambda extra: [tmp_path])
    with pytest.raises(DataError, match="apt-get install proj-data"):
        geoid.geoid_undulation_m(24.94, 60.17)
    with pytest.raises(DataError, match="SKYROUTE_GEOID_DIR"):
        geoid.height_reference("EGM96 geoid").ellipsoidal_m(24.94, 60.17, 10.0)


def test_pyproj_silent_skip_is_detected():
    """pyproj's EPSG route returns the input height unchanged when it lacks the CDN grid; the
    detector says so exactly when that happens."""
    import warnings

    from pyproj import Transformer

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # pyproj: "Best transformation is not available"
        h = Transformer.from_crs("EPSG:4326+5773", "EPSG:4979", always_xy=True).transform(24.94, 60.17, 30.0)[2]
    skipped = abs(h - 30.0) < 1e-9
    assert geoid.pyproj_skips_geoid("EGM96") == skipped


def test_datum_kinds_and_errors():
    assert geoid.datum_kind("EGM96 geoid") == "EGM96"
    assert geoid.datum_kind("EGM2008") == "EGM2008"
    assert geoid.datum_kind("WGS 84 ellipsoid") == "ellipsoid"
    assert geoid.datum_kind("local ground (flat terrain, heights above ground level)") == "local"
    assert geoid.datum_kind("NAP") is None
    with pytest.raises(InputError, match="data.ground"):
        geoid.height_reference("local ground (flat terrain, heights above ground level)")
    with pytest.raises(InputError, match="data.ground"):
        geoid.height_reference("NAP")
    with pytest.raises(InputError, match="data.ground.vertical_datum"):
        geoid.height_reference("NAP", 0.0, "N2000")
    assert geoid.height_reference("EGM96 geoid").offset_m == 0.0

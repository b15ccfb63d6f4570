"""What a new user meets on a fresh machine (issue 35, items 6, 7, 10 and 11): the EGM96 grid
shipped with the package, a copied catalog scenario, `skyroute inspect` on the mission points,
the fleet's departure window.

``.ci/run`` runs :func:`test_every_scenario_has_absolute_heights_without_system_grids` again in a
new virtual environment holding the built wheel (not the clone), with
``SKYROUTE_GEOID_SYSTEM_DIRS=none``, and there also ``skyroute run rotterdam-canyon`` and
``skyroute fleet helsinki-medical --missions 2 --seed 1``."""

from __future__ import annotations

import fnmatch
import re
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.errors import ScenarioError, SkyrouteError
from skyroute.pipeline.settings import catalog_dir, load_scenario, scenario_paths
from skyroute.stages import geoid
from skyroute.stages.base import DataError

REPO = Path(__file__).resolve().parents[1]
SYSTEM_GTX = Path("/usr/share/proj/egm96_15.gtx")

# Published EGM96 geoid heights N [m] (lon, lat [deg]): the UNAVCO geoid height calculator
# (www.unavco.org/software/geodetic-utilities/geoid-height-calculator), values to 1 cm as quoted
# by CesiumGS/cesium-native CesiumGeospatial/test/TestEarthGravitationalModel1996Grid.cpp
# (testCases and boundsCases); lat 0 lon 0 is also NGA's calculator's 17.16 m.
UNAVCO_EGM96 = [
    (0.0, 0.0, 17.16),
    (180.0, 0.0, 21.15),
    (-180.0, 0.0, 21.15),       # the same node from the other side: the grid wraps in longitude
    (0.0, -90.0, -29.53),
    (135.89012584487307, 11.046411138991914, 57.79),
    (77.26636943208759, 11.790177979066698, -90.03),     # the Indian Ocean low
    (6.9461874737732465, 57.95503483268874, 41.76),
    (179.78766535213848, -66.77911223257036, -57.37),    # next to the antimeridian
]
# NGA's own EGM96 test points (earth-info.nga.mil .../egm96/readme.txt, outintpt.dat, computed by
# NGA's INTPT.F with a spline on the same 15' grid, hence a few cm from bilinear); lon in 0..360
NGA_EGM96 = [(38.6281550, 269.7791550, -31.628), (46.8743190, 102.4487290, -43.575),
             (-23.6174460, 133.8747120, 15.871)]


@pytest.fixture
def fresh(monkeypatch):
    """A fresh machine's grid lookup: no system PROJ folder, no $SKYROUTE_GEOID_DIR."""
    monkeypatch.setenv("SKYROUTE_GEOID_SYSTEM_DIRS", "none")
    monkeypatch.delenv("SKYROUTE_GEOID_DIR", raising=False)


# ------------------------------------------------------------------------------ item 6: the EGM96 grid
@pytest.mark.skipif(not SYSTEM_GTX.is_file(), reason=f"{SYSTEM_GTX} not installed (proj-data): nothing to compare")
def test_shipped_grid_is_the_gtx_bit_for_bit():
    """The shipped GeoTIFF holds the nodes of PROJ's egm96_15.gtx exactly (same bytes, same
    georeferencing), and PROJ's vgridshift gives the same undulations from both, wrap included."""
    import rasterio

    with rasterio.open(SYSTEM_GTX) as a, rasterio.open(geoid.SHIPPED_EGM96) as b:
        ga, gb = a.read(1), b.read(1)
        assert a.transform == b.transform and a.crs == b.crs and b.tags()["AREA_OR_POINT"] == "Point"
    assert ga.dtype == gb.dtype == np.float32 and ga.shape == gb.shape == (721, 1440)
    assert ga.tobytes() == gb.tobytes()
    rng = np.random.default_rng(35)
    lon = np.r_[rng.uniform(-180, 180, 3000), -180.0, 180.0, 179.9, 0.0]
    lat = np.r_[rng.uniform(-90, 90, 3000), 0.0, 0.0, 89.99, -90.0]

    def n(grid):
        return np.asarray(geoid._transformer(str(grid)).transform(lon, lat, np.zeros(lon.size))[2])

    assert np.array_equal(n(SYSTEM_GTX), n(geoid.SHIPPED_EGM96))


def test_shipped_grid_found_and_matches_published_values(fresh):
    assert geoid.find_geoid_grid("EGM96") == geoid.SHIPPED_EGM96
    assert geoid.SHIPPED_EGM96.stat().st_size < 3_000_000        # compressed: the gtx is 4.15 MB
    lon, lat, ref = (np.array(c) for c in zip(*UNAVCO_EGM96, strict=True))
    n = geoid.geoid_undulation_m(lon, lat, "EGM96")
    assert np.max(np.abs(n - ref)) < 0.006      # the calculator rounds to 1 cm
    lat, lon, ref = (np.array(c) for c in zip(*NGA_EGM96, strict=True))
    n = geoid.geoid_undulation_m(np.where(lon > 180, lon - 360, lon), lat, "EGM96")
    assert np.max(np.abs(n - ref)) < 0.07       # NGA's spline vs bilinear: 2-6 cm at these points
    # a height above EGM96 becomes the ellipsoidal height at the equator / prime meridian
    assert float(geoid.to_ellipsoidal_m(0.0, 0.0, 100.0, "EGM96 geoid")) == pytest.approx(117.16, abs=0.006)


def test_grid_lookup_order(fresh, monkeypatch, tmp_path):
    """$SKYROUTE_GEOID_DIR first (a user's own grid), then the system's PROJ folders, the shipped
    grid last; without any: one DataError saying what to do."""
    own = tmp_path / "own"
    own.mkdir()
    (own / "egm96_15.gtx").write_bytes(SYSTEM_GTX.read_bytes() if SYSTEM_GTX.is_file() else b"x")
    monkeypatch.setenv("SKYROUTE_GEOID_DIR", str(own))
    assert geoid.find_geoid_grid("EGM96") == own / "egm96_15.gtx"
    monkeypatch.delenv("SKYROUTE_GEOID_DIR")
    monkeypatch.setenv("PROJ_DATA", str(own))              # hidden with the system folders
    assert geoid.find_geoid_grid("EGM96") == geoid.SHIPPED_EGM96
    monkeypatch.delenv("SKYROUTE_GEOID_SYSTEM_DIRS")
    assert geoid.find_geoid_grid("EGM96") == own / "egm96_15.gtx"   # a system folder comes before the shipped grid
    monkeypatch.setenv("SKYROUTE_GEOID_SYSTEM_DIRS", "none")
    monkeypatch.setattr(geoid, "SHIPPED_EGM96", tmp_path / "gone" / "egm96_15.tif")   # a broken install
    with pytest.raises(DataError, match="reinstall skyroute.*apt-get install proj-data.*SKYROUTE_GEOID_DIR"):
        geoid.find_geoid_grid("EGM96")


def test_the_package_ships_the_grid():
    """`pip install .` installs catalogs/data/egm96_15.tif (a package-data pattern matches it)."""
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert cfg["package-dir"]["skyroute.catalogs"] == "catalogs"
    rel = geoid.SHIPPED_EGM96.relative_to(REPO / "catalogs").as_posix()
    assert any(fnmatch.fnmatch(rel, pat) for pat in cfg["package-data"]["skyroute.catalogs"])
    assert geoid.SHIPPED_EGM96.parent == catalog_dir() / "data"


def test_every_scenario_has_absolute_heights_without_system_grids(fresh):
    """Each shipped scenario's absolute heights (plan.kml, plan.plan's home, intent.json) work
    with the shipped grid alone: `skyroute inspect`'s check, and a height converted at the AOI
    centre by the scenario's own height reference."""
    from skyroute.pipeline.inspect import Inspection, _absolute, _surface_datum
    from skyroute.stages.geoid import datum_kind, height_reference

    names = sorted(scenario_paths())
    assert len(names) >= 12
    for name in names:
        sc = load_scenario(name)
        ins = Inspection(name, "scenario")
        _absolute(ins, sc, None)
        assert ins.data["absolute_heights"]["available"], (name, ins.data["absolute_heights"]["why_not"])
        g = sc.data.ground
        ref = height_reference(_surface_datum(sc, None), g.height_m if g else None, g.vertical_datum if g else None)
        xmin, ymin, xmax, ymax = sc.grid.bounds
        lon, lat = sc.grid.to_lonlat((xmin + xmax) / 2, (ymin + ymax) / 2)
        off = 0.0 if g is None else g.height_m
        h_amsl = float(ref.egm96_m(lon, lat, 10.0))
        h_ell = float(ref.ellipsoidal_m(lon, lat, 10.0))
        n = float(geoid.geoid_undulation_m(lon, lat))
        if datum_kind(ref.datum) == "EGM96":
            assert h_amsl == pytest.approx(10.0 + off) and h_ell == pytest.approx(10.0 + off + n), name
        else:                     # Rotterdam: NAP 0 m given as an ellipsoidal height
            assert h_ell == pytest.approx(10.0 + off) and h_amsl == pytest.approx(10.0 + off - n), name
        assert 10.0 < abs(n) < 60.0, (name, n)   # EGM96 N in these places: -36 (California) .. +47 m (Europe)


# ------------------------------------------------------------------------------ item 7: a copied scenario
def _relative_paths(name: str) -> int:
    from skyroute.pipeline.settings.io import PATH_KEYS

    def walk(node, key=""):
        if isinstance(node, dict):
            return sum(walk(v, k) for k, v in node.items())
        if isinstance(node, list):
            return sum(walk(v, key) for v in node)
        return int(isinstance(node, str) and key in PATH_KEYS and not Path(node).is_absolute())

    return walk(yaml.safe_load(scenario_paths()[name].read_text()))


def test_copied_catalog_yaml_resolves_to_the_shipped_data(tmp_path, monkeypatch):
    """A catalog YAML copied elsewhere: its `../data/...` paths resolve to the shipped files,
    each with one warning naming the key (it was five `data file not found` errors)."""
    src = scenario_paths()["helsinki-medical"]
    copy = tmp_path / "mine" / "helsinki-medical.yaml"
    copy.parent.mkdir()
    copy.write_text(src.read_text())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sc = load_scenario(copy)
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == _relative_paths("helsinki-medical") >= 4
    shipped = (catalog_dir() / "data" / "helsinki_center.osm.pbf").resolve()
    assert Path(sc.data.buildings.path) == shipped
    assert any(m.startswith("data.buildings.path: ../data/helsinki_center.osm.pbf is not next to the scenario "
                            f"({tmp_path / 'data' / 'helsinki_center.osm.pbf'}); using the file shipped with "
                            f"skyroute: {shipped}") for m in msgs), msgs
    assert any(m.startswith("data.almanacs[1]: ") for m in msgs)
    assert sc.data == load_scenario("helsinki-medical").data
    # `skyroute inspect` lists each as a warning with its key
    from skyroute.pipeline.inspect import inspect_target

    with monkeypatch.context() as m:     # the loading only: the map checks are not the point here
        m.setattr("skyroute.pipeline.inspect._scenario", lambda ins, sc: None)
        ins_keys = {k for lv, k, _ in inspect_target(copy).problems if lv == "warning"}
    assert {"data.buildings.path", "data.landuse", "data.almanacs[0]"} <= ins_keys
    # a file next to the YAML wins (no warning); a file found nowhere is still an error
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "yuma_2020-01-03.txt").write_text((catalog_dir() / "data" / "yuma_2020-01-03.txt").read_text())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sc = load_scenario(copy)
    assert Path(sc.data.almanacs[0]) == (tmp_path / "data" / "yuma_2020-01-03.txt").resolve()
    assert not any("almanacs[0]" in str(w.message) for w in caught)
    copy.write_text(src.read_text().replace("../data/alm_gal_ed259.txt", "../data/no_such_almanac.txt"))
    with pytest.raises(ScenarioError, match="no_such_almanac.txt"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load_scenario(copy)


def test_scenarios_copy_writes_absolute_paths_and_never_replaces(tmp_path):
    out = tmp_path / "edit"
    for name in sorted(scenario_paths()):
        res = CliRunner().invoke(main, ["scenarios", "--copy", name, str(out)])
        assert res.exit_code == 0, res.output
        dest = out / f"{name}.yaml"
        assert f"{name} -> {dest} ({_relative_paths(name)} data path(s) made absolute)" in res.output
        text = dest.read_text()
        assert "../data/" not in yaml.safe_dump(yaml.safe_load(text))      # every data path absolute
        with warnings.catch_warnings():
            warnings.simplefilter("error")      # no path falls back to the shipped folder: all absolute
            sc = load_scenario(dest)
        ref = load_scenario(name)
        assert sc.model_dump(exclude={"source_path"}) == ref.model_dump(exclude={"source_path"}), name
    src = scenario_paths()["rotterdam-canyon"].read_text()
    text = (out / "rotterdam-canyon.yaml").read_text()
    assert text.startswith("# copied from the skyroute catalog scenario rotterdam-canyon")
    comments = [ln for ln in src.splitlines() if ln.lstrip().startswith("#")]
    assert comments and all(c in text for c in comments)                 # comments kept
    # an existing file is never replaced (edited or not)
    (out / "rotterdam-canyon.yaml").write_text(text + "# my edit\n")
    res = CliRunner().invoke(main, ["scenarios", "--copy", "rotterdam-canyon", str(out)])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert [ln for ln in res.output.splitlines() if ln.startswith("error:")] == [
        f"error: --copy rotterdam-canyon {out}: {out / 'rotterdam-canyon.yaml'} exists and is not replaced; "
        "remove or rename it, or give another folder"]
    assert (out / "rotterdam-canyon.yaml").read_text().endswith("# my edit\n")
    res = CliRunner().invoke(main, ["scenarios", "--copy", "no-such-city", str(out)])
    assert res.exit_code == 2 and res.output.startswith("error: unknown scenario 'no-such-city'")


# ------------------------------------------------------------------------------ item 10: inspect the mission points
def _start_in_building(tmp_path) -> Path:
    from skyroute.pipeline.settings.io import copy_scenario

    dest, _ = copy_scenario("helsinki-medical", tmp_path)
    text = dest.read_text()
    new = re.sub(r"^  start: \{.*\}$", "  start: {x: 385620, y: 6671880, alt_agl_m: 30}", text, count=1, flags=re.M)
    assert new != text
    dest.write_text(new)
    return dest


def test_inspect_refuses_a_start_inside_a_building_as_plan_does(tmp_path):
    """The issue's reproduction: exit 0 and no word before; now the same line as `plan`'s
    refusal (tests/test_cli.py), from the same function (runner.check_mission)."""
    path = _start_in_building(tmp_path)
    res = CliRunner().invoke(main, ["inspect", str(path)])
    assert res.exit_code == 2, res.output
    errors = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert errors == ["error: mission.start: altitude 30 m above ground is inside a building or the terrain "
                      "(surface 70.0 m above ground there); raise alt_agl_m or move the point"]
    assert "mission points" in res.output and "goal above the surface" in res.output


def test_inspect_mission_points_without_a_building_nearby(monkeypatch, tmp_path):
    """A point whose window holds no building: the surface there is the ground (the surface
    stage's "AOI does not intersect any building" is not a problem of a point window)."""
    import skyroute.pipeline.inspect as insp
    import skyroute.pipeline.stages_builtin as sb
    from skyroute.pipeline.errors import DataError as PDataError

    real = sb.surface_stage
    calls = []

    def stage(*, settings):
        calls.append(settings.buildings_path)
        if settings.buildings_path is not None:
            raise PDataError(f"the AOI does not intersect any building of {settings.buildings_path}; check aoi.bounds")
        return real(settings=settings)

    monkeypatch.setattr(sb, "surface_stage", stage)
    sc = load_scenario("helsinki-medical")
    ins = insp.Inspection("helsinki-medical", "scenario")
    insp._mission_points(ins, sc)
    assert ins.problems == [] and calls[1::2] == [None, None]
    assert ins.facts["mission points"].startswith("start and goal above the surface")


# ------------------------------------------------------------------------------ item 11: the fleet's window
def test_fleet_default_window_is_what_the_gnss_maps_cover():
    from skyroute.pipeline.cli_fleet import default_window_min

    for name in sorted(scenario_paths()):
        gmin = load_scenario(name).gnss.window_min
        w = default_window_min(gmin, 10.0)
        assert w > 0 and w + 10.0 <= gmin, (name, gmin, w)    # the warning's condition never holds
    assert default_window_min(20.0, 10.0) == 10.0
    assert default_window_min(5.0, 10.0) == 5.0      # the delay alone is longer: the GNSS window (and the warning)
    assert default_window_min(0.0, 10.0) == 1.0


def test_fleet_front_door_draws_within_the_gnss_window(monkeypatch, tmp_path):
    """`skyroute fleet helsinki-medical --missions 2 --seed 1` draws its departures over
    gnss.window_min - --max-delay-min (20 - 10 min), not 120 min; --window-min still rules.
    The maps and the planning are stubbed: the draw's window is the point."""
    import types

    from pyproj import CRS

    import skyroute.pipeline.fleet as fleet

    seen = []

    def draw(sc, maps, n, seed, window_s, **kw):
        seen.append(window_s)
        raise SkyrouteError("stopped after the draw")

    fake_surface = types.SimpleNamespace(rio=types.SimpleNamespace(crs=CRS.from_epsg(32635)))
    monkeypatch.setattr(fleet, "fleet_maps", lambda sc, root: {"surface": {"surface": fake_surface}})
    monkeypatch.setattr(fleet, "draw_missions", draw)
    for extra, window_s in (([], 600.0), (["--max-delay-min", "5"], 900.0), (["--window-min", "30"], 1800.0)):
        res = CliRunner().invoke(main, ["fleet", "helsinki-medical", "--missions", "2", "--seed", "1", "-q",
                                        "--out", str(tmp_path / f"o{len(seen)}"), "--cache-dir",
                                        str(tmp_path / "cache"), *extra])
        assert res.exit_code == 2 and "error: stopped after the draw" in res.output, res.output
        assert seen[-1] == window_s
    res = CliRunner().invoke(main, ["fleet", "--help"])
    assert "gnss.window_min minus --max-delay-min" in " ".join(res.output.split()).replace("- ", "-")

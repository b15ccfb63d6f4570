"""`skyroute report` / report.html and the interactive map plan.html: the page's content checked
against the folder's own files (candidates.csv, tactical.csv, summary.json) with plain code, and
both pages opened in a real headless browser (Debian's chromium; skipped only without it)."""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from skyroute.pipeline.cli import main

DATA = Path(__file__).resolve().parents[1] / "catalogs" / "data"

SMALL = f"""
name: report-small
description: "A small <b>Helsinki</b> block & its report"
aoi: {{bounds_lonlat: [24.9385, 60.1650, 24.9430, 60.1700], resolution_m: 4.0}}
data:
  buildings: {{path: {DATA}/helsinki_center.osm.pbf, format: osm, storey_height_m: 3.0}}
  landuse: {DATA}/helsinki_center.osm.pbf
  osm_landing_sites: true
  wind: {{path: {DATA}/gfs_2011-01-15T12_wind.nc, time_utc: 2011-01-15T12:00:00Z, profile: levels}}
  almanacs: [{DATA}/yuma_2020-01-03.txt, {DATA}/alm_gal_ed259.txt]
mission:
  start: {{name: start, lon: 24.9405421, lat: 60.1690, alt_agl_m: 60}}
  goal: {{name: goal, lon: 24.9408349, lat: 60.1660, alt_agl_m: 60}}
  start_time_utc: 2020-01-03T10:00:00Z
vehicle: dji-m300-rtk
constraints: {{min_altitude_agl_m: 0, max_altitude_agl_m: 80}}
gnss: {{elevation_mask_deg: 5, dop_kind: PDOP, dop_thresholds: [3, 4], window_min: 5, step_min: 1}}
planner: {{name: astar, weights: [1, 1, 1, 1], time_budget_s: 2, seed: 0}}
traffic:
  n_slices: 4
  intruders:
    - {{id: crosser, radius_m: 2.0, waypoints: [[5, 385600, 6671850, 60], [60, 385860, 6671850, 60]]}}
"""


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A small flyable run and the same scenario with PDOP < 1.05 (no flyable plan)."""
    tmp = tmp_path_factory.mktemp("report")
    small = tmp / "small.yaml"
    small.write_text(SMALL)
    nofly = tmp / "nofly.yaml"
    nofly.write_text(SMALL.replace("dop_thresholds: [3, 4]", "dop_thresholds: [1.05]").replace("report-small",
                                                                                               "report-nofly"))
    r = CliRunner()
    ok = r.invoke(main, ["run", str(small), "--out", str(tmp / "ok"), "--cache-dir", str(tmp / "c"), "-q"])
    assert ok.exit_code == 0, ok.output
    bad = r.invoke(main, ["run", str(nofly), "--out", str(tmp / "bad"), "--cache-dir", str(tmp / "c"), "-q"])
    assert bad.exit_code == 3, bad.output
    return tmp


class _Tables(HTMLParser):
    """Every <table class=...>: its header and rows of cell texts; and every src/href."""

    def __init__(self):
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self.refs: list[tuple[str, str, str]] = []
        self._cur = None
        self._cell = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for k in ("src", "href"):
            if k in a:
                self.refs.append((tag, k, a[k]))
        if tag == "table":
            self._cur = self.tables.setdefault(a.get("class") or f"t{len(self.tables)}", [])
        elif tag == "tr" and self._cur is not None:
            self._cur.append([])
        elif tag in ("td", "th") and self._cur is not None:
            self._cell = ""

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._cur[-1].append(self._cell)
            self._cell = None
        elif tag == "table":
            self._cur = None


def _parse(path: Path) -> _Tables:
    p = _Tables()
    p.feed(path.read_text())
    return p


def test_run_report_is_self_contained(runs):
    from PIL import Image

    out = runs / "ok"
    doc = json.loads((out / "summary.json").read_text())
    assert "report.html" in doc["files"] and "plan/plan.html" in doc["files"]
    text = (out / "report.html").read_text()
    pngs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(pngs) >= 5
    for b in pngs:   # every embedded figure is a real PNG with pixels
        im = Image.open(io.BytesIO(base64.b64decode(b)))
        assert im.format == "PNG" and im.size[0] > 100 and im.size[1] > 100
    refs = _parse(out / "report.html").refs
    assert refs, "the parser saw no src/href at all"
    for tag, attr, url in refs:   # data: URIs, or files of the folder itself
        assert url.startswith("data:") or (tag == "a" and (out / url).is_file()), (tag, attr, url[:80])
    assert "<script src" not in text and "<link" not in text
    # a warm run rebuilds the report (identical: same files, same summary content)
    again = CliRunner().invoke(main, ["run", str(runs / "small.yaml"), "--out", str(out), "--cache-dir",
                                      str(runs / "c"), "-q"])
    assert again.exit_code == 0, again.output
    assert (out / "report.html").is_file()


def test_report_escapes_text(runs):
    text = (runs / "ok" / "report.html").read_text()
    assert "A small &lt;b&gt;Helsinki&lt;/b&gt; block &amp; its report" in text
    assert "<b>Helsinki</b>" not in text


def test_candidate_table_equals_candidates_csv(runs):
    out = runs / "ok"
    rows = list(csv.DictReader((out / "plan" / "candidates.csv").open()))
    table = _parse(out / "report.html").tables["candidates"]
    header, body = table[0], table[1:]
    assert len(body) == len(rows) == 2
    col = {h: i for i, h in enumerate(header)}
    for csv_key, head in (("label", "D_j"), ("C_l_m", "C_l [m]"), ("C_r_m", "C_r [m]"), ("C_d_m", "C_d [m]"),
                          ("C_e_m", "C_e [m]"), ("f_m", "f [m]"), ("energy_Wh", "energy [Wh]"),
                          ("flight_time_s", "flight time [s]"), ("max_sigma_p_m", "max sigma_p [m]"),
                          ("chosen", "chosen"), ("reasons", "reasons")):
        for r, cells in zip(rows, body, strict=True):
            assert cells[col[head]] == r[csv_key], (head, cells[col[head]], r[csv_key])
    # and the chosen row's f is the plan section's f (same number, 0.05 m: the CSV's 1 decimal)
    plan = json.loads((out / "summary.json").read_text())["plan"]
    chosen = [c for c in body if c[col["chosen"]] == "true"]
    assert len(chosen) == 1 and abs(float(chosen[0][col["f [m]"]]) - plan["f_m"]) <= 0.05 + 1e-9


def test_no_flyable_plan_report_says_why(runs):
    out = runs / "bad"
    doc = json.loads((out / "summary.json").read_text())
    assert doc["plan"]["status"] == "no_flyable_plan" and "report.html" in doc["files"]
    text = (out / "report.html").read_text()
    m = re.search(r'<div class="outcome bad" id="no-flyable-plan">(.*?)</div>', text, re.S)
    assert m, "no 'no flyable plan' box"
    items = [html.unescape(x) for x in re.findall(r"<li>(.*?)</li>", m.group(1), re.S)]
    assert items == doc["plan"]["reasons"] and "PDOP < 1.05" in items[0]
    assert len(re.findall(r'<img src="data:image/png;base64,', text)) >= 3   # the maps still


def test_plan_map_page_has_leaflet_inline(runs):
    text = (runs / "ok" / "plan" / "plan.html").read_text()
    assert "Leaflet 1.9.4" in text or "1.9.4" in text
    assert not re.search(r"<(script|link)\b[^>]*(src|href)=", text)
    for layer in ("chosen plan D=3", "coverage floor D=3", "coverage floor D=4", "other candidates",
                  "intruders (known traffic)", "OpenStreetMap basemap"):
        assert layer in text, layer
    assert "tile.openstreetmap.org" in text   # the basemap: the only network resource


def _fake_fly_folder(tmp: Path, src_png: Path) -> Path:
    """A folder as `skyroute fly` writes it (summary, tactical.csv, geojson, one figure)."""
    from skyroute.stages.planning.outputs import write_csv
    from skyroute.stages.tactical.outputs import TACTICAL_COLUMNS

    d = tmp / "fly"
    d.mkdir()
    rows = [[0, "intruder x", "10.000", "43.878", "1", "true", "720.3", "1275.0", "1995.3", "1.353", "0.484153",
             "0.000018", "11.36", "true", ""],
            [0, "intruder x", "10.000", "43.878", "2", "true", "736.3", "1467.2", "2203.5", "1.338", "0.127719",
             "0.000018", "4.93", "false", "valid but f = 2203.5 m > 1995.3 m of level 1"],
            [1, "nofly <police>", "65.000", "10.688", "1", "false", "nan", "nan", "nan", "nan", "0.000054",
             "0.000017", "nan", "false", "frontal encounter"],
            [1, "nofly <police>", "65.000", "10.688", "landing", "true", "50.0", "60.0", "110.0", "1.0", "0.2",
             "0.000017", "-3.00", "true", ""]]
    write_csv(d / "tactical.csv", TACTICAL_COLUMNS, rows)
    line = {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [[24.94, 60.166, 60],
                                                                                  [24.941, 60.168, 60]]},
            "properties": {"part": "strategic"}}
    (d / "flown.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [line]}))
    zone = {"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [[[24.9395, 60.167, 0], [24.9405, 60.167, 0],
                                                                                 [24.9405, 60.1675, 0],
                                                                                 [24.9395, 60.167, 0]]]},
            "properties": {"feature": "nofly", "id": "police", "start_s": 65.0, "end_s": 200.0}}
    (d / "intruders.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [zone]}))
    shutil.copy(src_png, d / "fly_top.png")
    fly = {"outcome": "landed", "reason": "", "n_replannings": 2, "chosen_levels": ["1", "landing"],
           "events": [{"t_s": 10.0, "kind": "intruder", "label": "intruder x", "t_known_s": 10.0, "t_coll_s": 43.9,
                       "outcome": "replanned L1"}]}
    doc = {"schema_version": 1, "command": "fly", "files": sorted(["tactical.csv", "flown.geojson",
                                                                    "intruders.geojson", "fly_top.png",
                                                                    "summary.json"]),
           "warnings": [], "scenario": "fake", "stages": [{"name": "plan", "key": "k", "cache_hit": True,
                                                           "seconds": 0.1}], "seconds": 0.5, "fly": fly}
    (d / "summary.json").write_text(json.dumps(doc))
    from skyroute.pipeline.outfolder import add_to_manifest

    add_to_manifest(d, [d / f for f in doc["files"]])   # as skyroute writes it: its files in its manifest
    return d


def test_report_of_a_fly_folder_has_tables_3_and_5(runs, tmp_path):
    d = _fake_fly_folder(tmp_path, runs / "ok" / "figures" / "surface.png")
    res = CliRunner().invoke(main, ["report", str(d)])
    assert res.exit_code == 0, res.output
    doc = json.loads((d / "summary.json").read_text())
    assert {"report.html", "fly.html"} <= set(doc["files"]) and (d / "fly.html").is_file()
    text = (d / "report.html").read_text()
    t3 = _parse(d / "report.html").tables["tactical"]
    assert t3[0] == ["replanning", "event", "t_event [s]", "t_coll [s]", "DAA alert", "level 1", "level 2",
                     "level 3", "landing", "escape", "chosen"]
    assert t3[1] == ["0", "intruder x", "10.000", "43.878", "", "f 1995.3", "f 2203.5", "-", "-", "-", "1"]
    assert t3[2] == ["1", "nofly <police>", "65.000", "10.688", "", "not flyable", "-", "-", "f 110.0", "-", "landing"]
    assert "nofly &lt;police&gt;" in text and "<police>" not in text
    assert "fly.html" in text and "Flight replay: outcome landed" in text


def test_report_cli_errors(tmp_path):
    res = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert res.exit_code == 2 and "no readable summary.json" in res.output


# ------------------------------------------------------------------ in a real browser


def _chromium(url: str, shot: Path, size: str = "1200,2400") -> tuple[str, list[str]]:
    """(DOM after load, console messages) of ``url`` in headless chromium; screenshot to ``shot``."""
    exe = shutil.which("chromium")
    proc = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                           "--enable-logging=stderr", "--v=0", "--virtual-time-budget=5000", f"--window-size={size}",
                           f"--screenshot={shot}", "--dump-dom", url], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    console = [m for m in re.findall(r":CONSOLE[^\]]*\] (.*)", proc.stderr)]
    return proc.stdout, console


def _not_blank(shot: Path) -> float:
    from PIL import Image

    px = np.asarray(Image.open(shot).convert("L"), dtype=float)
    return float(px.std())


def _tile_error(msg: str) -> bool:
    return "tile.openstreetmap.org" in msg


needs_chromium = pytest.mark.skipif(shutil.which("chromium") is None,
                                    reason="no `chromium` on PATH (Debian: apt-get install -y chromium; .ci/run does)")


@needs_chromium
@pytest.mark.parametrize("folder, min_images", [("ok", 5), ("bad", 3)])
def test_report_in_a_browser(runs, tmp_path, folder, min_images):
    out = runs / folder
    dom, console = _chromium((out / "report.html").as_uri(), tmp_path / "report.png")
    m = re.search(r'<body data-images="(\d+)" data-images-loaded="(\d+)/(\d+)"', dom)
    assert m, "the page's load probe did not run"
    n, ok, total = (int(g) for g in m.groups())
    assert total >= min_images and ok == total == n
    assert [c for c in console if not _tile_error(c)] == []
    assert _not_blank(tmp_path / "report.png") > 10.0   # grey levels 0-255
    shutil.copy(tmp_path / "report.png", runs / f"report-screenshot-{folder}.png")


@needs_chromium
def test_plan_map_in_a_browser(runs, tmp_path):
    dom, console = _chromium((runs / "ok" / "plan" / "plan.html").as_uri(), tmp_path / "plan.png", "1000,800")
    m = re.search(r'data-overlays-loaded="(\d+)/(\d+)" data-vector-paths="(\d+)"', dom)
    assert m, "Leaflet did not run (no load probe)"
    ok, total, paths = (int(g) for g in m.groups())
    # the chosen plan's coverage floor (shown) decodes; the plan, its 2 markers and the intruder are drawn
    assert ok == total == 1 and paths >= 4
    assert "leaflet-container" in dom
    assert [c for c in console if not _tile_error(c)] == []
    assert _not_blank(tmp_path / "plan.png") > 10.0


def test_report_out_elsewhere_links_back(runs, tmp_path):
    page = tmp_path / "pages" / "r.html"
    res = CliRunner().invoke(main, ["report", str(runs / "ok"), "--out", str(page)])
    assert res.exit_code == 0, res.output
    links = [u for t, _, u in _parse(page).refs if t == "a"]
    assert links and all((page.parent / u).resolve().is_file() for u in links)
    assert (page.parent / links[0]).resolve() == (runs / "ok" / "plan" / "plan.html").resolve()
    assert "r.html" not in json.loads((runs / "ok" / "summary.json").read_text())["files"]


def test_report_of_a_plan_folder_draws_its_maps(runs):
    """A plan folder has 3 figures of its own; `skyroute report` draws the scenario's maps (from
    the cache) into the page only: the folder gets report.html and nothing else (issue 25)."""
    out = runs / "plan"
    r = CliRunner()
    res = r.invoke(main, ["plan", str(runs / "small.yaml"), "--out", str(out), "--cache-dir", str(runs / "c"), "-q"])
    assert res.exit_code == 0, res.output
    assert not (out / "figures").exists()
    res = r.invoke(main, ["report", str(out), "--cache-dir", str(runs / "c")])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "summary.json").read_text())
    assert doc["scenario_path"] == str((runs / "small.yaml").resolve())
    assert "report.html" in doc["files"] and all((out / f).is_file() for f in doc["files"])
    assert not (out / "figures").exists() and not any("figures/" in f for f in doc["files"])
    text = (out / "report.html").read_text()
    assert text.count('<img src="data:image/png;base64,') == 7   # 3 maps + top, profile, sigma_p, bubble
    assert 'alt="bubble.png"' in text
    cand = _parse(out / "report.html").tables["candidates"]
    assert [c[0] for c in cand[1:]] == ["D=3", "D=4"]


def test_raster_overlay_puts_each_cell_where_it_is():
    """The lon/lat overlay of plan.html: every pixel painted for one marked cell has its centre
    (transformed back by pyproj, independently) inside that cell; the cell's own centre falls
    on a painted pixel."""
    from PIL import Image
    from pyproj import Transformer

    from skyroute.pipeline.planmap import raster_overlay
    from skyroute.stages.grid import Grid

    g = Grid.from_bounds("EPSG:32635", 385400.0, 6671400.0, 386000.0, 6672200.0, 10.0)   # 60 x 80 cells
    vals = np.zeros((g.ny, g.nx))
    row, col = 23, 41
    vals[row, col] = 1.0

    def rgba(v):
        out = np.zeros((*np.shape(v), 4), dtype=np.uint8)
        out[np.asarray(v) > 0] = (255, 0, 0, 255)
        return out

    uri, ((s, w), (n, e)) = raster_overlay(vals, g, rgba, max_cells=400)
    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(uri.split(",", 1)[1]))))
    ny, nx = img.shape[:2]
    jj, ii = np.nonzero(img[..., 3])
    assert jj.size > 0
    lon = w + (ii + 0.5) * (e - w) / nx
    lat = n - (jj + 0.5) * (n - s) / ny
    x, y = Transformer.from_crs(4326, 32635, always_xy=True).transform(lon, lat)
    xmin, ymax = g.bounds[0], g.bounds[3]
    assert np.all((x >= xmin + col * 10.0) & (x < xmin + (col + 1) * 10.0))
    assert np.all((y <= ymax - row * 10.0) & (y > ymax - (row + 1) * 10.0))
    cx, cy = xmin + (col + 0.5) * 10.0, ymax - (row + 0.5) * 10.0
    clon, clat = Transformer.from_crs(32635, 4326, always_xy=True).transform(cx, cy)
    pi, pj = int((clon - w) / (e - w) * nx), int((n - clat) / (n - s) * ny)
    assert img[pj, pi, 3] == 255

"""The interactive map page ``plan.html`` (Leaflet through folium): the chosen plan, the other
candidates, the intruders, the no-fly cells / zones and the coverage floors per D_j as
toggleable layers over an OpenStreetMap basemap.

Leaflet 1.9.4 is vendored (``pipeline/vendor/leaflet``, BSD-2) and inlined into the page, with
its CSS images as data: URIs: the page loads no script or style from the network, so the vector
and raster layers render offline; only the basemap tiles need the network.  folium's other
default assets (jQuery, Bootstrap, Font Awesome) are not used: layers are plain polylines,
circle markers, GeoJSON polygons and image overlays.

Rasters (coverage floor, no-fly) are resampled (nearest cell) onto a regular lon/lat grid of
about the map's cell count and shown as ``ImageOverlay`` (PNG data: URI); over the <= few km of
an AOI the linear lat -> Web-Mercator stretch of an overlay is well below a cell.
"""

from __future__ import annotations

import base64
import io
import re
from functools import lru_cache
from html import escape
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

__all__ = ["leaflet_inline", "new_map", "map_html", "raster_overlay", "plan_map_html", "write_plan_map",
           "fly_map_html", "fly_map_layers", "add_legend", "CANDIDATE_COLOURS"]

VENDOR = Path(__file__).with_name("vendor") / "leaflet"
CANDIDATE_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf")
OSM_ATTRIBUTION = ('&copy; <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors')


# body[data-overlays-loaded] = "ok/n" raster overlays decoded, body[data-vector-paths] = drawn SVG
# paths, once the page has loaded (read back by the browser test through --dump-dom)
_LOADED_PROBE = """<script>
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.querySelectorAll("img.leaflet-image-layer"));
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.body.setAttribute("data-overlays-loaded", ok + "/" + imgs.length);
  document.body.setAttribute("data-vector-paths", document.querySelectorAll("path.leaflet-interactive").length);
});
</script>"""


@lru_cache(maxsize=1)
def leaflet_inline() -> str:
    """``<style>`` + ``<script>`` of the vendored Leaflet (CSS images inlined as data: URIs)."""
    css = (VENDOR / "leaflet.css").read_text()

    def data_uri(m: re.Match) -> str:
        png = (VENDOR / "images" / m.group(1)).read_bytes()
        return "url(data:image/png;base64," + base64.b64encode(png).decode() + ")"

    css = re.sub(r"url\(images/([\w.-]+\.png)\)", data_uri, css)
    js = (VENDOR / "leaflet.js").read_text()
    if "</script" in js.lower() or "</style" in css.lower():   # would end the inline element early
        raise RuntimeError("vendored Leaflet contains a closing tag; it cannot be inlined")
    return f"<style>{css}</style>\n<script>{js}</script>"


def new_map(bounds_lonlat: tuple[float, float, float, float], title: str):
    """A folium Map over ``bounds_lonlat`` (west, south, east, north) [deg] with the OSM basemap,
    Leaflet inlined (no CDN assets) and ``title`` as the page title."""
    import folium
    from branca.element import Element

    w, s, e, n = bounds_lonlat
    m = folium.Map(location=[(s + n) / 2, (w + e) / 2], zoom_start=15, tiles=None, control_scale=True)
    m.default_js = []    # folium's CDN scripts and styles: Leaflet comes inline instead
    m.default_css = []
    root = m.get_root()
    root.header.add_child(Element(leaflet_inline()), name="leaflet_inline", index=0)
    root.header.add_child(Element(f"<title>{escape(title)}</title>\n<style>.leaflet-image-layer "
                                  "{image-rendering: pixelated;}</style>"), name="page_title")
    folium.TileLayer("OpenStreetMap", name="OpenStreetMap basemap", attr=OSM_ATTRIBUTION).add_to(m)
    m.fit_bounds([[s, w], [n, e]])
    return m


def map_html(m) -> str:
    """Add the layer control (expanded) and render ``m`` as one HTML page; refuses a page that
    would load a script or stylesheet from elsewhere."""
    import folium
    from branca.element import Element

    folium.LayerControl(collapsed=False).add_to(m)
    m.get_root().html.add_child(Element(_LOADED_PROBE), name="loaded_probe")
    html = m.get_root().render()
    bad = re.findall(r"<(?:script|link)\b[^>]*(?:src|href)=\"[^\"]+\"", html)
    if bad:
        raise RuntimeError(f"plan map would load external assets: {bad[:3]}")
    return html


def raster_overlay(values: np.ndarray, grid, rgba_of, max_cells: int = 700):
    """An ``(ny, nx)`` raster on ``grid`` (a :class:`~skyroute.stages.grid.Grid`) resampled
    (nearest cell) onto a regular lon/lat grid; ``rgba_of(values) -> (..., 4) uint8``.
    Returns (PNG data: URI, [[south, west], [north, east]])."""
    from PIL import Image

    xmin, ymin, xmax, ymax = grid.bounds
    to_ll = Transformer.from_crs(grid.crs, 4326, always_xy=True)
    to_map = Transformer.from_crs(4326, grid.crs, always_xy=True)
    ex = np.linspace(xmin, xmax, 50)
    ey = np.linspace(ymin, ymax, 50)
    bx = np.concatenate([ex, ex, np.full(50, xmin), np.full(50, xmax)])
    by = np.concatenate([np.full(50, ymin), np.full(50, ymax), ey, ey])
    lon, lat = to_ll.transform(bx, by)
    w, e, s, n = float(lon.min()), float(lon.max()), float(lat.min()), float(lat.max())
    scale = min(1.0, max_cells / max(grid.nx, grid.ny))
    nxo, nyo = max(2, int(round(grid.nx * scale))), max(2, int(round(grid.ny * scale)))
    lo = w + (np.arange(nxo) + 0.5) * (e - w) / nxo
    la = n - (np.arange(nyo) + 0.5) * (n - s) / nyo
    LO, LA = np.meshgrid(lo, la)
    x, y = to_map.transform(LO, LA)
    res = float(grid.resolution_m)
    col = np.floor((x - xmin) / res).astype(int)
    row = np.floor((ymax - y) / res).astype(int)
    inside = (col >= 0) & (col < grid.nx) & (row >= 0) & (row < grid.ny)
    rgba = np.zeros((nyo, nxo, 4), dtype=np.uint8)
    rgba[inside] = rgba_of(np.asarray(values)[row[inside], col[inside]])
    buf = io.BytesIO()
    Image.fromarray(rgba, mode="RGBA").save(buf, format="PNG", optimize=True)
    uri = "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()
    return uri, [[s, w], [n, e]]


def _lonlat(grid_crs, xy: np.ndarray) -> np.ndarray:
    tr = Transformer.from_crs(grid_crs, 4326, always_xy=True)
    lon, lat = tr.transform(np.asarray(xy)[:, 0], np.asarray(xy)[:, 1])
    return np.column_stack([lat, lon])


def _line(group, latlon: np.ndarray, colour: str, weight: float, tooltip: str, dash: str | None = None) -> None:
    import folium

    folium.PolyLine(latlon.tolist(), color=colour, weight=weight, opacity=0.9, dash_array=dash,
                    tooltip=escape(tooltip)).add_to(group)


def _swatch(colour: str, kind: str = "line") -> str:
    """An inline HTML swatch of a legend row: a line, a dashed line, a box or a dot of ``colour``."""
    if kind == "box":
        return f'<span style="display:inline-block;width:16px;height:11px;background:{colour};opacity:0.8"></span>'
    if kind == "dot":
        return (f'<span style="display:inline-block;width:11px;height:11px;border-radius:50%;background:{colour};'
                'border:1px solid #000"></span>')
    style = "dashed" if kind == "dashed" else "solid"
    return f'<span style="display:inline-block;width:24px;height:0;border-top:4px {style} {colour};"></span>'


def _ramp(cmap_name: str, top: float, what: str) -> str:
    """A colour-ramp legend row: ``what`` from 0 to ``top`` in ``cmap_name``'s colours."""
    import matplotlib
    from matplotlib.colors import to_hex

    cmap = matplotlib.colormaps[cmap_name]
    stops = ", ".join(to_hex(cmap(v)) for v in np.linspace(0, 1, 6))
    return (f'<div class="ramp-row">{escape(what)}<br><span style="display:inline-block;width:150px;height:11px;'
            f'background:linear-gradient(to right, {stops});vertical-align:middle"></span>'
            f'<span class="ramp-ticks" style="display:flex;justify-content:space-between;width:150px">'
            f"<span>0</span><span>{top / 2:g}</span><span>{top:g}</span></span></div>")


def add_legend(m, title: str, rows: list[tuple[str, str]], ramps: tuple[str, ...] = ()) -> None:
    """A fixed legend box (lower left, ``id="map-legend"``) on the folium map ``m``: ``title``, one
    row per (swatch HTML from :func:`_swatch`, label) and the colour ramps of raster layers (HTML
    from :func:`_ramp`); labels are escaped.  Drawn by the page itself: shown offline too."""
    from branca.element import Element

    items = "".join(f"<div>{sw} {escape(label)}</div>" for sw, label in rows)
    html = ('<div id="map-legend" style="position:fixed;bottom:70px;left:10px;z-index:1000;background:rgba(255,255,255,'
            '0.92);padding:6px 9px;border:1px solid #888;border-radius:4px;font:12px system-ui,sans-serif;'
            f'max-width:320px;line-height:1.45"><b>{escape(title)}</b>{items}{"".join(ramps)}</div>')
    m.get_root().html.add_child(Element(html), name="map_legend")


COVERAGE_CMAP = "viridis"


def _coverage_layers(m, grid, coverage: dict, terrain_m, top: float, shown_threshold) -> None:
    """One image overlay per DOP threshold D_j of the coverage floors ``coverage`` ({D_j: (ny, nx)
    floor [m], inf/NaN = unflyable}) shown above ground (``terrain_m``) in 0 .. ``top`` [m AGL];
    only the layer of ``shown_threshold`` is switched on."""
    import folium
    import matplotlib

    cmap = matplotlib.colormaps[COVERAGE_CMAP]
    for thr, floor in sorted(coverage.items()):
        agl = np.asarray(floor, float) - (0.0 if terrain_m is None else np.asarray(terrain_m, float))

        def rgba(v, top=top):
            out = (np.asarray(cmap(np.clip(np.nan_to_num(v, nan=0.0, posinf=0.0) / top, 0, 1))) * 255).astype(
                np.uint8)
            out[..., 3] = 150
            out[~np.isfinite(v)] = (90, 90, 90, 190)
            return out

        uri, bounds = raster_overlay(agl, grid, rgba)
        shown = thr == shown_threshold
        folium.raster_layers.ImageOverlay(uri, bounds, name=f"coverage floor D={thr:g} [m AGL, 0-{top:g}; "
                                          "grey = unflyable]", show=bool(shown), opacity=0.8).add_to(m)


def _buildings_layer(m, grid, height_m) -> bool:
    """The buildings' footprints (``height_m`` [m] above ground > 0.5) as a grey image overlay;
    False (nothing added) when there is no building."""
    import folium

    h = np.nan_to_num(np.asarray(height_m, float))
    if not (h > 0.5).any():
        return False

    def grey(v):
        out = np.zeros((*np.shape(v), 4), dtype=np.uint8)
        out[np.asarray(v) > 0.5] = (70, 70, 80, 170)
        return out

    uri, bounds = raster_overlay(h, grid, grey)
    folium.raster_layers.ImageOverlay(uri, bounds, name="buildings (footprints)", show=True).add_to(m)
    return True


def plan_map_html(*, title: str, grid, chosen, candidates, intruders=(), nofly=None, coverage=None,
                  terrain_m=None, max_agl_m: float | None = None) -> str:
    """The page of a strategic plan.  ``grid``: the scenario Grid; ``chosen``/``candidates``:
    STEP III candidates (``xyz_m`` [m, map CRS], ``label``, ``f``); ``intruders``: objects with
    ``id``, ``times_s``, ``xyz_m``; ``nofly``: (ny, nx) bool; ``coverage``: {D_j: (ny, nx) floor
    [m] in the surface datum, inf/NaN = unflyable}; ``terrain_m``: (ny, nx) ground [m] (the floors
    are shown above ground, 0 .. ``max_agl_m``)."""
    import folium

    to_ll = Transformer.from_crs(grid.crs, 4326, always_xy=True)
    xmin, ymin, xmax, ymax = grid.bounds
    lon, lat = to_ll.transform([xmin, xmax, xmin, xmax], [ymin, ymin, ymax, ymax])
    m = new_map((min(lon), min(lat), max(lon), max(lat)), title)
    top = float(max_agl_m) if max_agl_m else 120.0
    rows: list[tuple[str, str]] = []
    ramps: list[str] = []
    if coverage:
        _coverage_layers(m, grid, coverage, terrain_m, top,
                         chosen.dop_threshold if chosen is not None else min(coverage))
        ramps.append(_ramp(COVERAGE_CMAP, top, "coverage floor per D_j [m above ground]"))
        rows.append((_swatch("rgb(90,90,90)", "box"), "coverage floor: unflyable (no GNSS level)"))
    if nofly is not None and np.asarray(nofly).any():
        def red(v):
            out = np.zeros((*np.shape(v), 4), dtype=np.uint8)
            out[np.asarray(v, bool)] = (220, 20, 20, 150)
            return out

        uri, bounds = raster_overlay(nofly, grid, red)
        folium.raster_layers.ImageOverlay(uri, bounds, name="no-fly cells", show=True).add_to(m)
        rows.append((_swatch("rgb(220,20,20)", "box"), "no-fly cells"))
    others = folium.FeatureGroup(name="other candidates", show=True)
    for i, c in enumerate(candidates):
        if c is chosen or np.asarray(c.xyz_m).shape[0] < 2:
            continue
        _line(others, _lonlat(grid.crs, c.xyz_m), CANDIDATE_COLOURS[i % len(CANDIDATE_COLOURS)], 3,
              f"{c.label}: f = {float(c.f):.1f} m{'' if c.flyable else ' (not flyable)'}", dash="6 6")
    others.add_to(m)
    if intruders:
        grp = folium.FeatureGroup(name="intruders (known traffic)", show=True)
        for it in intruders:
            ll = _lonlat(grid.crs, np.asarray(it.xyz_m)[:, :2])
            _line(grp, ll, "#d62728", 2, f"intruder {it.id}: t = {float(it.times_s[0]):g}-"
                  f"{float(it.times_s[-1]):g} s")
            folium.CircleMarker(ll[0].tolist(), radius=4, color="#d62728", fill=True,
                                tooltip=escape(f"intruder {it.id} at t = {float(it.times_s[0]):g} s")).add_to(grp)
        grp.add_to(m)
    if chosen is not None:
        grp = folium.FeatureGroup(name=f"chosen plan {chosen.label}", show=True)
        ll = _lonlat(grid.crs, chosen.xyz_m)
        _line(grp, ll, "#000000", 5, f"chosen {chosen.label}: f = {float(chosen.f):.1f} m")
        folium.CircleMarker(ll[0].tolist(), radius=7, color="#000", fill_color="#2ca02c", fill=True,
                            fill_opacity=1, tooltip="start").add_to(grp)
        folium.CircleMarker(ll[-1].tolist(), radius=7, color="#000", fill_color="#d62728", fill=True,
                            fill_opacity=1, tooltip="goal").add_to(grp)
        grp.add_to(m)
        rows = [(_swatch("#000000"), f"chosen plan {chosen.label}"), (_swatch("#2ca02c", "dot"), "start"),
                (_swatch("#d62728", "dot"), "goal")] + rows
    drawn = [c for c in candidates if c is not chosen and np.asarray(c.xyz_m).shape[0] >= 2]
    if drawn:
        rows.append((_swatch(CANDIDATE_COLOURS[0], "dashed"), "other candidates (dashed, one colour each)"))
    if intruders:
        rows.append((_swatch("#d62728"), "intruders (known traffic; dot: first position)"))
    add_legend(m, "Legend", rows, tuple(ramps))
    return map_html(m)


def write_plan_map(result, path: Path, chosen, candidates) -> Path:
    """``plan.html`` of a run result (:class:`~skyroute.pipeline.graph.RunResult` with the plan
    stage): the candidates, the scenario's intruders, the no-fly cells and the coverage floors."""
    from skyroute.pipeline.maps import display_grid, display_view

    sc = result.scenario
    surface = result["surface"]
    # the overlays are a few hundred pixels a side: a city's maps are read as their k x k block
    # maxima (pipeline.maps.display_view), never whole
    terrain, k = display_view(surface["terrain"])
    grid = display_grid(sc.grid, terrain, k)
    terrain = np.asarray(terrain.values, float)
    intr = ()
    if sc.traffic.intruders:
        from skyroute.stages.traffic import intruders_for

        intr = intruders_for([i.model_dump() for i in sc.traffic.intruders], surface)
    nofly = display_view(result["clearance"]["nofly"])[0].values if "clearance" in result.datasets else None
    coverage = None
    if "coverage" in result.datasets:
        cf = result["coverage"]["coverage_floor"]
        coverage = {float(t): display_view(cf.sel(threshold=t))[0].values for t in cf["threshold"].values}
    html = plan_map_html(title=f"skyroute plan map: {sc.name}", grid=grid, chosen=chosen, candidates=candidates,
                         intruders=intr, nofly=nofly, coverage=coverage, terrain_m=terrain,
                         max_agl_m=sc.constraints.max_altitude_agl_m)
    path = Path(path)
    path.write_text(html)
    return path


def fly_map_layers(result) -> dict[str, Any]:
    """The map layers of a flight page from its run result (a
    :class:`~skyroute.pipeline.graph.RunResult` with the surface stage; coverage when it has it):
    ``grid``, ``height_m`` (buildings above ground [m]), ``terrain_m``, ``coverage`` ({D_j:
    floor [m]}), ``max_agl_m``, ``shown_threshold`` (the plan's D_j) and the mission's ``start`` /
    ``goal`` [lon, lat], each read as its k x k block maxima on a city (never whole)."""
    from skyroute.pipeline.maps import display_grid, display_view

    sc = result.scenario
    surf, k = display_view(result["surface"][["surface", "terrain"]])
    surf = surf.load()
    grid = display_grid(sc.grid, surf["surface"], k)
    terrain = np.asarray(surf["terrain"].values, float)
    out: dict[str, Any] = {"grid": grid, "terrain_m": terrain, "height_m": np.asarray(surf["surface"].values, float)
                           - terrain, "max_agl_m": sc.constraints.max_altitude_agl_m}
    if "coverage" in result.datasets:
        cf = result["coverage"]["coverage_floor"]
        out["coverage"] = {float(t): display_view(cf.sel(threshold=t))[0].values for t in cf["threshold"].values}
        if "plan" in result.datasets and int(result["plan"].attrs.get("chosen_level", -1)) >= 0:
            thr = float(result["plan"]["dop_threshold"].isel(level=int(result["plan"].attrs["chosen_level"])))
            out["shown_threshold"] = None if np.isnan(thr) else thr
    tr = Transformer.from_crs(sc.grid.crs, 4326, always_xy=True)
    for name in ("start", "goal"):
        out[name] = list(tr.transform(*sc.point_xy(getattr(sc.mission, name))))
    return out


def fly_map_html(title: str, flown: dict[str, Any], intruders: dict[str, Any] | None,
                 plan: dict[str, Any] | None = None, layers: dict[str, Any] | None = None) -> str:
    """The page of a flight replay from its GeoJSON files: ``flown`` (flown.geojson, one line per
    part), ``intruders`` (intruders.geojson: tracks and temporary no-fly polygons), ``plan``
    (plan.geojson of the strategic plan, optional) and ``layers`` (optional,
    :func:`fly_map_layers`: the buildings, the coverage floors and the mission's start and
    goal).  A legend names every colour: the flown parts, the intruders (each labelled with its
    id), the zones, the plan, the start, the goal and the coverage ramp; offline the layers and
    the legend show without the basemap."""
    import folium
    from branca.element import Element

    from skyroute.stages.tactical.outputs import PART_COLOURS

    layers = layers or {}
    pts = [c for f in flown["features"] for c in _coords(f["geometry"])]
    if intruders:
        pts += [c for f in intruders["features"] for c in _coords(f["geometry"])]
    lon = [p[0] for p in pts] or [0.0]
    lat = [p[1] for p in pts] or [0.0]
    m = new_map((min(lon), min(lat), max(lon), max(lat)), title)
    from matplotlib.colors import to_hex

    rows: list[tuple[str, str]] = []
    ramps: list[str] = []
    grid = layers.get("grid")
    if grid is not None and layers.get("coverage"):
        top = float(layers.get("max_agl_m") or 120.0)
        cov = layers["coverage"]
        shown = layers.get("shown_threshold")
        _coverage_layers(m, grid, cov, layers.get("terrain_m"), top, shown if shown in cov else min(cov))
        ramps.append(_ramp(COVERAGE_CMAP, top, "coverage floor of the plan's D_j [m above ground]"))
        rows.append((_swatch("rgb(90,90,90)", "box"), "coverage floor: unflyable"))
    if grid is not None and layers.get("height_m") is not None and _buildings_layer(m, grid, layers["height_m"]):
        rows.append((_swatch("rgb(70,70,80)", "box"), "buildings"))
    if plan is not None:
        grp = folium.FeatureGroup(name="strategic plan", show=True)
        for f in plan["features"]:
            if f["geometry"]["type"] == "LineString":
                _line(grp, np.array([[c[1], c[0]] for c in f["geometry"]["coordinates"]]), "#555555", 3,
                      "strategic plan", dash="6 6")
        grp.add_to(m)
        rows.append((_swatch("#555555", "dashed"), "strategic plan"))
    if intruders:
        zones = [f for f in intruders["features"] if f["properties"].get("feature") == "nofly"]
        tracks = [f for f in intruders["features"] if f["properties"].get("feature") == "intruder"]
        if zones:
            grp = folium.FeatureGroup(name="temporary no-fly zones", show=True)
            for f in zones:
                p = f["properties"]
                folium.GeoJson({"type": "Feature", "geometry": _flat(f["geometry"]), "properties": {}},
                               style_function=lambda _f: {"color": "#d62728", "fillOpacity": 0.3},
                               tooltip=escape(f"no-fly zone {p.get('id')}: {p.get('start_s')}-{p.get('end_s')} s"),
                               ).add_to(grp)
            grp.add_to(m)
            rows.append((_swatch("rgba(214,39,40,0.45)", "box"), "temporary no-fly zones"))
        if tracks:
            grp = folium.FeatureGroup(name="intruders (truth tracks)", show=True)
            for f in tracks:
                c = _coords(f["geometry"])
                ll = np.array([[q[1], q[0]] for q in c])
                if not len(ll):
                    continue
                ident = str(f["properties"].get("id"))
                if len(ll) >= 2:
                    _line(grp, ll, "#d62728", 2, f"intruder {ident}", dash="2 5")
                folium.CircleMarker(ll[0].tolist(), radius=4, color="#d62728", fill=True,
                                    tooltip=folium.Tooltip(escape(ident), permanent=True, direction="right",
                                                           className="intruder-label")).add_to(grp)
            grp.add_to(m)
            rows.append((_swatch("#d62728", "dashed"), "intruders (truth tracks; label at the first position)"))
    grp = folium.FeatureGroup(name="flown trajectory", show=True)
    parts: list[str] = []
    for f in flown["features"]:
        part = str(f["properties"].get("part", ""))
        ll = np.array([[q[1], q[0]] for q in _coords(f["geometry"])])
        colour = to_hex(PART_COLOURS.get(part, "black"))
        if len(ll) >= 2:
            _line(grp, ll, colour, 5, f"flown: {part}")
            if part not in parts:
                parts.append(part)
    flown_pts = [q for f in flown["features"] for q in _coords(f["geometry"])]
    start = layers.get("start") or (flown_pts[0][:2] if flown_pts else None)
    goal = layers.get("goal")
    for name, where, fill in (("goal", goal, "#d62728"), ("start", start, "#2ca02c")):   # legend: start first
        if where is not None:
            folium.CircleMarker([where[1], where[0]], radius=7, color="#000", fill_color=fill, fill=True,
                                fill_opacity=1, tooltip=name).add_to(grp)
            rows.insert(0, (_swatch(fill, "dot"), name))
    if flown_pts and goal is None:
        end = flown_pts[-1]
        folium.CircleMarker([end[1], end[0]], radius=6, color="#000", fill_color="#ffffff", fill=True,
                            fill_opacity=1, tooltip="end of the flight").add_to(grp)
        rows.append((_swatch("#ffffff", "dot"), "end of the flight"))
    grp.add_to(m)
    rows = [(_swatch(to_hex(PART_COLOURS.get(pt, "black"))), f"flown: {pt}") for pt in parts] + rows
    add_legend(m, "Legend", rows, tuple(ramps))
    m.get_root().header.add_child(Element("<style>.intruder-label { font-weight: bold; color: #d62728; "
                                          "padding: 1px 4px; }</style>"), name="intruder_css")
    return map_html(m)


def _coords(geom: dict) -> list[list[float]]:
    t, c = geom["type"], geom["coordinates"]
    if t == "Point":
        return [c]
    if t in ("LineString", "MultiPoint"):
        return list(c)
    if t == "Polygon":
        return [q for ring in c for q in ring]
    return []


def _flat(geom: dict) -> dict:
    """A GeoJSON geometry without its z coordinates."""
    if geom["type"] == "Polygon":
        return {"type": "Polygon", "coordinates": [[q[:2] for q in ring] for ring in geom["coordinates"]]}
    return geom

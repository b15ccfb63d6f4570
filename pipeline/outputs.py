"""Writing a run's outputs: dataset links, GeoTIFFs, figures and ``summary.json``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from skyroute.pipeline.graph import RunResult


def plot_surface(result: RunResult, path: Path) -> Path:
    """Surface model (hill-shaded heights) with the mission start and goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = result.scenario
    ds = result["surface"]
    g = sc.grid
    z = np.asarray(ds["surface"].values, dtype=float)
    terr = np.asarray(ds["terrain"].values, dtype=float)
    extent = g.bounds[0], g.bounds[2], g.bounds[1], g.bounds[3]
    fig, ax = plt.subplots(figsize=(7.5, 7.5 * g.ny / max(g.nx, 1) * 0.9 + 0.8), dpi=110)
    dy, dx = np.gradient(z, g.resolution_m)
    shade = 0.5 + 0.5 * (-dx - dy) / np.sqrt(2 + dx**2 + dy**2 + 1e-9)
    im = ax.imshow(z, extent=extent, cmap="terrain" if np.ptp(terr) > 20 else "viridis", interpolation="nearest")
    ax.imshow(shade, extent=extent, cmap="gray", alpha=0.25, interpolation="nearest")
    for name, marker, colour in (("start", "o", "white"), ("goal", "*", "red")):
        p = getattr(sc.mission, name)
        x, y = sc.point_xy(p)
        ax.plot(x, y, marker, ms=12, mfc=colour, mec="black", label=f"{name}: {p.name or f'({x:.0f}, {y:.0f})'}")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    cb.set_label(f"surface height [m] ({ds.attrs.get('vertical_datum', '')[:40]})", fontsize=8)
    ax.set_xlabel(f"x [m] ({g.crs_wkt[:30]})")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{sc.name}: surface model, {g.nx} x {g.ny} cells @ {g.resolution_m:g} m", fontsize=10)
    ax.ticklabel_format(useOffset=False, style="plain")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_plan_outputs(result: RunResult, out_dir: Path) -> dict[str, Path]:
    """plan.geojson, waypoints.csv, candidates.csv and figures of the cached plan stage.

    The plan was validated independently (``stages.planning.validate``) when it was made;
    the chosen trajectory is validated again here and nothing is written if it fails."""
    from skyroute.pipeline.errors import PlanningError
    from skyroute.stages.planning.outputs import write_plan
    from skyroute.stages.planning.strategic import plan_from_dataset

    ds = result["plan"].load()
    chosen, cands = plan_from_dataset(ds)
    surface = result["surface"].load()
    floor = None
    if "clearance" in result.datasets:
        floor = result["clearance"]["min_altitude_m"].values
    if chosen is not None and "coverage" in result.datasets and chosen.dop_threshold is not None:
        import numpy as np

        cov = result["coverage"]["coverage_floor"].sel(threshold=chosen.dop_threshold).values
        floor = np.fmax(floor, cov) if floor is not None else cov
    if chosen is not None:
        problems = revalidate(result, chosen)
        if problems:
            raise PlanningError("refusing to write a plan that fails validation: " + "; ".join(problems))
    cost = result["environment"]["risk_cost"].values if "environment" in result.datasets else None
    return write_plan(chosen, cands, result.scenario.grid, Path(out_dir), ds.attrs["start_time_utc"],
                      ds.attrs.get("vertical_datum", ""), surface_m=surface["surface"].values,
                      terrain_m=surface["terrain"].values, floor_m=floor, cost_m=cost)


def revalidate(result: RunResult, chosen) -> list[str]:
    """Independent check of the chosen trajectory against the cached maps."""
    import numpy as np

    from skyroute.stages.planning.strategic import intruders_for
    from skyroute.stages.planning.validate import validate_plan
    from skyroute.stages.wind import sample_wind

    sc = result.scenario
    surface = result["surface"].load()
    clear = result["clearance"].load()
    gnss = None
    if "coverage" in result.datasets and chosen.dop_threshold is not None:
        gnss = result["coverage"]["coverage_floor"].sel(threshold=chosen.dop_threshold).values
    wind = None
    if "wind" in result.datasets:
        wmap = result["wind"].load()
        terrain = surface["terrain"]

        def wind(p):  # noqa: E306 - heights above ground for the wind map
            g = sc.grid
            r, c = g.index_of(p[:, 0], p[:, 1])
            agl = p[:, 2] - terrain.values[np.clip(r, 0, g.ny - 1), np.clip(c, 0, g.nx - 1)]
            return np.column_stack(sample_wind(wmap, p[:, 0], p[:, 1], agl))
    intr = intruders_for([i.model_dump() for i in sc.traffic.intruders], surface) if sc.traffic.intruders else ()
    return validate_plan(chosen, grid=sc.grid, terrain_m=surface["terrain"].values, vehicle=sc.vehicle,
                         terrain_min_m=surface["terrain_min"].values if "terrain_min" in surface else None,
                         clearance_floor_m=clear["obstacle_floor_m"].values, gnss_floor_m=gnss,
                         min_agl_m=sc.constraints.min_altitude_agl_m, max_agl_m=sc.constraints.max_altitude_agl_m,
                         nofly=clear["nofly"].values, wind=wind, intruders=intr, d_c_m=sc.traffic.margin_m,
                         dt_c_s=sc.traffic.time_margin_s, battery_reserve_pct=sc.constraints.battery_reserve_pct)


def _previous_outputs(out_dir: Path) -> dict[str, str]:
    try:
        return json.loads((out_dir / "summary.json").read_text()).get("output_keys", {})
    except (OSError, ValueError):
        return {}


def write_run_outputs(result: RunResult, out_dir: Path) -> dict[str, Any]:
    """Write links to the cached zarr datasets, GeoTIFFs, PNG figures and ``summary.json``.

    A GeoTIFF or figure is rewritten only when the stage key it was made from changed (or the
    file is missing), so a warm re-run costs little more than reading the cache.
    """
    out_dir = Path(out_dir)
    (out_dir / "datasets").mkdir(parents=True, exist_ok=True)
    (out_dir / "figures").mkdir(exist_ok=True)
    previous = _previous_outputs(out_dir)
    keys = {r.name: r.key for r in result.records}
    output_keys: dict[str, str] = {}
    files: list[str] = []

    def produce(path: Path, stage: str, make) -> None:
        if not (previous.get(str(path)) == keys[stage] and path.is_file()):
            make(path)
        output_keys[str(path)] = keys[stage]
        files.append(str(path))

    for rec in result.records:
        link = out_dir / "datasets" / f"{rec.name}.zarr"
        if link.is_symlink() or link.exists():
            link.unlink()
        os.symlink(Path(rec.path) / "data.zarr", link)
        files.append(str(link))
    if "surface" in result.datasets:
        produce(out_dir / "surface.tif", "surface",
                lambda p: result["surface"]["surface"].rio.to_raster(p, compress="deflate"))
        produce(out_dir / "figures" / "surface.png", "surface", lambda p: plot_surface(result, p))
    if "plan" in result.datasets:
        produce(out_dir / "plan" / "candidates.csv", "plan", lambda p: write_plan_outputs(result, p.parent))
    sc = result.scenario
    summary = {
        "scenario": sc.name,
        "description": sc.description,
        "crs": sc.grid.crs_wkt,
        "grid": {"nx": sc.grid.nx, "ny": sc.grid.ny, "resolution_m": sc.grid.resolution_m,
                 "bounds": list(sc.grid.bounds)},
        "stages": [{"name": r.name, "key": r.key, "cache_hit": r.cache_hit, "seconds": round(r.seconds, 4),
                    "path": r.path} for r in result.records],
        "stages_run": [r.name for r in result.records if not r.cache_hit],
        "cache_hits": result.cache_hits,
        "seconds": result.seconds,
        "files": files,
        "output_keys": output_keys,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary

"""Writing a run's outputs: dataset links, GeoTIFFs, figures and ``summary.json``."""

from __future__ import annotations

import json
import os
import shutil
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from skyroute.pipeline.errors import InputError
from skyroute.pipeline.graph import RunResult, stage_attrs
from skyroute.pipeline.progress import note, phased
from skyroute.stages.figures import (
    GOAL_STYLE,
    START_STYLE,
    add_map_furniture,
    grow_until_unclipped,
    image_extent,
    side_colorbar,
)


def plot_surface(result: RunResult, path: Path) -> Path:
    """Surface model (hill-shaded heights) with the mission start and goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.pipeline.maps import display_grid, display_view

    sc = result.scenario
    g = sc.grid
    ds, k = display_view(result["surface"][["surface", "terrain"]])   # a city: its k x k block maxima
    ds = ds.load()
    view = display_grid(g, ds["surface"], k)
    z = np.asarray(ds["surface"].values, dtype=float)
    terr = np.asarray(ds["terrain"].values, dtype=float)
    extent = image_extent(ds["surface"])
    fig, ax = plt.subplots(figsize=(7.5, 7.5 * g.ny / max(g.nx, 1) * 0.9 + 0.8), dpi=110)
    dy, dx = np.gradient(z, view.resolution_m)
    shade = 0.5 + 0.5 * (-dx - dy) / np.sqrt(2 + dx**2 + dy**2 + 1e-9)
    im = ax.imshow(z, extent=extent, cmap="terrain" if np.ptp(terr) > 20 else "viridis", interpolation="nearest")
    ax.imshow(shade, extent=extent, cmap="gray", alpha=0.25, interpolation="nearest")
    for name, style in (("start", START_STYLE), ("goal", GOAL_STYLE)):   # the markers of every map figure
        p = getattr(sc.mission, name)
        x, y = sc.point_xy(p)
        ax.plot(x, y, **style, label=f"{name}: {p.name or f'({x:.0f}, {y:.0f})'}")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), fontsize=7, framealpha=0.85, ncol=2)
    datum = "\n".join(textwrap.wrap(str(ds.attrs.get("vertical_datum", "")), 40)[:2])
    cb = side_colorbar(fig, ax, im, f"surface height [m]\n{datum}")
    cb.ax.yaxis.label.set_fontsize(8)
    ax.set_xlabel(f"x [m] ({g.crs.name})")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{sc.name}: surface model, {g.nx} x {g.ny} cells @ {g.resolution_m:g} m", fontsize=10)
    ax.ticklabel_format(useOffset=False, style="plain")
    add_map_furniture(ax)
    fig.tight_layout()
    grow_until_unclipped(fig)     # a narrow AOI: the legend below and the long x label need room
    fig.savefig(path)
    plt.close(fig)
    return path


def write_plan_outputs(result: RunResult, out_dir: Path, map_page: bool = True) -> dict[str, Path]:
    """plan.geojson, waypoints.csv, candidates.csv, figures, the pilot exports
    (:mod:`skyroute.pipeline.plan_exports`: plan.kml, plan.plan, plan.gpkg, intent.json) and
    (``map_page``) the interactive map ``plan.html`` (:mod:`skyroute.pipeline.planmap`) of the
    cached plan stage.

    The plan was validated independently (``stages.planning.validate``) when it was made;
    the chosen trajectory is validated again here and nothing is written if it fails."""
    from skyroute.pipeline.errors import PlanningError
    from skyroute.stages.planning.outputs import write_plan
    from skyroute.stages.planning.strategic import plan_from_dataset

    ds = result["plan"].load()
    chosen, cands = plan_from_dataset(ds)
    if chosen is not None:
        problems = revalidate(result, chosen)
        if problems:
            raise PlanningError("refusing to write a plan that fails validation: " + "; ".join(problems))
    grid, surface, terrain, floor, cost, profile = result.scenario.grid, None, None, None, None, None
    if chosen is not None:         # (no flyable plan: candidates.csv alone, no figure)
        grid, surface, terrain, floor, cost = plan_figure_rasters(result, chosen)
        profile = plan_profile(result, chosen)
    files = write_plan(chosen, cands, grid, Path(out_dir), ds.attrs["start_time_utc"],
                       ds.attrs.get("vertical_datum", ""), surface_m=surface, terrain_m=terrain, floor_m=floor,
                       cost_m=cost, cost_label="ground risk cost (normalised, 0-1) [-]",
                       bubble=_bubble_params(result.scenario), provenance=plan_provenance_of(ds), profile=profile)
    if chosen is not None:
        from skyroute.pipeline.plan_exports import write_pilot_exports

        files.update(write_pilot_exports(result, Path(out_dir)))
    if map_page:
        from skyroute.pipeline.planmap import write_plan_map

        files["plan.html"] = write_plan_map(result, Path(out_dir) / "plan.html", chosen, cands)
    return files


def _path_crop(result: RunResult, chosen) -> tuple[Any, Any]:
    """(grid, crop) for reading ``result``'s maps along ``chosen``'s path: on a city-scale AOI
    (:func:`~skyroute.stages.planning.window.path_window`) the window around the path and a
    function cropping a dataset on the AOI's grid to it (lazily: only its chunks are read), else
    the scenario's grid and the identity.  Every point of the path lies in the window, so what is
    read at them is what the whole maps hold there."""
    from skyroute.stages.gridspec import Grid
    from skyroute.stages.planning.window import crop_on_grid, path_window

    grid = result.scenario.grid
    xy = np.asarray(chosen.xyz_m, float)[:, :2]
    window = path_window(grid, xy) if len(xy) else None
    if window is None:
        return grid, lambda ds: ds
    rows, cols = window

    def crop(ds):
        return crop_on_grid(ds, rows, cols, (grid.ny, grid.nx))
    return Grid.from_dataarray(crop(result["surface"]["terrain"])), crop


def plan_figure_rasters(result: RunResult, chosen) -> tuple[Any, Any, Any, Any, Any]:
    """(grid, surface, terrain, floor, cost) [m, m, m, -] the plan's top view is drawn over: the
    maps as they are up to :data:`~skyroute.pipeline.maps.DISPLAY_MAX_CELLS` cells a side, else
    (a city) their k x k block maxima on the coarser grid of that view (never the whole AOI in
    memory); floor: the clearance floor and, for ``chosen``'s level, the coverage floor (their
    maximum)."""
    from skyroute.pipeline.maps import display_grid, display_view

    def view(da):
        return display_view(da)[0].values

    surf, k = display_view(result["surface"][["surface", "terrain"]])
    surf = surf.load()
    grid = display_grid(result.scenario.grid, surf["terrain"], k)
    cost = view(result["environment"]["risk_cost"]) if "environment" in result.datasets else None
    return grid, surf["surface"].values, surf["terrain"].values, _admissible_floor(result, chosen, view), cost


def plan_profile(result: RunResult, chosen) -> dict[str, np.ndarray]:
    """The maps at the cells of ``chosen``'s points, read at full resolution (only the chunks
    those cells lie in): ``surface``, ``terrain`` and ``floor`` (clearance floor and the
    coverage floor of its level, their maximum) [m], one value per point, for the profile figure."""
    import xarray as xr

    grid = result.scenario.grid
    p = np.asarray(chosen.xyz_m, float)
    row, col = grid.cell_of(p[:, 0], p[:, 1])
    at = {"y": xr.DataArray(np.asarray(row), dims="k"), "x": xr.DataArray(np.asarray(col), dims="k")}

    def sample(da):
        return np.asarray(da.isel(at).values, float)

    out = {"surface": sample(result["surface"]["surface"]), "terrain": sample(result["surface"]["terrain"])}
    floor = _admissible_floor(result, chosen, sample)
    if floor is not None:
        out["floor"] = floor
    return out


def _admissible_floor(result: RunResult, chosen, read) -> np.ndarray | None:
    """The lowest admissible altitude [m] the plan figures draw, as ``read`` (DataArray ->
    ndarray: a display view, or samples at points) gives it: the clearance floor and, for
    ``chosen``'s DOP level, the coverage floor, their maximum (``np.fmax``); None without either."""
    floor = read(result["clearance"]["min_altitude_m"]) if "clearance" in result.datasets else None
    if chosen is not None and "coverage" in result.datasets and chosen.dop_threshold is not None:
        cov = read(result["coverage"]["coverage_floor"].sel(threshold=chosen.dop_threshold))
        floor = np.fmax(floor, cov) if floor is not None else cov
    return floor


def _bubble_params(sc) -> tuple[float, float, float]:
    """(k, surface uncertainty [m], r_p [m]) of the scenario's safety bubble (seed 003)."""
    from skyroute.stages.vehicle import load_vehicle

    return (float(sc.constraints.sboa_k), float(sc.navsim.surface_uncertainty_m), float(load_vehicle(sc.vehicle).r_p_m))


def revalidate(result: RunResult, chosen) -> list[str]:
    """Independent check of the chosen trajectory against the cached maps."""
    import numpy as np

    from skyroute.stages.planning.validate import validate_plan
    from skyroute.stages.traffic import intruders_for
    from skyroute.stages.wind import sample_wind

    sc = result.scenario
    grid, crop = _path_crop(result, chosen)
    surface = crop(result["surface"]).load()
    clear = crop(result["clearance"]).load()
    gnss = None
    if "coverage" in result.datasets and chosen.dop_threshold is not None:
        gnss = crop(result["coverage"]["coverage_floor"].sel(threshold=chosen.dop_threshold)).values
    wind = None
    if "wind" in result.datasets:
        wmap = result["wind"].load()
        terrain = surface["terrain"]

        def wind(p):  # noqa: E306 - heights above ground for the wind map
            agl = p[:, 2] - terrain.values[grid.cell_of(p[:, 0], p[:, 1])]
            return np.column_stack(sample_wind(wmap, p[:, 0], p[:, 1], agl))
    intr = (intruders_for([i.model_dump() for i in sc.traffic.intruders], result["surface"])
            if sc.traffic.intruders else ())
    return validate_plan(chosen, grid=grid, terrain_m=surface["terrain"].values, vehicle=sc.vehicle,
                         terrain_min_m=surface["terrain_min"].values if "terrain_min" in surface else None,
                         clearance_floor_m=clear["obstacle_floor_m"].values, gnss_floor_m=gnss,
                         min_agl_m=sc.constraints.min_altitude_agl_m, max_agl_m=sc.constraints.max_altitude_agl_m,
                         nofly=clear["nofly"].values, wind=wind, intruders=intr, d_c_m=sc.traffic.margin_m,
                         dt_c_s=sc.traffic.time_margin_s, battery_reserve_pct=sc.constraints.battery_reserve_pct)


SUMMARY_SCHEMA_VERSION = 1


def stage_warnings(result: RunResult) -> list[str]:
    """The warnings every stage dataset of ``result`` carries (``attrs["warnings"]``, a
    JSON-encoded list of strings), in stage order, without repeats."""
    out: list[str] = []
    for name in result.datasets:
        raw = stage_attrs(result, name).get("warnings")   # a cached dataset is not opened for its attributes
        if raw is None or raw == "":
            continue
        try:
            items = json.loads(raw) if isinstance(raw, str) else list(raw)
        except ValueError:
            items = [raw]
        if isinstance(items, str):
            items = [items]
        for w in items:
            text = str(w)
            if text and text not in out:
                out.append(text)
    return out


def _num(v: Any, nd: int = 3) -> float | None:
    v = float(v)
    return round(v, nd) if np.isfinite(v) else None


def plan_provenance_of(ds) -> dict[str, Any] | None:
    """The plan stage's ``provenance`` attribute (planner, seed, weights, budgets, version), or None."""
    raw = ds.attrs.get("provenance")
    return json.loads(raw) if raw else None


def plan_section(ds) -> dict[str, Any]:
    """The ``plan`` section of ``summary.json`` from the plan stage's dataset:
    ``status`` (``flyable`` | ``no_flyable_plan``), the chosen candidate's ``label``,
    ``dop_threshold``, ``f_m``, ``C_l_m``, ``C_r_m``, ``C_d_m``, ``C_e_m``, ``length_m`` (3-D
    length of the written trajectory), ``energy_Wh``, ``flight_time_s`` (None when no plan) and
    ``reasons`` (one per level that is not flyable, "label: why"; empty when a plan flies); with
    ``constraints.clearance: sboa`` also the chosen level's ``clearance_radius_m`` r_j [m]."""
    chosen = int(ds.attrs.get("chosen_level", -1))
    reasons = []
    for i in range(ds.sizes.get("level", 0)):
        if not bool(ds["flyable"].values[i]):
            why = str(ds["reasons"].values[i]) or "not flyable"
            reasons.append(f"{ds['label'].values[i]}: {why}")
    sec: dict[str, Any] = {"status": "flyable" if chosen >= 0 else "no_flyable_plan", "label": None,
                           "dop_threshold": None, "f_m": None, "C_l_m": None, "C_r_m": None, "C_d_m": None,
                           "C_e_m": None, "length_m": None, "energy_Wh": None, "flight_time_s": None}
    if chosen >= 0:
        row = ds.isel(level=chosen)
        xyz = np.column_stack([ds["x_m"].values, ds["y_m"].values, ds["z_m"].values])
        sec.update(label=str(row["label"].values), dop_threshold=_num(row["dop_threshold"]),
                   f_m=_num(row["f"]), C_l_m=_num(row["C_l"]), C_r_m=_num(row["C_r"]), C_d_m=_num(row["C_d"]),
                   C_e_m=_num(row["C_e"]), length_m=_num(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()),
                   energy_Wh=_num(float(row["energy_J"]) / 3600.0), flight_time_s=_num(row["flight_time_s"]))
        if "clearance_radius_m" in ds:   # constraints.clearance: sboa
            sec["clearance_radius_m"] = _num(row["clearance_radius_m"])
        reasons = []
    else:
        why = str(ds.attrs.get("reason", "")).removeprefix("no flyable plan: ")
        if not reasons and why:
            reasons = [why]
    sec["reasons"] = reasons
    prov = plan_provenance_of(ds)
    if prov:
        sec["provenance"] = prov
    return sec


def plan_summary_line(sec: dict[str, Any]) -> str:
    """One line: the chosen plan's label, f, length, energy, flight time and DOP level."""
    if sec["status"] != "flyable":
        return "no flyable plan: " + (" | ".join(sec["reasons"]) or "no candidate was produced")
    dop = "no GNSS level" if sec["dop_threshold"] is None else f"DOP < {sec['dop_threshold']:g}"
    return (f"plan {sec['label']}: f {sec['f_m']:.1f} m, length {sec['length_m']:.1f} m, "
            f"energy {sec['energy_Wh']:.2f} Wh, flight time {sec['flight_time_s']:.1f} s, {dop}")


def relative_files(out_dir: Path, paths) -> list[str]:
    """``paths`` (inside ``out_dir``) relative to ``out_dir``, POSIX style."""
    base = os.path.abspath(out_dir)
    return [Path(os.path.relpath(os.path.abspath(p), base)).as_posix() for p in paths]


PRINTED_WARNINGS: list[str] = []     # every `warning: ...` line the CLI printed in this process


def note_printed_warning(text: str) -> None:
    """Record a warning the CLI printed on stderr, so the folder's summary.json lists it too."""
    if text not in PRINTED_WARNINGS:
        PRINTED_WARNINGS.append(text)


def write_summary(out_dir: Path, command: str, files: list[str], warnings: list[str],
                  sections: dict[str, Any]) -> dict[str, Any]:
    """Write ``out_dir/summary.json``: ``schema_version``, ``command``, ``files`` (every file
    written, paths relative to ``out_dir``, ``summary.json`` included), ``warnings`` (the given
    ones, then every other warning the CLI printed on stderr in this process) and the command's
    own ``sections``; return the document.  ``files`` also lists the manifest
    (:data:`~skyroute.pipeline.outfolder.MANIFEST_NAME`), written when the outputs are put into
    place.  Outside a command's staging folder
    (:mod:`skyroute.pipeline.outfolder`: the Python API writing into a folder directly) the
    folder's manifest is written too, listing the files with their checksums."""
    from skyroute.pipeline.outfolder import MANIFEST_NAME, folder_of, record_of, write_manifest

    out_dir = Path(out_dir)
    rel = sorted({Path(f).as_posix() for f in files} | {"summary.json", MANIFEST_NAME})
    warns = list(dict.fromkeys([*warnings, *PRINTED_WARNINGS]))
    doc = {"schema_version": SUMMARY_SCHEMA_VERSION, "command": command, "files": rel,
           "warnings": warns, **sections}
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / ".summary.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))
    os.replace(tmp, out_dir / "summary.json")
    if folder_of(out_dir) is None:
        entries = {f: r for f in rel if (r := record_of(out_dir / f)) is not None}
        write_manifest(out_dir, command, entries)
    return doc


def previous_summary(out_dir: Path) -> dict[str, Any]:
    """The summary of the folder's previous contents (``summary.json``; for a command writing
    into a staging folder, the one of its ``--out``), when skyroute wrote it; else {}."""
    from skyroute.pipeline.outfolder import folder_of, owned_by_skyroute

    out_dir = Path(out_dir)
    f = folder_of(out_dir)
    if f is not None:
        out_dir = f.shown(out_dir)
    p = out_dir / "summary.json"
    if not owned_by_skyroute(p):
        return {}
    try:
        doc = json.loads(p.read_text())
        return doc if isinstance(doc, dict) else {}
    except (OSError, ValueError):
        return {}


# ---------------------------------------------------------------- rewrites never leave a mix
# A command writes into a staging folder put into place at its end (skyroute.pipeline.outfolder):
# while its files move, the folder's summary.json is set aside (RETIRED_SUMMARY) and the new one
# comes last, so a folder caught half-way has no summary.json, which `report` and `diff` refuse.
from skyroute.pipeline.outfolder import RETIRED_SUMMARY, check_writable_dir  # noqa: E402,F401  (their home)


def check_summary_files(folder: Path, doc: dict[str, Any], name: str = "folder",
                        may_miss: tuple[str, ...] = ("report.html", ".skyroute-manifest.json")) -> None:
    """InputError when the folder does not hold what its summary lists (files deleted, or a
    rewrite that did not finish); ``may_miss``: files written after the summary (the report
    page, built from the summary; the manifests, of the folder and of its sub-folders, written
    when the outputs are put into place)."""
    files = doc.get("files", [])
    if not isinstance(files, list):
        raise InputError(f"{name} {folder}: summary.json's files is not a list; run the command that wrote it again")
    for f in files:
        if not isinstance(f, str) or ".." in Path(f).parts or Path(f).is_absolute():
            raise InputError(f"{name} {folder}: summary.json lists {str(f)[:80]!r}, not a file of the folder")
        if f not in may_miss and Path(f).name not in may_miss[1:] and not os.path.lexists(Path(folder) / f):
            raise InputError(f"{name} {folder}: summary.json lists {f}, which is missing: the folder is not what its "
                             "command wrote; run that command again")


def unfinished_rewrite(folder: Path) -> bool:
    """A folder whose summary was set aside by a rewrite that did not finish."""
    return not (Path(folder) / "summary.json").exists() and (Path(folder) / RETIRED_SUMMARY).is_file()


def remove_stale(out_dir: Path, previous: dict[str, Any], files: list[str], command: str) -> None:
    """Remove the files the previous summary of ``out_dir`` listed that this run did not write
    (e.g. plan.geojson of a plan that no longer flies), so the folder holds what summary.json
    says.  Only when that summary was written by the same ``command`` (a folder shared by two
    commands keeps the other command's files), and only files skyroute wrote there and nobody
    changed since (its manifest: :func:`~skyroute.pipeline.outfolder.owned_by_skyroute`), never
    through a symbolic link.  Inside a command's staging folder this is the commit's work."""
    from skyroute.pipeline.outfolder import folder_of, owned_by_skyroute

    out_dir = Path(out_dir)
    if folder_of(out_dir) is not None or previous.get("command") != command:
        return
    keep = {Path(f).as_posix() for f in files}
    listed = previous.get("files", [])
    for f in listed if isinstance(listed, list) else []:
        if not isinstance(f, str) or f in keep or f == "summary.json" or ".." in Path(f).parts or Path(f).is_absolute():
            continue
        p = out_dir / f
        if p.is_file() and not p.is_symlink() and owned_by_skyroute(p, out_dir):
            p.unlink()


def ensure_writable_dir(out_dir: Path | str, option: str = "--out") -> Path:
    """The folder a command writes its outputs into, checked before any long work (one clear
    error otherwise).  Inside a CLI command: the staging folder of ``out_dir``
    (:func:`skyroute.pipeline.outfolder.open_output_folder`), put into place when the command
    ends; from the Python API: ``out_dir`` itself, created and proven writable."""
    import click

    from skyroute.pipeline.outfolder import open_output_folder

    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return check_writable_dir(out_dir, option)
    command = " ".join(ctx.command_path.split()[1:]) or ctx.info_name or "skyroute"
    return open_output_folder(out_dir, command, option).path


def remove_path(path: Path) -> None:
    """Remove a file, a symlink (not its target) or a folder, if there."""
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.exists():
        shutil.rmtree(path)


def _place_store(dst: Path, fill) -> None:
    """Make the zarr store ``dst`` atomically (a partial store never takes the final name):
    ``fill(tmp)`` writes it under a temporary sibling, its metadata is consolidated (so
    ``xr.open_zarr`` reads it without a warning), then it is renamed into place."""
    import warnings

    import zarr

    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    fill(tmp)
    with warnings.catch_warnings():       # "consolidated metadata is not part of the Zarr v3 spec" (yet)
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(tmp))
    remove_path(dst)
    os.rename(tmp, dst)


def _copy_store(src: Path, dst: Path) -> None:
    """Copy the zarr store ``src`` to ``dst`` (:func:`_place_store`)."""
    _place_store(dst, lambda tmp: shutil.copytree(src, tmp))


def _write_store(ds, dst: Path) -> None:
    """Write an in-memory dataset as the zarr store ``dst`` (:func:`_place_store`)."""
    from skyroute.pipeline.cache import prepare_for_zarr

    _place_store(dst, lambda tmp: prepare_for_zarr(ds).to_zarr(tmp, mode="w", consolidated=False))


OUTPUT_MODULES = ("skyroute.pipeline.outputs", "skyroute.pipeline.maps", "skyroute.pipeline.cli_coverage",
                  "skyroute.pipeline.plan_exports", "skyroute.pipeline.planmap")


def outputs_code_version() -> str:
    """Hash of the code that draws and writes a run's outputs (:data:`OUTPUT_MODULES` and every
    module they import, read with :func:`~skyroute.pipeline.graph.code_version_of`, nothing
    imported): part of every figure, GeoTIFF and plan-file key, as a stage's code is part of its
    key, so a warm run after an edit to a figure or an export rewrites it."""
    from skyroute.pipeline.graph import code_version_of

    return code_version_of(modules=OUTPUT_MODULES, salt="run-outputs")


def output_key(result: RunResult, stages: tuple[str, ...], code: str | None = None) -> str:
    """The key of an output drawn from ``stages`` of ``result`` (a figure, a GeoTIFF): their
    stage keys and the output code (:func:`outputs_code_version`).  ``summary.json``'s
    ``output_keys`` and the output memo (:mod:`skyroute.pipeline.output_memo`) use it."""
    keys = {r.name: r.key for r in result.records}
    return "+".join([*(keys[s] for s in stages), code or outputs_code_version()])


def map_figure(result: RunResult, path: Path, rel: str, stages: tuple[str, ...], make) -> Path:
    """``make(path)`` of a figure drawn from ``stages`` (``rel``: its name in a run folder, e.g.
    ``figures/maps.png``), or its copy from the output memo when it was drawn before from the
    same cached stages by the same code."""
    from skyroute.pipeline.output_memo import computed_in_run, memo_of

    cached = all(r.path for r in result.records if r.name in stages)
    memo = memo_of(result) if cached else None
    if memo is None:
        make(path)
    else:
        memo.make(f"{rel}|{output_key(result, stages)}", path, make, fresh=computed_in_run(result, stages))
    return Path(path)


def plan_output_key(result: RunResult, code: str | None = None) -> str:
    """The key of a plan's files (:func:`plan_outputs`): the plan stage's key, what the pilot
    exports read beyond it (``data.ground``...: :func:`~skyroute.pipeline.plan_exports.export_key`)
    and the output code (:func:`outputs_code_version`)."""
    from skyroute.pipeline.plan_exports import export_key

    rec = next(r for r in result.records if r.name == "plan")
    return f"{rec.key}+{export_key(result)}+{code or outputs_code_version()}"


@phased("plan files")
def plan_outputs(result: RunResult, plan_dir: Path, prefix: str = "",
                 key: str | None = None) -> tuple[list[str], dict[str, Any], dict[str, Any]]:
    """The plan files (:func:`write_plan_outputs`) in ``plan_dir`` and the summary's ``plan`` and
    ``exports`` sections (their file names prefixed by ``prefix``, e.g. ``plan/`` inside a run
    folder): ``(file names relative to plan_dir, plan section, exports section)``.  With ``key``
    (the plan stage's key, the exports' and the output code's), copied from the output memo
    (:mod:`skyroute.pipeline.output_memo`) when they were written before, else written and
    memoised: a warm command into a new folder reads no dataset and draws nothing."""
    from skyroute.pipeline.output_memo import computed_in_run, memo_of
    from skyroute.pipeline.plan_exports import exports_section

    plan_dir = Path(plan_dir)
    memo = memo_of(result) if key is not None else None
    mkey = f"plan-files|{prefix}|{key}"
    if memo is not None and not computed_in_run(result):     # --force of any stage: written again
        meta = memo.fetch(mkey, plan_dir)
        if meta and isinstance(meta.get("files"), list):
            return list(meta["files"]), meta["plan"], meta["exports"]
    written = write_plan_outputs(result, plan_dir)
    rel = sorted(Path(p).resolve().relative_to(plan_dir.resolve()).as_posix() for p in written.values())
    # a callable scheduler: dask looks a named one up by importing distributed (~0.5 s)
    from dask.local import get_sync

    plan = plan_section(result["plan"].compute(scheduler=get_sync))   # small: read at once
    exports = exports_section(result, [prefix + f for f in rel], plan_dir.parent if prefix else plan_dir)
    if memo is not None:
        memo.store(mkey, plan_dir, {"files": rel, "plan": plan, "exports": exports}, only=rel)
    return rel, plan, exports


@phased("outputs")
def write_run_outputs(result: RunResult, out_dir: Path, command: str = "run", link: bool = False,
                      extra: dict[str, Any] | None = None, also_files: tuple[str, ...] = ()) -> dict[str, Any]:
    """Write copies of the cached zarr datasets (symlinks into the cache with ``link``), GeoTIFFs,
    PNG figures, the plan files and ``summary.json`` (see :func:`write_summary`; with a ``plan``
    section when the plan stage ran; ``extra``: ``{"files": [...], "section": {...}}`` of the
    flight replay written under ``DIR/fly/``, listed here too; ``also_files``: files the caller
    writes into ``out_dir`` after this, e.g. ``report.html``, listed too).  Copies make the folder self-contained: it survives
    ``skyroute cache clear`` and can be archived or moved.

    A GeoTIFF or figure is rewritten only when the stage keys it was made from or the output code
    (:func:`outputs_code_version`) changed, or the file is missing, so a warm re-run costs little
    more than deriving the keys.
    """
    out_dir = Path(out_dir)
    (out_dir / "datasets").mkdir(parents=True, exist_ok=True)
    (out_dir / "figures").mkdir(exist_ok=True)
    code = outputs_code_version()
    previous = previous_summary(out_dir)
    prev_keys = previous.get("output_keys", {})
    prev_files = previous.get("files", [])
    keys = {r.name: r.key for r in result.records}
    output_keys: dict[str, str] = {}
    files: list[str] = []

    uncached = {r.name for r in result.records if not r.path}   # load-dependent results kept in memory only
    from skyroute.pipeline.outfolder import folder_of

    staged = folder_of(out_dir)
    from skyroute.pipeline.output_memo import memo_of

    memo = memo_of(result)
    computed = {r.name for r in result.records if not r.cache_hit}   # this run: never from the memo

    def _kept(rel: str) -> bool:
        """``rel`` of the previous run is reused as it is (a staged command keeps it in place)."""
        if staged is not None:
            return staged.reuse(rel)
        p = out_dir / rel
        return p.is_dir() and not p.is_symlink() if rel.endswith(".zarr") else p.is_file()

    def produce(rel: str, stage: str | tuple[str, ...], make) -> None:
        stages = (stage,) if isinstance(stage, str) else tuple(stage)
        key = output_key(result, stages, code)
        reusable = not uncached.intersection(stages)
        path = out_dir / rel
        note(rel)                          # the progress line's current file
        if not (reusable and not computed & set(stages) and prev_keys.get(rel) == key and _kept(rel)):
            if reusable and memo is not None:        # a new folder: copied from the memo when drawn before
                memo.make(f"{rel}|{key}", path, make, fresh=bool(computed & set(stages)))
            else:
                make(path)
        output_keys[rel] = key if reusable else ""
        files.append(rel)

    for rec in result.records:
        rel = f"datasets/{rec.name}.zarr"
        dst = out_dir / rel
        note(rel)
        if not rec.path:                   # not cached: written from memory, never reused by key
            _write_store(result[rec.name], dst)
            output_keys[rel] = ""
            files.append(rel)
            continue
        src = Path(rec.path) / "data.zarr"
        if link:
            remove_path(dst)
            os.symlink(src, dst)
        elif not (rec.cache_hit and prev_keys.get(rel) == rec.key and _kept(rel)):   # --force: again
            _copy_store(src, dst)
        output_keys[rel] = rec.key
        files.append(rel)
    if "surface" in result.datasets:
        produce("surface.tif", "surface",
                lambda p: result["surface"]["surface"].rio.to_raster(p, compress="deflate"))
        produce("figures/surface.png", "surface", lambda p: plot_surface(result, p))
    if "surface" in result.datasets and "environment" in result.datasets:
        def draw_maps(p: Path) -> None:
            from skyroute.pipeline.maps import plot_maps_panel

            plot_maps_panel(result, p)

        drawn = tuple(s for s in ("surface", "environment", "wind", "clearance", "traffic") if s in keys)
        produce("figures/maps.png", drawn, draw_maps)
    if "coverage" in result.datasets:
        def draw_coverage(p: Path) -> None:
            from skyroute.pipeline.cli_coverage import plot_coverage

            plot_coverage(result["coverage"], p)

        kind = str(stage_attrs(result, "coverage").get("dop_kind", "DOP"))
        produce(f"figures/coverage_{kind}.png", "coverage", draw_coverage)
    sections: dict[str, Any] = {}
    if "plan" in result.datasets:
        plan_key = plan_output_key(result, code)
        old = [f for f in prev_files if f.startswith("plan/")]
        # (a folder written before plan.html existed gets its plan files rewritten once)
        reused = ("plan" not in uncached and not computed and prev_keys.get("plan/") == plan_key and old
                  and "plan/plan.html" in old and all(_kept(f) for f in old)
                  and isinstance(previous.get("plan"), dict) and isinstance(previous.get("exports"), dict))
        output_keys["plan/"] = plan_key if "plan" not in uncached else ""
        if reused:        # same plan stage, same exports: the same files and sections (not read again)
            files.extend(old)
            sections["plan"], sections["exports"] = previous["plan"], previous["exports"]
        else:
            rel_files, sections["plan"], sections["exports"] = plan_outputs(
                result, out_dir / "plan", "plan/", plan_key if "plan" not in uncached else None)
            files.extend(f"plan/{f}" for f in rel_files)
    files.extend(also_files)
    if extra is not None:
        files.extend(extra["files"])
        sections["fly"] = extra["section"]
    sc = result.scenario
    remove_stale(out_dir, previous, files, command)
    sections = {
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
        "output_keys": output_keys,
        **sections,
    }
    export_notes = list((sections.get("exports") or {}).get("notes", []))   # a pilot file not written
    return write_summary(out_dir, command, files, stage_warnings(result) + export_notes, sections)


def report_warnings(warnings: list[str]) -> None:
    """Each warning as one ``warning: <text>`` line on stderr."""
    import click

    for w in warnings:
        click.echo(f"warning: {w}", err=True)


def write_folder_summary(out_dir: Path, command: str, result, files, sections: dict) -> dict:
    """summary.json of a folder-writing command (files relative to ``out_dir``, stage warnings
    printed on stderr), removing the files an earlier summary listed that were not rewritten."""
    rel = relative_files(out_dir, files)
    remove_stale(Path(out_dir), previous_summary(Path(out_dir)), rel, command)
    warnings = stage_warnings(result) + [n for n in (sections.get("exports") or {}).get("notes", [])]
    report_warnings(warnings)
    sc = result.scenario
    return write_summary(out_dir, command, rel, warnings, {
        "scenario": sc.name,
        "scenario_path": None if sc.source_path is None else str(Path(sc.source_path).resolve()),
        "stages": [{"name": r.name, "key": r.key, "cache_hit": r.cache_hit, "seconds": round(r.seconds, 4)}
                   for r in result.records],
        "seconds": result.seconds, **sections})

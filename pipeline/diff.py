"""``skyroute diff RUN_A RUN_B``: what changed between two skyroute output folders.

Reads only what the folders hold (``summary.json``, the CSVs, ``datasets/*.zarr`` and the
GeoTIFFs); never the cache or the scenario files.  Sections, each compared when both folders
have it:

* ``scenario``: the command, scenario name, description, CRS and grid, and the settings a
  summary records (fly: ``t_rep_s``, ``tick_s``, ``seed``, ``dop_threshold``, ``clearance``,
  ``tactical_method``; navsim: ``runs``, ``seed``, ``source``, ``surface_uncertainty_m``);
* ``plan``: the chosen plan (status, label, DOP level, f and its terms [m], length [m],
  energy [Wh], flight time [s], clearance radius [m]) and how it was made (``provenance``:
  planner, seed, weights, budget, counted budgets, vehicle, skyroute version);
* ``candidates``: per coverage level (``candidates.csv`` row label) its flyability, costs [m],
  energy [Wh], flight time [s], max sigma_p [m] and whether it was chosen;
* ``stages``: stage cache keys (a changed key = the stage's code, settings or inputs
  changed); which stages were computed rather than read from the cache is a note, not a change;
* ``fly``: outcome, replannings, chosen levels, levels tried / flyable per replanning,
  flight time, length, energy, closest approach per intruder [m];
* ``navsim``: runs, epochs, k-sigma containment per filter, share of time the proposed error
  is the smaller, RMS and 95 % errors [m], protection-level medians [m];
* ``compare``: per planner its flyability, f, length, energy, clearances;
* ``maps``: per raster (a variable of ``datasets/*.zarr`` whose last two dims are ``(y, x)``,
  and every band of every ``*.tif`` the summaries list) the largest absolute difference and
  the number of cells that differ (NaN against NaN is equal; a shape or grid change is one
  change with a note);
* ``files``: files only one folder lists.

Timings (``seconds``, ``compute_s`` ...) are never compared.  Numbers are equal when they
differ by at most 1e-9 of their size (JSON and CSV round trips).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from skyroute.pipeline.errors import InputError

__all__ = ["SECTIONS", "Change", "DiffResult", "diff_folders", "format_diff", "raster_difference", "read_summary"]

SECTIONS = ("scenario", "plan", "candidates", "stages", "fly", "navsim", "compare", "maps", "files")

# keys never compared (wall-clock timings, cache bookkeeping)
_TIMING = {"seconds", "compute_s", "compute_time_s", "plan_cached", "update_s", "compile_s", "cache_hits", "cache_hit", "path",
           "created_utc"}

_PLAN_KEYS = ("status", "label", "dop_threshold", "f_m", "C_l_m", "C_r_m", "C_d_m", "C_e_m", "length_m", "energy_Wh",
              "flight_time_s", "clearance_radius_m")
_PROVENANCE_KEYS = ("planner", "seed", "time_budget_s", "max_tries", "step_cells", "vehicle", "vehicle_profile_hash",
                    "skyroute_version")
_FLY_SETTINGS = ("t_rep_s", "tick_s", "seed", "dop_threshold", "clearance", "tactical_method")
_FLY_KEYS = ("outcome", "reason", "n_replannings", "flight_time_s", "length_m", "energy_Wh")
_NAVSIM_SETTINGS = ("runs", "seed", "source", "surface_uncertainty_m")


@dataclass
class Change:
    """One difference: ``section`` (one of :data:`SECTIONS`), ``item`` (what), the values in
    A and B, ``delta`` = B - A for numbers (None otherwise), its ``unit`` and a ``note``."""

    section: str
    item: str
    a: Any
    b: Any
    delta: float | None = None
    unit: str = ""
    note: str = ""


@dataclass
class DiffResult:
    """``changes`` (empty: nothing differs), ``compared`` (the sections both folders had),
    ``notes`` (e.g. stages computed rather than read from the cache) and the two folders."""

    a: Path
    b: Path
    command_a: str
    command_b: str
    changes: list[Change] = field(default_factory=list)
    compared: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def same(self) -> bool:
        return not self.changes

    def by_section(self, section: str) -> list[Change]:
        return [c for c in self.changes if c.section == section]

    def to_json(self) -> dict[str, Any]:
        """A JSON-safe document (non-finite numbers as strings ``inf``, ``-inf``, ``nan``)."""
        return _json_safe({"a": str(self.a), "b": str(self.b), "command_a": self.command_a,
                           "command_b": self.command_b, "same": self.same, "compared": list(self.compared),
                           "notes": list(self.notes), "changes": [asdict(c) for c in self.changes]})


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else ("nan" if math.isnan(f) else ("inf" if f > 0 else "-inf"))
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.bool_,)):
        return bool(v)
    return v


# ------------------------------------------------------------------ reading
def read_summary(folder: Path | str, name: str = "folder") -> dict[str, Any]:
    """``folder/summary.json`` of a skyroute output folder; :class:`InputError` (one line, exit
    2) when ``folder`` is not one."""
    folder = Path(folder)
    hint = "give a folder written by skyroute run, plan, fly, navsim, compare, maps or coverage"
    if not folder.is_dir():
        raise InputError(f"{name} {folder}: no such folder ({hint})")
    path = folder / "summary.json"
    from skyroute.pipeline.outputs import check_summary_files, unfinished_rewrite

    if unfinished_rewrite(folder):
        raise InputError(f"{name} {folder} was being rewritten by a command that did not finish (interrupted or "
                         "failed): its files may mix two runs; run that command again")
    if not path.is_file():
        raise InputError(f"{name} {folder} is not a skyroute output folder (no summary.json): {hint}")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{name} {folder}: summary.json is not valid JSON ({exc}): {hint}") from None
    if not isinstance(doc, dict) or "schema_version" not in doc or "command" not in doc:
        raise InputError(f"{name} {folder}: summary.json has no schema_version / command, so it was not written "
                         f"by skyroute: {hint}")
    from skyroute.pipeline.summary_schema import check_summary

    check_summary(doc, folder, name)      # every value read below has its type (a hand-edited summary)
    check_summary_files(folder, doc, name)
    return doc


def _unit(name: str) -> str:
    for suffix, unit in (("_Wh", "Wh"), ("_m2", "m^2"), ("_m", "m"), ("_s", "s"), ("_deg", "deg"),
                         ("_mps", "m/s"), ("_J", "J")):
        if name.endswith(suffix):
            return unit
    if "sigma" in name or name.endswith("share") or name in ("proposed_beats_weak", "availability"):
        return "fraction"
    return ""


def _as_number(v: Any) -> float | None:
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, (int, float, np.integer, np.floating)):
        return float(v)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return None
    return None


def _equal(a: Any, b: Any) -> bool:
    na, nb = _as_number(a), _as_number(b)
    if na is not None and nb is not None:
        if math.isnan(na) or math.isnan(nb):
            return math.isnan(na) and math.isnan(nb)
        if math.isinf(na) or math.isinf(nb):
            return na == nb
        return abs(na - nb) <= 1e-9 * max(1.0, abs(na), abs(nb))
    return a == b


def _change(section: str, item: str, a: Any, b: Any, unit: str | None = None, note: str = "") -> Change | None:
    if _equal(a, b):
        return None
    na, nb = _as_number(a), _as_number(b)
    delta = nb - na if na is not None and nb is not None and math.isfinite(na) and math.isfinite(nb) else None
    return Change(section, item, a, b, delta, _unit(item) if unit is None else unit, note)


def _compare_keys(out: list[Change], section: str, a: dict, b: dict, keys, prefix: str = "",
                  both: bool = False) -> None:
    """A change per key of ``keys`` whose values differ (``both``: only keys both documents have)."""
    for k in keys:
        if k in _TIMING or (k not in a and k not in b) or (both and (k not in a or k not in b)):
            continue
        c = _change(section, f"{prefix}{k}", a.get(k), b.get(k), _unit(k))
        if c is not None:
            out.append(c)


def _read_csv(path: Path) -> list[dict[str, str]]:
    try:
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))
    except (OSError, csv.Error):
        return []


def _file(folder: Path, summary: dict[str, Any], name: str) -> Path | None:
    """The file ``name`` (a base name) the summary lists, if on disk."""
    for f in summary.get("files", []):
        if Path(f).name == name and (folder / f).is_file():
            return folder / f
    return None


# ------------------------------------------------------------------ sections
def _scenario(a: dict, b: dict) -> list[Change]:
    out: list[Change] = []
    _compare_keys(out, "scenario", a, b, ("command",))
    _compare_keys(out, "scenario", a, b, ("scenario", "description", "crs"), both=True)   # not every command records them
    ga, gb = a.get("grid"), b.get("grid")
    if isinstance(ga, dict) and isinstance(gb, dict):
        _compare_keys(out, "scenario", ga, gb, ("nx", "ny", "resolution_m"), "grid.")
        if not all(_equal(x, y) for x, y in zip(ga.get("bounds", []), gb.get("bounds", []), strict=False)):
            out.append(Change("scenario", "grid.bounds", ga.get("bounds"), gb.get("bounds"), None, "m"))
    fa, fb = a.get("fly"), b.get("fly")
    if isinstance(fa, dict) and isinstance(fb, dict):
        _compare_keys(out, "scenario", fa, fb, _FLY_SETTINGS, "fly.")
    na, nb = a.get("navsim"), b.get("navsim")
    if isinstance(na, dict) and isinstance(nb, dict):
        _compare_keys(out, "scenario", na, nb, _NAVSIM_SETTINGS, "navsim.")
    return out


def _plan(a: dict, b: dict) -> list[Change]:
    out: list[Change] = []
    _compare_keys(out, "plan", a, b, _PLAN_KEYS)
    ra, rb = a.get("reasons") or [], b.get("reasons") or []
    if ra != rb:
        out.append(Change("plan", "reasons", " | ".join(ra), " | ".join(rb)))
    pa, pb = a.get("provenance"), b.get("provenance")      # how each plan was made
    if isinstance(pa, dict) and isinstance(pb, dict):
        _compare_keys(out, "plan", pa, pb, _PROVENANCE_KEYS, "provenance.")
        if [float(w) for w in pa.get("weights", [])] != [float(w) for w in pb.get("weights", [])]:
            out.append(Change("plan", "provenance.weights", pa.get("weights"), pb.get("weights")))
        _compare_keys(out, "plan", pa.get("budgets") or {}, pb.get("budgets") or {},
                      sorted({*(pa.get("budgets") or {}), *(pb.get("budgets") or {})}), "provenance.budgets.")
    return out


def _candidates(rows_a: list[dict[str, str]], rows_b: list[dict[str, str]]) -> list[Change]:
    out: list[Change] = []
    by_a = {r.get("label", str(i)): r for i, r in enumerate(rows_a)}
    by_b = {r.get("label", str(i)): r for i, r in enumerate(rows_b)}
    for label in sorted(set(by_a) | set(by_b)):
        if label not in by_b:
            out.append(Change("candidates", label, "present", "absent", note="level only in A"))
            continue
        if label not in by_a:
            out.append(Change("candidates", label, "absent", "present", note="level only in B"))
            continue
        ra, rb = by_a[label], by_b[label]
        cols = [c for c in ra if c in rb and c != "label" and c not in _TIMING]
        _compare_keys(out, "candidates", ra, rb, cols, f"{label}.")
    return out


def _stages(a: dict, b: dict, notes: list[str]) -> list[Change]:
    out: list[Change] = []
    ka = {s["name"]: s.get("key") for s in a.get("stages", []) if isinstance(s, dict) and "name" in s}
    kb = {s["name"]: s.get("key") for s in b.get("stages", []) if isinstance(s, dict) and "name" in s}
    for name in list(ka) + [n for n in kb if n not in ka]:
        if name not in kb:
            out.append(Change("stages", name, ka[name], None, note="stage only in A"))
        elif name not in ka:
            out.append(Change("stages", name, None, kb[name], note="stage only in B"))
        elif ka[name] != kb[name]:
            out.append(Change("stages", name, ka[name], kb[name],
                              note="cache key changed: its code, settings or inputs differ"))
    for tag, doc in (("A", a), ("B", b)):
        run = [s["name"] for s in doc.get("stages", []) if isinstance(s, dict) and s.get("cache_hit") is False]
        if run:
            notes.append(f"{tag}: stages computed (not from the cache): {', '.join(run)}")
    return out


def _fly(a: dict, b: dict) -> list[Change]:
    out: list[Change] = []
    _compare_keys(out, "fly", a, b, _FLY_KEYS)
    for key in ("chosen_levels",):
        if list(a.get(key) or []) != list(b.get(key) or []):
            out.append(Change("fly", key, ",".join(a.get(key) or []), ",".join(b.get(key) or [])))
    reps_a = {r["replanning"]: r for r in a.get("replannings", [])
              if isinstance(r, dict) and "replanning" in r}
    reps_b = {r["replanning"]: r for r in b.get("replannings", [])
              if isinstance(r, dict) and "replanning" in r}
    for r in sorted(set(reps_a) & set(reps_b)):
        ra, rb = reps_a[r], reps_b[r]
        _compare_keys(out, "fly", ra, rb, ("event", "t_event_s", "t_coll_s", "chosen_level", "added_flight_time_s",
                                            "f_m"), f"replanning {r}.")
        for key in ("levels_tried", "levels_flyable"):
            if list(ra.get(key) or []) != list(rb.get(key) or []):
                out.append(Change("fly", f"replanning {r}.{key}", ",".join(ra.get(key) or []),
                                  ",".join(rb.get(key) or [])))
    sep_a = {s["id"]: s for s in a.get("min_separation", []) if isinstance(s, dict) and "id" in s}
    sep_b = {s["id"]: s for s in b.get("min_separation", []) if isinstance(s, dict) and "id" in s}
    for i in sorted(set(sep_a) | set(sep_b)):
        va = sep_a.get(i, {}).get("min_distance_m")
        vb = sep_b.get(i, {}).get("min_distance_m")
        c = _change("fly", f"closest approach {i}", va, vb, "m")
        if c is not None:
            out.append(c)
    return out


def _navsim(a: dict, b: dict) -> list[Change]:
    out: list[Change] = []
    _compare_keys(out, "navsim", a, b, ("epochs", "proposed_beats_weak", "nlos_used_share"))
    for f in ("proposed", "weak"):
        ca = (a.get("containment") or {}).get(f) or {}
        cb = (b.get("containment") or {}).get(f) or {}
        _compare_keys(out, "navsim", ca, cb, sorted(set(ca) | set(cb)), f"containment.{f}.")
        _compare_keys(out, "navsim", a.get(f) or {}, b.get(f) or {},
                      sorted(set(a.get(f) or {}) | set(b.get(f) or {})), f"{f}.")
    pa, pb = a.get("protection_level") or {}, b.get("protection_level") or {}
    _compare_keys(out, "navsim", pa, pb, sorted(k for k in set(pa) | set(pb) if not isinstance(pa.get(k), (dict, list))),
                  "protection_level.")
    return out


def _compare(a: dict, b: dict) -> list[Change]:
    out: list[Change] = []
    pa = {r.get("planner"): r for r in a.get("planners", []) if isinstance(r, dict)}
    pb = {r.get("planner"): r for r in b.get("planners", []) if isinstance(r, dict)}
    for p in sorted(set(pa) | set(pb), key=str):
        if p not in pb or p not in pa:
            out.append(Change("compare", str(p), "present" if p in pa else "absent", "present" if p in pb else "absent",
                              note="planner only in " + ("A" if p in pa else "B")))
            continue
        _compare_keys(out, "compare", pa[p], pb[p], [k for k in pa[p] if k != "planner"], f"{p}.")
    return out


# ------------------------------------------------------------------ rasters
def raster_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """``(max |b - a|, cells that differ)`` of two arrays of the same shape: NaN against NaN
    and equal infinities are equal; a NaN or infinity against anything else is a changed cell
    with an infinite difference."""
    a = np.asarray(a)
    b = np.asarray(b)
    if a.dtype.kind not in "fiub" or b.dtype.kind not in "fiub":
        changed = a != b
        return (math.inf if changed.any() else 0.0), int(changed.sum())
    a = a.astype(float)
    b = b.astype(float)
    both_nan = np.isnan(a) & np.isnan(b)
    finite = np.isfinite(a) & np.isfinite(b)
    same_inf = np.isinf(a) & np.isinf(b) & (a == b)
    d = np.abs(np.subtract(b, a, out=np.zeros_like(a), where=finite))
    odd = ~(finite | both_nan | same_inf)             # NaN or inf on one side only
    changed = (finite & (d > 0)) | odd
    n = int(changed.sum())
    if odd.any():
        return math.inf, n
    return (float(d.max()) if d.size else 0.0), n


def _zarr_rasters(store: Path) -> dict[str, tuple[np.ndarray, str, tuple]]:
    import xarray as xr

    out = {}
    try:
        ds = xr.open_zarr(store, consolidated=False, decode_timedelta=False)
    except Exception:                                    # noqa: BLE001 - unreadable store: no rasters
        return out
    for name, v in ds.data_vars.items():
        if v.ndim >= 2 and v.dims[-2:] == ("y", "x"):
            grid = (tuple(np.asarray(ds["x"].values)[[0, -1]]), tuple(np.asarray(ds["y"].values)[[0, -1]]))
            out[str(name)] = (v, str(v.attrs.get("units", "")), grid)
    return out


def _tif_bands(path: Path) -> dict[str, tuple[np.ndarray, str, tuple]]:
    import rasterio

    out = {}
    try:
        with rasterio.open(path) as src:
            nodata = src.nodata
            for i in range(1, src.count + 1):
                arr = src.read(i).astype(float) if nodata is not None else src.read(i)
                if nodata is not None:
                    arr[arr == nodata] = np.nan
                out[f"band {i}"] = (arr, src.units[i - 1] or "", tuple(src.transform)[:6])
    except Exception:                                    # noqa: BLE001 - unreadable file: no bands
        return out
    return out


def _maps(fa: Path, fb: Path, sa: dict, sb: dict) -> list[Change]:
    out: list[Change] = []
    files_a = {f for f in sa.get("files", [])}
    files_b = {f for f in sb.get("files", [])}
    stores = sorted(f for f in files_a & files_b if f.endswith(".zarr"))
    tifs = sorted(f for f in files_a & files_b if f.endswith((".tif", ".tiff")))
    for rel in stores:
        ra, rb = _zarr_rasters(fa / rel), _zarr_rasters(fb / rel)
        for name in sorted(set(ra) | set(rb)):
            item = f"{Path(rel).stem}.{name}"
            if name not in ra or name not in rb:
                out.append(Change("maps", item, "present" if name in ra else "absent",
                                  "present" if name in rb else "absent", note="raster only in " + ("A" if name in ra else "B")))
                continue
            out.extend(_raster_change(item, ra[name], rb[name]))
    for rel in tifs:
        ba, bb = _tif_bands(fa / rel), _tif_bands(fb / rel)
        for band in sorted(set(ba) | set(bb)):
            item = f"{rel}:{band}" if max(len(ba), len(bb)) > 1 else rel
            if band not in ba or band not in bb:
                out.append(Change("maps", item, "present" if band in ba else "absent",
                                  "present" if band in bb else "absent", note="band only in " + ("A" if band in ba else "B")))
                continue
            out.extend(_raster_change(item, ba[band], bb[band]))
    return out


def _raster_change(item: str, a: tuple, b: tuple) -> list[Change]:
    va, unit, grid_a = a
    vb, _, grid_b = b
    if tuple(np.shape(va)) != tuple(np.shape(vb)) or not all(_equal(x, y) for x, y in zip(
            np.ravel(np.asarray(grid_a, dtype=object)), np.ravel(np.asarray(grid_b, dtype=object)), strict=False)):
        return [Change("maps", item, f"shape {tuple(np.shape(va))}", f"shape {tuple(np.shape(vb))}", None, "",
                       "different grids: cells not compared")]
    diff, n = raster_difference(np.asarray(va), np.asarray(vb))
    if n == 0:
        return []
    return [Change("maps", item, None, None, diff, unit,
                   f"{n} of {int(np.size(va))} cells differ")]


# ------------------------------------------------------------------ driver
def diff_folders(a: Path | str, b: Path | str, *, maps: bool = True) -> DiffResult:
    """Compare two skyroute output folders (see the module docstring); ``maps=False`` skips
    the rasters (the slowest part on city-size grids)."""
    a, b = Path(a), Path(b)
    sa, sb = read_summary(a, "RUN_A"), read_summary(b, "RUN_B")
    res = DiffResult(a, b, str(sa["command"]), str(sb["command"]))
    if sa["command"] != sb["command"]:
        res.notes.append(f"different commands: A is `{sa['command']}`, B is `{sb['command']}`; only the sections "
                         "both have are compared")
    res.compared.append("scenario")
    res.changes.extend(_scenario(sa, sb))
    if isinstance(sa.get("plan"), dict) and isinstance(sb.get("plan"), dict):
        res.compared.append("plan")
        res.changes.extend(_plan(sa["plan"], sb["plan"]))
    ca, cb = _file(a, sa, "candidates.csv"), _file(b, sb, "candidates.csv")
    if ca is not None and cb is not None:
        res.compared.append("candidates")
        res.changes.extend(_candidates(_read_csv(ca), _read_csv(cb)))
    if sa.get("stages") and sb.get("stages"):
        res.compared.append("stages")
        res.changes.extend(_stages(sa, sb, res.notes))
    for name, fn in (("fly", _fly), ("navsim", _navsim), ("compare", _compare)):
        if isinstance(sa.get(name), dict) and isinstance(sb.get(name), dict):
            res.compared.append(name)
            res.changes.extend(fn(sa[name], sb[name]))
    if maps:
        res.compared.append("maps")
        res.changes.extend(_maps(a, b, sa, sb))
    if sa["command"] != sb["command"]:
        return res                            # different commands write different files
    res.compared.append("files")
    fa, fb = set(sa.get("files", [])), set(sb.get("files", []))
    for f in sorted(fa - fb):
        res.changes.append(Change("files", f, "present", "absent", note="only in A"))
    for f in sorted(fb - fa):
        res.changes.append(Change("files", f, "absent", "present", note="only in B"))
    return res


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "true" if v else "false"
    n = _as_number(v)
    if n is not None and not isinstance(v, str):
        return f"{n:.6g}" if math.isfinite(n) else str(n)
    s = str(v)
    return s if len(s) <= 40 else s[:37] + "..."


def _delta_text(c: Change) -> str:
    if c.delta is None:
        return ""
    unit = f" {c.unit}" if c.unit else ""
    if c.section == "maps":                    # the largest absolute difference of the raster
        return f"max {c.delta:.6g}{unit}"
    return f"{c.delta:+.6g}{unit}"


def format_diff(res: DiffResult) -> str:
    """The readable table ``skyroute diff`` prints: one block per section with changes
    (item, A, B, B - A with its unit, note), then the notes."""
    lines = [f"A: {res.a} ({res.command_a})", f"B: {res.b} ({res.command_b})"]
    if res.same:
        lines.append(f"no differences ({', '.join(res.compared)} compared)")
    for section in SECTIONS:
        rows = res.by_section(section)
        if not rows:
            continue
        lines.append("")
        lines.append(f"[{section}] {len(rows)} change{'s' if len(rows) != 1 else ''}")
        cells = [(c.item, _fmt(c.a), _fmt(c.b), _delta_text(c), c.note) for c in rows]
        w = [max(len(r[i]) for r in [("item", "A", "B", "B - A", ""), *cells]) for i in range(4)]
        lines.append(f"  {'item':<{w[0]}}  {'A':<{w[1]}}  {'B':<{w[2]}}  {'B - A':<{w[3]}}  note")
        for r in cells:
            lines.append(f"  {r[0]:<{w[0]}}  {r[1]:<{w[1]}}  {r[2]:<{w[2]}}  {r[3]:<{w[3]}}  {r[4]}".rstrip())
    unchanged = [s for s in res.compared if not res.by_section(s)]
    if unchanged and not res.same:
        lines.append("")
        lines.append(f"unchanged: {', '.join(unchanged)}")
    for n in res.notes:
        lines.append(f"note: {n}")
    return "\n".join(lines)

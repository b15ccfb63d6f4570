"""``skyroute compare``: several STEP I planners on the same maps, one table and one figure.

Each planner plans the scenario through the cached pipeline with only ``planner.name``
changed, so every map stage (surface, environment, clearance, wind, coverage, satellites,
traffic) is shared and only the plan stage differs.  Per planner the table gives the chosen
candidate's f (seed 000 eq. 11 on the written trajectory, one definition for every planner) and
its terms [m], the planner's own search objective where it is not f (``search_cost_m``, the
fixed-wing planners; NaN otherwise), 3-D length [m], energy [Wh], flight time
[s], the minimum exact clearance of the written trajectory from the surface prisms [m] (brute
force over the cells around each sample, :func:`~skyroute.stages.planning.validate.surface_clearance_m`),
the largest sigma_p [m], the planner's compute time over all levels [s] (measured when the
plan was computed; a cached plan keeps it, and ``plan_cached`` says the plan was read from the
stage cache: the console line then says ``compute 62.91 s (cached)``) and whether it is
flyable.  A planner that does not apply (e.g. to the vehicle kind) or finds no flyable plan
gets its row with the reason.
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.errors import InputError, SkyrouteError
from skyroute.pipeline.settings import PLANNERS, Scenario

__all__ = ["CLEARANCE_WINDOW_M", "COLUMNS", "CompareRow", "compare_planners", "json_safe", "write_compare"]

CLEARANCE_WINDOW_M = 50.0     # clearances above this are reported as this (the brute-force window)
COLUMNS = ("planner", "flyable", "label", "dop_threshold", "f_m", "C_l_m", "C_r_m", "C_d_m", "C_e_m", "search_cost_m",
           "length_m", "energy_Wh", "flight_time_s", "min_clearance_m", "mean_clearance_m", "max_sigma_p_m", "compute_s",
           "reason", "plan_cached")
# compute_s [s]: the wall time of the planner's plan stage (all levels, which run in parallel and
# may share a solution: never the sum of the per-level times); plan_cached: true when that plan
# was read from the stage cache (compute_s is then the time it took when it was computed)


@dataclass
class CompareRow:
    planner: str
    values: dict[str, Any] = field(default_factory=dict)
    xyz_m: np.ndarray | None = None       # the chosen trajectory's samples (map frame, surface datum)

    @property
    def flyable(self) -> bool:
        return bool(self.values.get("flyable"))


def _row(planner: str, result) -> CompareRow:
    """The compare.csv row of ``planner`` from its run (see :data:`COLUMNS`)."""
    from skyroute.stages.grid import Grid
    from skyroute.stages.planning.strategic import plan_from_dataset
    from skyroute.stages.planning.validate import surface_clearance_m

    ds = result["plan"].load()
    chosen, cands = plan_from_dataset(ds)
    compute_s = float(ds.attrs.get("compute_s", math.nan))
    cached = next((bool(r.cache_hit) for r in result.records if r.name == "plan"), False)
    if chosen is None:
        why = str(ds.attrs.get("reason", "")) or "; ".join(f"{c.label}: {'; '.join(c.reasons)}" for c in cands)
        return CompareRow(planner, {"planner": planner, "flyable": False, "compute_s": compute_s,
                                    "reason": why or "no flyable plan", "plan_cached": cached})
    surf = result["surface"]["surface"]
    grid = Grid.from_dataarray(surf)
    xyz = np.asarray(chosen.xyz_m, float)
    d = np.minimum(surface_clearance_m(xyz, grid=grid, surface_m=np.asarray(surf.values, float),
                                       radius_m=CLEARANCE_WINDOW_M), CLEARANCE_WINDOW_M)
    v = {"planner": planner, "flyable": bool(chosen.flyable), "label": chosen.label,
         "dop_threshold": chosen.dop_threshold, "f_m": chosen.f, "C_l_m": chosen.C_l, "C_r_m": chosen.C_r,
         "C_d_m": chosen.C_d, "C_e_m": chosen.C_e, "search_cost_m": chosen.search_cost_m,
         "length_m": float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()),
         "energy_Wh": chosen.energy_J / 3600.0, "flight_time_s": chosen.flight_time_s,
         "min_clearance_m": float(d.min()), "mean_clearance_m": float(d.mean()),
         "max_sigma_p_m": (float(np.nanmax(chosen.sigma_p_m)) if np.isfinite(chosen.sigma_p_m).any()
                           else math.nan),         # NaN: no GNSS data (e.g. no almanac)
         "compute_s": compute_s, "reason": "", "plan_cached": cached}
    return CompareRow(planner, v, xyz)


def compare_planners(sc: Scenario, planners: list[str], *, cache: Cache | None = None,
                     scheduler: str = "threads", echo=None) -> tuple[list[CompareRow], Any]:
    """One :class:`CompareRow` per planner (in order) and the RunResult of the shared maps."""
    from skyroute.pipeline.runner import run_scenario

    unknown = [p for p in planners if p not in PLANNERS]
    if unknown:
        raise InputError(f"unknown planner(s) {', '.join(unknown)}; known planners: {', '.join(PLANNERS)}")
    if not planners:
        raise InputError(f"give at least one planner, e.g. --planners {','.join(PLANNERS)}")
    from skyroute.pipeline.graph import stages_for

    cache = cache or Cache()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        maps = run_scenario(sc, cache=cache, scheduler=scheduler,
                            targets=[s.name for s in stages_for(sc, ["plan"]) if s.name != "plan"])
    rows = []
    for p in planners:
        if echo is not None:
            echo(f"compare: {p}")
        try:
            sc_p = sc.model_copy(update={"planner": sc.planner.model_copy(update={"name": p})})
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = run_scenario(sc_p, cache=cache, targets=["plan"], scheduler=scheduler)
        except SkyrouteError as exc:
            rows.append(CompareRow(p, {"planner": p, "flyable": False, "reason": f"not applicable: {exc}"}))
            continue
        rows.append(_row(p, res))
    return rows, maps


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.3f}"
    return str(v)


def write_compare(rows: list[CompareRow], maps, out_dir: Path, title: str = "") -> dict[str, Path]:
    """``compare.csv`` (columns :data:`COLUMNS`) and ``compare.png`` (top view of every flyable
    planner's path over the surface, and the vertical profiles against distance)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"compare.csv": out_dir / "compare.csv"}
    with open(files["compare.csv"], "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([_fmt(r.values.get(c)) for c in COLUMNS])
    files["compare.png"] = _figure(rows, maps, out_dir / "compare.png", title)
    return files


def json_safe(values: dict[str, Any]) -> dict[str, Any]:
    """``values`` with non-finite floats as None (strict JSON)."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in values.items()}


def _resampled(xyz: np.ndarray, n: int = 200) -> np.ndarray:
    """``xyz`` (m, k) resampled to ``n`` points equally spaced along its length."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, xyz[:, i]) for i in range(xyz.shape[1])])


def same_paths(rows: list[CompareRow], tol_m: float = 0.5, horizontal: bool = False) -> dict[int, int]:
    """``{i: j}`` for each path ``rows[i].xyz_m`` that is the same as an earlier ``rows[j].xyz_m``
    (j the first such): resampled along their lengths, every point within ``tol_m`` [m] (in x, y
    only when ``horizontal``: the same track in a top view).  Drawn over it, it would hide it."""
    out: dict[int, int] = {}
    k = 2 if horizontal else 3
    res = [None if r.xyz_m is None or len(r.xyz_m) < 2 else _resampled(np.asarray(r.xyz_m, float)[:, :k])
           for r in rows]
    for i in range(len(rows)):
        for j in range(i):
            if j not in out and res[i] is not None and res[j] is not None \
                    and float(np.max(np.linalg.norm(res[i] - res[j], axis=1))) <= tol_m:
                out[i] = j
                break
    return out


def _figure(rows: list[CompareRow], maps, path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyroute.stages import figures as F
    from skyroute.stages.figures import add_map_furniture, grow_until_unclipped, image_extent

    surf = maps["surface"]["surface"]
    fig, (ax, axp) = plt.subplots(1, 2, figsize=(13, 7.5), gridspec_kw={"width_ratios": [1.2, 1]},
                                  layout="constrained")
    flown = [r for r in rows if r.xyz_m is not None]
    pts = np.concatenate([r.xyz_m for r in flown]) if flown else None
    im = ax.imshow(np.asarray(surf.values, float), extent=image_extent(surf), cmap="Greys", origin="upper")
    import textwrap

    datum = "\n".join(textwrap.wrap(str(surf.attrs.get("vertical_datum", "datum n/a")), 40)[:2])   # a long datum
    fig.colorbar(im, ax=ax, shrink=0.8, label=f"surface [m]\n{datum}")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    span = float(max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]))) + 120.0 if pts is not None else 0.0
    tol_top = max(3.0, 0.005 * span)      # tracks closer than about 3 px of the top view hide each other
    same_top = same_paths(flown, tol_top, horizontal=True)
    same = same_paths(flown)                              # the same 3-D path (within 0.5 m)
    dashes = ((None, None), (0, (6, 4)), (3, (2, 3)), (0, (1, 2)))   # one more dash per path drawn over another

    def style_of(i: int, groups: dict[int, int]) -> dict:
        first = groups.get(i)
        if first is None:
            return {"ls": "-", "lw": 1.6}
        n = sum(1 for j in range(i) if groups.get(j) == first) + 1
        return {"ls": dashes[min(n, len(dashes) - 1)], "lw": 2.4}   # dashed and wider over the first

    for i, r in enumerate(flown):
        c = colors[i % len(colors)]
        v = r.values
        lab = f"{r.planner}: f {v['f_m']:.0f} m, {v['length_m']:.0f} m, min clear. {v['min_clearance_m']:.1f} m"
        if i in same_top:   # identical or on the same track: dashed, and the legend says so
            lab += (f" (same path as {flown[same[i]].planner}: dashed)" if i in same else
                    f" (within {tol_top:.0f} m of {flown[same_top[i]].planner}'s track: dashed)")
        ax.plot(r.xyz_m[:, 0], r.xyz_m[:, 1], color=c, label=lab, **style_of(i, same_top))
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(r.xyz_m[:, :2], axis=0).T))])
        axp.plot(s, r.xyz_m[:, 2], color=c, label=r.planner + ("" if i not in same else
                                                              f" (= {flown[same[i]].planner}, dashed)"),
                 **style_of(i, same))
    if pts is not None:
        ax.plot(*pts[0, :2], **F.START_STYLE, label="start")
        ax.plot(*flown[0].xyz_m[-1, :2], **F.GOAL_STYLE, label="goal")
        half = 0.5 * max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1])) + 60.0     # square window around every path
        cx, cy = 0.5 * (pts[:, 0].min() + pts[:, 0].max()), 0.5 * (pts[:, 1].min() + pts[:, 1].max())
        ax.set_xlim(cx - half, cx + half)
        ax.set_ylim(cy - half, cy + half)
    skipped = [r for r in rows if r.xyz_m is None]
    if skipped:
        ax.plot([], [], " ", label="no path: " + ", ".join(r.planner for r in skipped))
    # below the map: a legend inside it would cover the start of every path
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), framealpha=0.85)
    from matplotlib.ticker import MaxNLocator

    for a in (ax.xaxis, ax.yaxis):
        a.set_major_locator(MaxNLocator(4))
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("paths, top view")
    add_map_furniture(ax)
    axp.set_xlabel("horizontal distance along the path [m]")
    axp.set_ylabel(f"altitude [m]\n{datum}")
    axp.set_title("vertical profiles")
    axp.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)
    axp.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    grow_until_unclipped(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

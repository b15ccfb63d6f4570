"""The outputs of ``skyroute fleet``: ``fleet.csv`` (:data:`FLEET_COLUMNS`), the intents, the
independent check in the summary section (:func:`write_fleet`) and the top-view figure
(:func:`plot_fleet`)."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from skyroute.pipeline.fleet_check import independent_conflicts, min_separation_m
from skyroute.pipeline.fleet_missions import FleetResult, MissionOutcome
from skyroute.pipeline.settings import Scenario

__all__ = ["FLEET_COLUMNS", "plot_fleet", "write_fleet"]


FLEET_COLUMNS = ("mission", "operator", "priority", "status", "departure_utc", "earliest_s", "delay_s", "dop_level",
                 "energy_Wh", "length_m", "flight_time_s", "compute_s", "attempts", "volumes", "preempted_by",
                 "reason")


# ---------------------------------------------------------------------------------- outputs
def _accepted(res: FleetResult) -> list[MissionOutcome]:
    return [o for o in res.outcomes if o.attempt is not None and o.status != "rejected"]


def write_fleet(res: FleetResult, sc: Scenario, maps: dict, out_dir: Path) -> tuple[list[Path], dict]:
    """fleet.csv, intents/<mission>.json (accepted, delayed, re-planned), fleet.geojson,
    tracks.csv (0.05 s), fleet.png; returns (files, summary ``fleet`` section)."""
    import json

    import pandas as pd
    from pyproj import Transformer

    from skyroute.stages.intents import parse_intent

    out = Path(out_dir)
    (out / "intents").mkdir(parents=True, exist_ok=True)
    for old in (out / "intents").glob("*.json"):
        old.unlink()
    t0 = pd.Timestamp(sc.mission.start_time_utc)
    files: list[Path] = []
    rows = []
    for o in res.outcomes:
        a = o.attempt if o.status != "rejected" else None
        rows.append({"mission": o.task.id, "operator": o.task.operator, "priority": o.task.priority,
                     "status": o.status,
                     "departure_utc": (t0 + pd.Timedelta(seconds=a.departure_s)).isoformat() if a else "",
                     "earliest_s": round(o.task.earliest_s, 3), "delay_s": round(o.delay_s, 3) if a else "",
                     "dop_level": "" if o.level is None else o.level,
                     "energy_Wh": round(a.energy_Wh, 3) if a else "", "length_m": round(a.length_m, 2) if a else "",
                     "flight_time_s": round(a.flight_time_s, 2) if a else "", "compute_s": round(o.compute_s, 3),
                     "attempts": o.attempts, "volumes": len(a.volumes) if a else 0, "preempted_by": o.preempted_by,
                     "reason": o.reason})
    p = out / "fleet.csv"
    with open(p, "w", newline="") as f:
        w = csv.DictWriter(f, FLEET_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    files.append(p)
    acc = _accepted(res)
    docs = {}
    for o in acc:
        parse_intent(o.attempt.doc)          # F3548 schema and limits (uas-standards)
        docs[o.task.id] = o.attempt.doc
        q = out / "intents" / f"{o.task.id}.json"
        q.write_text(json.dumps(o.attempt.doc, indent=1))
        files.append(q)
    crs = maps["surface"]["surface"].rio.crs
    datum = str(maps["surface"]["surface"].attrs.get("vertical_datum", ""))
    to_ll = Transformer.from_crs(crs, 4326, always_xy=True)
    feats = []
    with open(out / "tracks.csv", "w") as f:
        f.write("mission,t_s,x_m,y_m,z_m\n")
        for o in acc:
            a = o.attempt
            np.savetxt(f, np.column_stack([a.t_s, a.xyz_m]), fmt=[o.task.id + ",%.3f", "%.3f", "%.3f", "%.3f"],
                       delimiter=",")
            k = np.unique(np.r_[np.arange(0, a.t_s.size, 20), a.t_s.size - 1])
            lon, lat = to_ll.transform(a.xyz_m[k, 0], a.xyz_m[k, 1])
            feats.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": [
                [round(float(x), 7), round(float(y), 7), round(float(z), 2)] for x, y, z in zip(lon, lat, a.xyz_m[k, 2],
                                                                                             strict=True)]},
                "properties": {"mission": o.task.id, "operator": o.task.operator, "status": o.status,
                               "priority": o.task.priority,
                               "departure_utc": (t0 + pd.Timedelta(seconds=a.departure_s)).isoformat(),
                               "delay_s": o.delay_s, "z_datum": datum}})
    files.append(out / "tracks.csv")
    gj = {"type": "FeatureCollection", "name": f"skyroute fleet {sc.name}",
          "description": f"accepted trajectories (lon, lat [deg] WGS 84; z [m] in the surface datum of the maps: "
                         f"{datum}; absolute heights are in intents/*.json, WGS 84 ellipsoidal)",
          "vertical_datum": datum, "features": feats}
    (out / "fleet.geojson").write_text(json.dumps(gj))
    files.append(out / "fleet.geojson")
    files.append(plot_fleet(res, sc, maps, out / "fleet.png"))
    conflicts = independent_conflicts(docs, crs, sc.mission.start_time_utc.isoformat())
    sep, pair = min_separation_m({o.task.id: (o.attempt.t_s, o.attempt.xyz_m) for o in acc})
    counts = res.counts()
    delays = [o.delay_s for o in acc]
    attempts = sum(o.attempts for o in res.outcomes)
    section = {"missions": len(res.outcomes), "counts": counts, "accepted_total": len(acc),
               "mean_delay_s": float(np.mean(delays)) if delays else None,
               "seconds": round(res.seconds, 3), "planning_attempts": attempts,
               "throughput_plans_per_min": round(attempts / res.seconds * 60.0, 2) if res.seconds > 0 else None,
               "missions_per_min": round(len(res.outcomes) / res.seconds * 60.0, 2) if res.seconds > 0 else None,
               "conflicts_independent_check": len(conflicts), "conflicting_pairs": [list(c) for c in conflicts],
               "min_separation_m": None if not math.isfinite(sep) else round(sep, 3),
               "min_separation_pair": list(pair) if pair else None,
               "required_separation_m": _required_separation_m(acc, sc), "preempted": sorted(o.task.id for o in res.outcomes if o.preempted_by),
               "speculative": res.speculative, "z_datum_geojson": datum,
               "notes": ["the scenario's own intruders are not fleet traffic: the traffic of each mission is the "
                         "accepted intents"]}
    return files, section


def _required_separation_m(acc: Sequence[MissionOutcome], sc: Scenario) -> float | None:
    """The separation the accepted tracks must keep [m]: the least r_p of their vehicles + d_c."""
    from skyroute.stages.vehicle import load_vehicle

    r = [load_vehicle(o.task.vehicle).r_p_m for o in acc]
    return round(min(r) + float(sc.traffic.margin_m), 3) if r else None


def plot_fleet(res: FleetResult, sc: Scenario, maps: dict, path: Path) -> Path:
    """Two panels: the accepted paths over the surface model, and the timeline of every
    accepted mission's intent volumes (one row per mission)."""
    import matplotlib

    matplotlib.use("Agg")
    import textwrap

    import matplotlib.pyplot as plt
    from matplotlib import patheffects

    acc = _accepted(res)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 6.2), gridspec_kw={"width_ratios": [1, 1.25]})
    s = maps["surface"]["surface"]
    x, y = np.asarray(s["x"].values), np.asarray(s["y"].values)
    step = max(1, int(max(x.size, y.size) / 800))
    im = ax.imshow(np.asarray(s[::step, ::step].values), extent=(x.min(), x.max(), y.min(), y.max()), origin="upper"
                   if y[0] > y[-1] else "lower", cmap="Greys", interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.7, label="surface [m]")
    cmap = plt.get_cmap("tab20")
    ids = [str(o.task.id) for o in acc]
    starts: dict[tuple[int, int], list[int]] = {}
    for i, o in enumerate(acc):   # each path numbered at its start as its row of the timeline
        p = o.attempt.xyz_m
        ax.plot(p[:, 0], p[:, 1], lw=0.9, color=cmap(i % 20))
        ax.plot(p[0, 0], p[0, 1], "o", ms=2.5, color=cmap(i % 20))
        starts.setdefault((int(round(p[0, 0] / 5.0)), int(round(p[0, 1] / 5.0))), []).append(i)
    for group in starts.values():   # missions from the same place: one label listing them all
        p = acc[group[0]].attempt.xyz_m
        text = "\n".join(textwrap.wrap(", ".join(str(i) for i in group), 24))
        ax.annotate(text, (p[0, 0], p[0, 1]), xytext=(3, 3), textcoords="offset points", fontsize=7,
                    color=cmap(group[0] % 20) if len(group) == 1 else "k", fontweight="bold",
                    path_effects=[patheffects.withStroke(linewidth=2, foreground="white")])
    ax.set_title(f"{sc.name}: {len(acc)} accepted paths\n(numbered at their start as the rows at right)", fontsize=10)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    colors = {"accepted": "tab:green", "delayed": "tab:orange", "preempted-replanned": "tab:purple"}
    for i, o in enumerate(acc):
        for v in o.attempt.volumes:
            bx.plot([v.t_start_s / 60.0, v.t_end_s / 60.0], [i, i], lw=2.5, color=colors.get(o.status, "k"),
                    solid_capstyle="butt")
    for k, c in colors.items():
        bx.plot([], [], color=c, lw=3, label=k)
    rej = sum(o.status == "rejected" for o in res.outcomes)
    bx.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title=f"rejected: {rej}", title_fontsize=8)
    bx.set_yticks(range(len(acc)))   # one integer row per mission (never 2.5, 7.5), labelled with its id
    bx.set_yticklabels([f"{i}: {m}" for i, m in enumerate(ids)], fontsize=7 if len(acc) <= 30 else 5)
    for i, lab in enumerate(bx.get_yticklabels()):
        lab.set_color(cmap(i % 20))
    if len(acc):
        bx.set_ylim(-0.6, len(acc) - 0.4)
    bx.set_xlabel("time after the scenario start [min]")
    bx.set_ylabel("accepted mission (order of acceptance: number, id)")
    bx.set_title("intent volumes' time windows")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

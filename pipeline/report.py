"""``report.html``: one self-contained HTML page of a run, plan, fly or navsim folder.

Everything comes from the files the folder already holds (``summary.json``, the CSV tables and
the PNG/GIF figures, embedded as base64 ``data:`` URIs), so building a report imports neither
matplotlib nor the stage code and a warm ``skyroute run`` rebuilds it in milliseconds.  The page
loads nothing: no external ``src``; its only links are to files of the folder (``plan.html``)
and, in the attribution text, to the data licences.  All text from the folder is escaped.

Sections (each only when the folder has what it needs): the scenario; the outcome (the chosen
plan's line, or why no plan flies); maps; the chosen path (top and vertical views, sigma_p);
the candidates' cost table (seed 000 Tables II-V layout: one row per coverage level D_j);
tactical events and levels (seed 001 Tables 3 and 5); the navigation Monte Carlo; stage timings
and cache hits; warnings; data attribution (``catalogs/data/ATTRIBUTION.md``).
"""

from __future__ import annotations

import base64
import csv
import json
import os
import re
from html import escape
from pathlib import Path
from string import Template
from typing import Any

from skyroute.pipeline.errors import InputError

__all__ = ["build_report", "report_html", "read_summary", "write_fly_map", "draw_missing_maps", "add_to_summary",
           "REPORT_NAME", "FIGURES"]

REPORT_NAME = "report.html"
ATTRIBUTION = Path(__file__).resolve().parents[1] / "catalogs" / "data" / "ATTRIBUTION.md"

# (section, glob relative to the plan / fly / navsim / top folder, caption); first match order
FIGURES: tuple[tuple[str, str, str], ...] = (
    ("maps", "figures/surface.png", "Surface model (buildings and terrain) with the start and goal"),
    ("maps", "figures/maps.png", "Ground risk levels, landing cost, wind over the buildings, no-fly cells, traffic"),
    ("maps", "maps.png", "Ground risk levels, landing cost, wind over the buildings, no-fly cells, traffic"),
    ("maps", "figures/coverage_*.png", "GNSS coverage floors per DOP threshold D_j (worst case over the window)"),
    ("maps", "coverage_*.png", "GNSS coverage floors per DOP threshold D_j (worst case over the window)"),
    ("plan", "top_view.png", "Chosen path, top view, over the ground risk cost and the admissible floor"),
    ("plan", "profile.png", "Chosen path, vertical view, over the surface and the admissible (coverage) floor"),
    ("plan", "sigma_p.png", "Predicted navigation error sigma_p along the candidates (the chosen one drawn thicker; "
                            "a red dashed line marks dp_max where the plan records it)"),
    ("plan", "bubble.png", "Safety bubble max(r_p, k sigma_p + surface uncertainty) along the chosen trajectory"),
    ("fly", "fly_top.png", "Flown trajectory, top view, with the intruders and no-fly zones (seed 001 Fig. 9)"),
    ("fly", "fly_profile.png", "Flown trajectory, vertical view"),
    ("fly", "fly_speed.png", "Ground speed along the flight"),
    ("fly", "fly_daa.png", "Detect-and-avoid alerts per known intruder (DO-365 levels scaled to the separation)"),
    ("navsim", "navsim_errors.png", "Navigation errors of the proposed and weak filters"),
    ("navsim", "navsim_bubble.png", "Safety bubble r = k sigma + surface uncertainty along the path"),
    ("navsim", "navsim_pl.png", "Protection levels (solution separation) along the path"),
    ("navsim", "navsim_sats.png", "Satellites in line of sight / received along the path"),
    ("navsim", "morphing_*.gif", "Digital morphing map: the coverage floor per epoch under the vehicle"),
    ("fleet", "fleet.png", "Fleet: the accepted trajectories over the map and the timeline of their reserved volumes"),
    ("compare", "compare.png", "Planners compared on the same maps: paths (top view) and vertical profiles"),
)

PAGE = Template("""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>$title</title>
<style>
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; } h2 { border-bottom: 1px solid #ccc; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0; font-size: 0.85em; }
.table-wrap { max-width: 100%; overflow-x: auto; margin: 0.6em 0; }
.table-wrap.long { max-height: 70vh; overflow-y: auto; } .table-wrap.long thead th { position: sticky; top: 0; }
th, td { border: 1px solid #bbb; padding: 3px 7px; text-align: right; vertical-align: top; white-space: nowrap; }
th { background: #eee; } td.text { text-align: left; }
td.wrap { text-align: left; white-space: normal; min-width: 22em; max-width: 48em; overflow-wrap: anywhere; }
tr.chosen td { background: #e3f4e1; font-weight: bold; }
figure { margin: 1em 0; } figure img { max-width: 100%; max-height: 85vh; border: 1px solid #ddd; }
figure.zoomable img { cursor: zoom-in; } figure.full { overflow: auto; max-height: 95vh; }
figure.full img { max-width: none; max-height: none; cursor: zoom-out; }
figcaption { font-size: 0.85em; color: #555; }
.outcome { padding: 0.6em 1em; border-radius: 4px; } .ok { background: #e3f4e1; } .bad { background: #fbe3e3; }
pre { white-space: pre-wrap; font-size: 0.8em; background: #f6f6f6; padding: 0.6em; }
</style>
</head>
<body data-images="$n_images">
<h1>$title</h1>
$body
<script>
// Sets body[data-images-loaded] = "n/m" once every image has decoded (read by the browser test).
// A figure shrunk to the page (e.g. maps.png) opens at full size on a click, and back on another.
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.body.setAttribute("data-images-loaded", ok + "/" + imgs.length);
  var zoomable = 0;
  imgs.forEach(function (img) {
    var fig = img.closest("figure");
    if (!fig || img.naturalWidth <= img.clientWidth + 1) { return; }
    zoomable += 1;
    fig.classList.add("zoomable");
    var hint = fig.querySelector(".zoom-hint");
    if (hint) { hint.textContent = " Shrunk to the page: click the image for full size (" + img.naturalWidth +
                " x " + img.naturalHeight + " px)."; }
    img.addEventListener("click", function () { fig.classList.toggle("full"); });
  });
  document.body.setAttribute("data-images-zoomable", zoomable);
});
</script>
</body>
</html>
""")


# ------------------------------------------------------------------ small HTML helpers


def _table(header: list[str], rows: list[list[Any]], chosen: list[bool] | None = None,
           text_cols: tuple[int, ...] = (), cls: str = "", wrap_cols: tuple[int, ...] | None = None) -> str:
    """An HTML table in a scrolling box (a wide table scrolls sideways inside the page, a long
    one, over 25 rows, down, its header kept); cells are escaped; ``chosen`` marks rows (class
    ``chosen``); ``text_cols`` are left-aligned text; ``wrap_cols`` (default: the text columns
    whose longest cell has more than 40 characters, e.g. reasons) wrap in a column at least
    22 em wide instead of becoming a narrow, very tall one."""
    if wrap_cols is None:
        wrap_cols = tuple(j for j in text_cols if any(len(str(r[j])) > 40 for r in rows if j < len(r)))
    head = "".join(f"<th>{escape(str(h))}</th>" for h in header)
    head = f"<thead><tr>{head}</tr></thead>" if any(str(h) for h in header) else ""
    body = []
    for i, row in enumerate(rows):
        tr = ' class="chosen"' if chosen and chosen[i] else ""
        cells = "".join(('<td class="wrap">' if j in wrap_cols else '<td class="text">' if j in text_cols else "<td>")
                        + escape("" if v is None else str(v)) + "</td>" for j, v in enumerate(row))
        body.append(f"<tr{tr}>{cells}</tr>")
    box = "table-wrap long" if len(rows) > 25 else "table-wrap"
    return f'<div class="{box}"><table class="{cls}">{head}<tbody>{"".join(body)}</tbody></table></div>'


PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
GIF_MAGIC = (b"GIF87a", b"GIF89a")


def _embeddable(root: Path, path: Path) -> bool:
    """A figure the page may embed: a regular file inside ``root`` reached through no symbolic
    link, that is a PNG (or, named .gif, a GIF) by its first bytes: a ``figures/x.png`` link to
    another file never puts that file into the page."""
    from skyroute.pipeline.outfolder import safe_member

    magic = GIF_MAGIC if path.suffix.lower() == ".gif" else (PNG_MAGIC,)
    return safe_member(root, path, magic)


def _figure(path: Path, caption: str) -> str:
    mime = "image/gif" if path.suffix.lower() == ".gif" else "image/png"
    data = base64.b64encode(path.read_bytes()).decode()
    return (f'<figure><img src="data:{mime};base64,{data}" alt="{escape(path.name)}">'
            f'<figcaption>{escape(caption)} ({escape(path.name)}).<span class="zoom-hint"></span></figcaption>'
            "</figure>")


def _num(v: Any, fmt: str = ".1f") -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)):
        return format(v, fmt)
    return str(v)


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """The header and rows of a CSV of the folder (a symbolic link or a non-regular file reads
    as an empty table: the page shows only what the folder's command wrote)."""
    from skyroute.pipeline.outfolder import safe_member

    if not safe_member(path.parent, path):
        return [], []
    with open(path, newline="") as fh:
        r = csv.DictReader(fh)
        return list(r.fieldnames or []), list(r)


def _markdown(text: str) -> str:
    """The few markdown forms of ATTRIBUTION.md: headings, pipe tables, paragraphs (escaped)."""
    out, table = [], []

    def flush() -> None:
        if table:
            rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in table]
            rows = [r for r in rows if not all(re.fullmatch(r":?-+:?", c) for c in r)]
            out.append(_table(rows[0], rows[1:], text_cols=tuple(range(len(rows[0])))))
            table.clear()

    for line in text.splitlines():
        if line.lstrip().startswith("|"):
            table.append(line)
            continue
        flush()
        if line.startswith("#"):
            level = min(len(line) - len(line.lstrip("#")) + 2, 6)
            out.append(f"<h{level}>{escape(line.lstrip('#').strip())}</h{level}>")
        elif line.strip():
            out.append(f"<p>{escape(line.strip())}</p>")
    flush()
    return "\n".join(out)


# ------------------------------------------------------------------ sections


def _folders(run_dir: Path, command: str) -> dict[str, Path | None]:
    """Where the plan / fly / navsim files of a folder written by ``command`` are."""
    top = run_dir
    return {
        "maps": top,
        "plan": top / "plan" if command == "run" else top if command == "plan" else None,
        "fly": top / "fly" if command == "run" else top if command == "fly" else None,
        "navsim": top if command == "navsim" else None,
        "fleet": top if command == "fleet" else None,
        "compare": top if command == "compare" else None,
    }


def _inside(run_dir: Path, folder: Path) -> bool:
    """``folder`` is ``run_dir`` or a real sub-folder of it (not a symbolic link out of it)."""
    import os

    from skyroute.pipeline.outfolder import no_link_between

    top = os.path.realpath(run_dir)
    return folder == run_dir or (no_link_between(top, os.path.join(top, os.path.relpath(folder, run_dir), "x"))
                                 and not os.path.islink(folder))


def _figures(folders: dict[str, Path | None], section: str) -> list[str]:
    base = folders.get(section)
    if base is None or not base.is_dir():
        return []
    out, seen = [], set()
    for sec, pattern, caption in FIGURES:
        if sec != section:
            continue
        for p in sorted(base.glob(pattern)):
            if p not in seen and _embeddable(base, p):
                seen.add(p)
                out.append(_figure(p, caption))
    return out


def _scenario_section(doc: dict[str, Any]) -> str:
    rows = [["scenario", doc.get("scenario", "")], ["command", doc.get("command", "")]]
    if doc.get("description"):
        rows.append(["description", " ".join(str(doc["description"]).split())])
    if doc.get("crs"):
        rows.append(["CRS", doc["crs"]])
    g = doc.get("grid")
    if g and all(k in g for k in ("nx", "ny", "resolution_m", "bounds")):
        rows.append(["grid", f"{g['nx']} x {g['ny']} cells @ {g['resolution_m']:g} m; bounds "
                     f"{', '.join(f'{b:.0f}' for b in g['bounds'])} [m]"])
    return "<h2>Scenario</h2>" + _table(["", ""], rows, text_cols=(0, 1))


def _outcome_section(doc: dict[str, Any]) -> str:
    parts = []
    plan = doc.get("plan")
    if plan is not None:
        if plan.get("status") == "flyable":
            dop = "no GNSS level" if plan.get("dop_threshold") is None else f"DOP < {plan['dop_threshold']:g}"
            line = (f"Chosen plan {plan.get('label')}: f = {_num(plan.get('f_m'), '.1f') or 'n/a'} m, length "
                    f"{_num(plan.get('length_m'), '.1f') or 'n/a'} m, energy {_num(plan.get('energy_Wh'), '.2f') or 'n/a'}"
                    f" Wh, flight time {_num(plan.get('flight_time_s'), '.1f') or 'n/a'} s, {dop}.")
            parts.append(f'<p class="outcome ok">{escape(line)}</p>')
        else:
            reasons = plan.get("reasons") or ["no candidate was produced"]
            items = "".join(f"<li>{escape(str(r))}</li>" for r in reasons)
            parts.append('<div class="outcome bad" id="no-flyable-plan"><p><b>No flyable plan.</b> '
                         f"Why, per coverage level:</p><ul>{items}</ul></div>")
        prov = plan.get("provenance")
        if isinstance(prov, dict):
            budgets = ", ".join(f"{k} {v:g}" if isinstance(v, (int, float)) else f"{k} {v}"
                                for k, v in (prov.get("budgets") or {}).items())
            line = (f"Made by planner {prov.get('planner')} (seed {prov.get('seed')}, weights w_l, w_r, w_d, w_e = "
                    f"{', '.join(f'{float(w):g}' for w in prov.get('weights', []))}, budget "
                    f"{prov.get('time_budget_s')} s; counted budgets: {budgets or '-'}) for vehicle "
                    f"{prov.get('vehicle')}, skyroute {prov.get('skyroute_version')}.")
            parts.append(f'<p class="provenance" id="plan-provenance">{escape(line)}</p>')
    fly = doc.get("fly")
    if fly is not None:
        line = (f"Flight replay: outcome {fly.get('outcome')}"
                f"{' (' + str(fly['reason']) + ')' if fly.get('reason') else ''}; "
                f"{fly.get('n_replannings', 0)} replannings, chosen levels {', '.join(fly.get('chosen_levels', [])) or '-'}.")
        parts.append(f'<p class="outcome {"ok" if fly.get("outcome") != "failed" else "bad"}">{escape(line)}</p>')
    return ("<h2>Outcome</h2>" + "".join(parts)) if parts else ""


CANDIDATE_HEADER = (("label", "D_j"), ("C_l_m", "C_l [m]"), ("C_r_m", "C_r [m]"), ("C_d_m", "C_d [m]"),
                    ("C_e_m", "C_e [m]"), ("f_m", "f [m]"), ("max_sigma_p_m", "max sigma_p [m]"),
                    ("clearance_radius_m", "r_j [m]"), ("energy_Wh", "energy [Wh]"),
                    ("flight_time_s", "flight time [s]"), ("compute_time_s", "compute [s]"),
                    ("flyable", "flyable"), ("chosen", "chosen"), ("reasons", "reasons"))


def _is_number(v: str) -> bool:
    """A CSV cell that reads as a number (or is empty)."""
    try:
        float(v or 0)
        return True
    except ValueError:
        return False


def _csv_section(folder: Path | None, name: str, title: str, intro: str, max_rows: int = 200) -> str:
    """A CSV table of ``folder/name`` (at most ``max_rows`` rows, the count stated)."""
    if folder is None or not (folder / name).is_file():
        return ""
    fields, rows = _read_csv(folder / name)
    more = f" The first {max_rows} of {len(rows)} rows." if len(rows) > max_rows else ""
    shown = [[r.get(k) or "" for k in fields] for r in rows[:max_rows]]
    text = tuple(j for j in range(len(fields)) if any(not _is_number(row[j]) for row in shown))   # reasons, ids
    table = _table(fields, shown, text_cols=text)
    return f"<h2>{escape(title)}</h2><p>{escape(intro)} From {escape(name)}.{more}</p>" + table


def _fleet_section(folder: Path | None, sec: dict[str, Any] | None) -> str:
    """Counts of a ``skyroute fleet`` folder and its fleet.csv."""
    if folder is None or sec is None:
        return ""
    counts = sec.get("counts") or {}
    rows = [[k, v] for k, v in counts.items()]
    for k in ("mean_delay_s", "throughput_plans_per_min", "conflicts_independent_check"):
        if k in sec:
            rows.append([k, sec[k]])
    head = "<h2>Fleet (U-space, first come first served)</h2>" + _table(["", ""], rows, text_cols=(0,))
    return head + _csv_section(folder, "fleet.csv", "Missions", "One row per mission: its status (accepted, delayed, "
                               "preempted and re-planned, rejected and why), delay, energy, length and compute time.")


def _candidates_section(plan_dir: Path | None) -> str:
    if plan_dir is None or not (plan_dir / "candidates.csv").is_file():
        return ""
    fields, rows = _read_csv(plan_dir / "candidates.csv")
    cols = [(k, h) for k, h in CANDIDATE_HEADER if k in fields]
    table = _table([h for _, h in cols], [[r[k] for k, _ in cols] for r in rows],
                   chosen=[r.get("chosen") == "true" for r in rows], text_cols=(len(cols) - 1,), cls="candidates")
    return ("<h2>Candidates (seed 000 Tables II-V layout)</h2><p>One candidate per GNSS coverage level D_j; "
            "f = w_l C_l + w_r C_r + w_d C_d + w_e C_e (eq. 11); the chosen one (highlighted) is the flyable "
            f"candidate with minimum f. From {escape((plan_dir / 'candidates.csv').name)}.</p>" + table)


LEVELS = ("1", "2", "3", "landing", "escape")


def _tactical_section(fly_dir: Path | None, fly: dict[str, Any] | None) -> str:
    if fly_dir is None or not (fly_dir / "tactical.csv").is_file():
        return ""
    out = ["<h2>Tactical events (seed 001 Tables 3 and 5)</h2>"]
    if fly and fly.get("events"):
        rows = [[_num(e.get("t_s")), e.get("kind"), e.get("label"), _num(e.get("t_known_s")), _num(e.get("t_coll_s")),
                 e.get("outcome")] for e in fly["events"]]
        out.append("<h3>Events</h3>" + _table(["t [s]", "kind", "event", "known at [s]", "t_coll [s]", "outcome"],
                                              rows, text_cols=(1, 2, 5)))
    _, rows = _read_csv(fly_dir / "tactical.csv")
    by: dict[str, dict[str, dict[str, str]]] = {}
    for r in rows:
        by.setdefault(r["replanning"], {})[r["level"]] = r
    t3, t5 = [], []
    for rep, levels in by.items():
        first = next(iter(levels.values()))
        chosen = next((lv for lv, r in levels.items() if r["chosen"] == "true"), "")
        head = [rep, first["event"], first["t_event_s"], first["t_coll_s"]]
        t3.append(head + [first.get("alert", "")] + [("f " + levels[lv]["f_m"] if levels[lv]["flyable"] == "true"
                                                       else "not flyable") if lv in levels else "-" for lv in LEVELS]
                  + [chosen])
        t5.append(head[:2] + [levels[lv]["compute_s"] if lv in levels else "-" for lv in LEVELS]
                  + [first["update_s"], levels[chosen]["added_flight_time_s"] if chosen else ""])
    out.append("<h3>Replanning levels (Table 3 layout)</h3><p>Per replanning, each level's cost f = w_l C_l + "
               "w_e C_e [m] when flyable; the chosen level has the minimum f.</p>"
               + _table(["replanning", "event", "t_event [s]", "t_coll [s]", "DAA alert", "level 1", "level 2",
                         "level 3", "landing", "escape", "chosen"], t3, text_cols=(1, 4), cls="tactical"))
    out.append("<h3>Computation times (Table 5 layout)</h3>"
               + _table(["replanning", "event", "level 1 [s]", "level 2 [s]", "level 3 [s]", "landing [s]",
                         "escape [s]", "update [s]", "added flight time [s]"], t5, text_cols=(1,)))
    reasons = [[r["replanning"], r["level"], r["reasons"]] for r in rows if r["reasons"]]
    if reasons:
        out.append("<details><summary>Why each level was (not) chosen</summary>"
                   + _table(["replanning", "level", "reason"], reasons, text_cols=(2,)) + "</details>")
    if fly and fly.get("min_separation"):
        rows = [[s.get("id"), s.get("kind"), _num(s.get("min_distance_m")), _num(s.get("required_m")),
                 _num(s.get("clearance_m")), _num(s.get("t_s"))] for s in fly["min_separation"]]
        out.append("<h3>Minimum separation to each intruder (brute force on the flown trajectory)</h3>"
                   + _table(["intruder", "kind", "min distance [m]", "required [m]", "margin [m]", "at t [s]"], rows,
                            text_cols=(0, 1)))
    if fly and fly.get("unavoidable_losses"):
        rows = [[u.get("intruder", ""), _num(u.get("t_s")), _num(u.get("predicted_margin_m",
                                                                        u.get("predicted_min_m"))), u.get("why", "")]
                for u in fly["unavoidable_losses"]]
        out.append("<h3>Losses of separation the flight had to accept</h3>"
                   + _table(["intruder", "decided at [s]", "predicted margin [m]", "why"], rows, text_cols=(0, 3)))
    return "".join(out)


def _navsim_section(nav: dict[str, Any] | None) -> str:
    if not nav:
        return ""
    c = nav.get("containment", {})
    rows = [[f, _num(c[f].get("1sigma"), ".3f"), _num(c[f].get("2sigma"), ".3f"), _num(c[f].get("3sigma"), ".3f"),
             _num(nav.get(f, {}).get("rms_error_m"), ".2f"), _num(nav.get(f, {}).get("p95_error_m"), ".2f"),
             _num(nav.get(f, {}).get("bubble_3sigma_median_m"), ".2f"),
             _num(nav.get(f, {}).get("bubble_3sigma_max_m"), ".2f")] for f in c]
    out = [f"<h2>Navigation Monte Carlo</h2><p>{nav.get('runs')} runs x {nav.get('epochs')} epochs; surface "
           f"uncertainty {_num(nav.get('surface_uncertainty_m'), 'g')} m.</p>",
           _table(["filter", "1-sigma", "2-sigma", "3-sigma", "RMS error [m]", "p95 error [m]",
                   "3-sigma bubble median [m]", "3-sigma bubble max [m]"], rows, text_cols=(0,))]
    pl = nav.get("protection_level")
    if pl:
        out.append(_table(["protection level", "median HPL [m]", "median VPL [m]", "availability", "containment h",
                           "containment v"],
                          [[pl.get("method"), _num(pl.get("hpl_median_m")), _num(pl.get("vpl_median_m")),
                            _num(pl.get("availability"), ".3f"), _num(pl.get("containment_h"), ".3f"),
                            _num(pl.get("containment_v"), ".3f")]], text_cols=(0,)))
    return "".join(out)


def _timings_section(doc: dict[str, Any]) -> str:
    stages = doc.get("stages") or []
    if not stages:
        return ""
    rows = [[s["name"], "cache" if s.get("cache_hit") else "computed", _num(s.get("seconds"), ".2f"), s.get("key", "")]
            for s in stages]
    hits = sum(bool(s.get("cache_hit")) for s in stages)
    total = doc.get("seconds")
    return ("<h2>Timings and cache</h2>"
            f"<p>{len(stages)} stages, {hits} from the cache; {_num(total, '.2f')} s in all.</p>"
            + _table(["stage", "source", "seconds", "cache key"], rows, text_cols=(0, 1, 3), cls="timings"))


def _map_links(page_dir: Path, folders: dict[str, Path | None]) -> str:
    links = []
    for sec, name in (("plan", "plan.html"), ("fly", "fly.html")):
        base = folders.get(sec)
        if base is not None and (base / name).is_file():
            rel = Path(os.path.relpath((base / name).resolve(), page_dir.resolve())).as_posix()
            links.append(f'<li><a href="{escape(rel)}">{escape(rel)}</a></li>')
    return ("<p>Interactive map (Leaflet; layers toggle; the basemap needs the network):</p><ul>"
            + "".join(links) + "</ul>") if links else ""


# ------------------------------------------------------------------ the page


def read_summary(run_dir: Path) -> dict[str, Any]:
    """``run_dir/summary.json``; InputError naming the folder when it is missing or unreadable."""
    from skyroute.pipeline.outputs import check_summary_files, unfinished_rewrite

    if unfinished_rewrite(Path(run_dir)):
        raise InputError(f"{run_dir} was being rewritten by a command that did not finish (interrupted or failed): "
                         "its files may mix two runs; run that command again")
    try:
        doc = json.loads((Path(run_dir) / "summary.json").read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{run_dir} has no readable summary.json ({exc}): give a folder written by skyroute run, "
                         "plan, fly or navsim") from None
    if not isinstance(doc, dict):
        raise InputError(f"{run_dir}/summary.json is not a skyroute summary (not a JSON object)")
    from skyroute.pipeline.summary_schema import check_summary

    check_summary(doc, run_dir, "run folder")   # every value the page reads has its type (a hand-edited summary)
    check_summary_files(Path(run_dir), doc, "run folder")
    return doc


def report_html(run_dir: Path, page_dir: Path | None = None, maps_dir: Path | None = None) -> str:
    """The report page of the folder ``run_dir`` (written by ``skyroute run``, ``plan``, ``fly``,
    ``navsim``, ``fleet``, ``compare``, ``maps`` or ``coverage``: the kind is ``summary.json``'s ``command``);
    ``page_dir``: where the page will be (its links to the map pages are relative to it;
    default ``run_dir``); ``maps_dir``: where the scenario maps' ``figures/`` are when the folder
    has none of its own (:func:`draw_missing_maps` into a temporary folder)."""
    run_dir = Path(run_dir)
    page_dir = run_dir if page_dir is None else Path(page_dir)
    doc = read_summary(run_dir)
    command = str(doc.get("command", ""))
    folders = {k: v if v is None or _inside(run_dir, v) else None for k, v in _folders(run_dir, command).items()}
    if maps_dir is not None:
        folders["maps"] = Path(maps_dir)
    if command == "run" and (run_dir / "fly" / "summary.json").is_file():
        from skyroute.pipeline.summary_schema import check_summary

        try:
            fly_doc = json.loads((run_dir / "fly" / "summary.json").read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"run folder {run_dir / 'fly'}: summary.json is not readable JSON ({exc}); run the "
                             "command that wrote it again") from None
        check_summary(fly_doc, run_dir / "fly", "run folder")
    else:
        fly_doc = doc
    body = [_scenario_section(doc), _outcome_section(doc)]
    maps = _figures(folders, "maps")
    if maps:
        body.append("<h2>Maps</h2>" + "".join(maps))
    plan_figs = _figures(folders, "plan")
    links = _map_links(page_dir, folders)
    if plan_figs or links:
        body.append("<h2>Chosen path</h2>" + links + "".join(plan_figs))
    body.append(_candidates_section(folders["plan"]))
    body.append(_tactical_section(folders["fly"], fly_doc.get("fly")))
    fly_figs = _figures(folders, "fly")
    if fly_figs:
        body.append("<h3>Flight figures</h3>" + "".join(fly_figs))
    body.append(_navsim_section(doc.get("navsim")))
    nav_figs = _figures(folders, "navsim")
    body.extend(nav_figs)
    body.append(_fleet_section(folders["fleet"], doc.get("fleet")))
    body.append(_csv_section(folders["compare"], "compare.csv", "Planners compared",
                             "One row per planner on the same maps: f and its terms, length, energy, exact "
                             "clearance from the surface, max sigma_p, compute time, flyable or why not."))
    other_figs = _figures(folders, "fleet") + _figures(folders, "compare")
    body.extend(other_figs)
    n_img = len(maps) + len(plan_figs) + len(fly_figs) + len(nav_figs) + len(other_figs)
    body.append(_timings_section(doc))
    warnings = list(doc.get("warnings") or [])
    if warnings:
        body.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{escape(str(w))}</li>" for w in warnings) + "</ul>")
    if ATTRIBUTION.is_file():
        body.append("<h2>Data attribution</h2>" + _markdown(ATTRIBUTION.read_text()))
    title = f"skyroute {command} report: {doc.get('scenario', run_dir.name)}"
    return PAGE.substitute(title=escape(title), body="\n".join(b for b in body if b), n_images=n_img)


def build_report(run_dir: Path, out: Path | None = None, maps_dir: Path | None = None) -> Path:
    """Write :func:`report_html` of ``run_dir`` to ``out`` (default ``run_dir/report.html``)
    atomically; return the path."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / REPORT_NAME
    html = report_html(run_dir, out.parent, maps_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(html, encoding="utf-8")
    tmp.replace(out)
    return out


def write_fly_map(fly_dir: Path, result=None) -> Path | None:
    """``fly_dir/fly.html``: the interactive map of a flight replay folder, from its
    flown.geojson and intruders.geojson (and a plan.geojson beside them, if any), with the
    buildings, coverage floors, start and goal of ``result`` (the flight's
    :class:`~skyroute.pipeline.graph.RunResult`, when given); None (nothing written) when the
    folder has no flown.geojson."""
    from skyroute.pipeline.planmap import fly_map_html, fly_map_layers

    fly_dir = Path(fly_dir)
    flown = fly_dir / "flown.geojson"
    if not flown.is_file():
        return None
    intr = fly_dir / "intruders.geojson"
    plan = fly_dir / "plan.geojson"
    title = f"skyroute flight map: {fly_dir.resolve().name}"
    html = fly_map_html(title, json.loads(flown.read_text()), json.loads(intr.read_text()) if intr.is_file() else None,
                        json.loads(plan.read_text()) if plan.is_file() else None,
                        fly_map_layers(result) if result is not None and "surface" in result.datasets else None)
    out = fly_dir / "fly.html"
    out.write_text(html, encoding="utf-8")
    return out


def add_to_summary(run_dir: Path, paths: list[Path]) -> None:
    """List ``paths`` (those inside ``run_dir``) in ``run_dir/summary.json``'s ``files``."""
    run_dir = Path(run_dir).resolve()
    rel = []
    for p in paths:
        try:
            rel.append(Path(p).resolve().relative_to(run_dir).as_posix())
        except ValueError:
            continue
    doc = json.loads((run_dir / "summary.json").read_text())
    if all(f in doc.get("files", []) for f in rel):
        return
    doc["files"] = sorted(set(doc.get("files", [])) | set(rel))
    tmp = run_dir / ".summary.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))
    tmp.replace(run_dir / "summary.json")


DRAWN_STAGES = ("surface", "environment", "wind", "clearance", "traffic", "coverage")   # the maps a report draws


def draw_missing_maps(run_dir: Path, cache, into: Path | None = None) -> list[Path]:
    """Draw the scenario maps (``figures/surface.png``, ``figures/maps.png``,
    ``figures/coverage_<KIND>.png``) of a ``plan``, ``fly`` or ``navsim`` folder that has no
    ``figures/*.png`` yet, from its scenario's map stages (``cache``: a
    :class:`~skyroute.pipeline.cache.Cache`; stages missing from it are computed), into
    ``into/figures/`` (default: the folder itself; ``skyroute report`` draws them into a
    temporary folder and only embeds them, so the folder is left as it was).  The scenario
    is the summary's ``scenario_path`` (else its catalog name); nothing is drawn (empty list)
    when it cannot be loaded or is no longer the folder's scenario."""
    from skyroute.pipeline.errors import SkyrouteError

    run_dir = Path(run_dir)
    doc = read_summary(run_dir)
    if doc.get("command") not in ("plan", "fly", "navsim") or any((run_dir / "figures").glob("*.png")):
        return []
    from skyroute.pipeline.graph import stages_for
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import load_scenario

    try:
        sc = load_scenario(doc.get("scenario_path") or doc.get("scenario", ""))
    except SkyrouteError:
        return []
    if sc.name != doc.get("scenario"):
        return []
    targets = [s.name for s in stages_for(sc) if s.name in DRAWN_STAGES]
    result = run_scenario(sc, cache=cache, targets=targets, progress=False)
    from skyroute.pipeline.graph import stage_attrs
    from skyroute.pipeline.outputs import map_figure

    def surface(p):
        from skyroute.pipeline.outputs import plot_surface

        plot_surface(result, p)

    def maps(p):
        from skyroute.pipeline.maps import plot_maps_panel

        plot_maps_panel(result, p)

    def coverage(p):
        from skyroute.pipeline.cli_coverage import plot_coverage

        plot_coverage(result["coverage"], p)

    # the same figures, under the same keys, as a run folder's (drawn once: the output memo)
    fig_dir = (run_dir if into is None else Path(into)) / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    out = [map_figure(result, fig_dir / "surface.png", "figures/surface.png", ("surface",), surface)]
    if "environment" in result.datasets:
        drawn = tuple(s for s in ("surface", "environment", "wind", "clearance", "traffic")
                      if s in {r.name for r in result.records})
        out.append(map_figure(result, fig_dir / "maps.png", "figures/maps.png", drawn, maps))
    if "coverage" in result.datasets:
        kind = str(stage_attrs(result, "coverage").get("dop_kind", "DOP"))
        rel = f"figures/coverage_{kind}.png"
        out.append(map_figure(result, fig_dir / f"coverage_{kind}.png", rel, ("coverage",), coverage))
    return out

"""``skyroute compare``: STEP I planners side by side on the same maps
(:mod:`skyroute.pipeline.compare`)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from skyroute.pipeline.cli import SCHEDULER_HELP, OutPath, max_memory_option
from skyroute.pipeline.outfolder import shown
from skyroute.stages.planning.registry import planner_help

if TYPE_CHECKING:
    from skyroute.pipeline.compare import CompareRow


@click.command("compare")
@click.argument("scenario", required=False, default=None)
@click.option("--planners", default=None,
              help=f"Comma-separated planner names ({planner_help()}; default: every planner that fits the vehicle).")
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/compare).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("-q", "--quiet", is_flag=True, help="No progress lines.")
@max_memory_option
def compare_command(scenario, planners, out_dir, cache_dir, scheduler, quiet) -> None:
    """Plan SCENARIO with each planner on the same (cached) maps: compare.csv (f and its
    terms, length, energy, minimum and mean exact clearance from the surface, max sigma_p,
    compute time, flyable, or why not) and compare.png (every path, top view and profiles).
    Planners that do not apply to the scenario are listed with the reason."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.compare import compare_planners, json_safe, write_compare
    from skyroute.pipeline.outputs import ensure_writable_dir, write_folder_summary
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, PLANNERS, load_scenario
    from skyroute.stages.planning.kinds import planners_for

    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    names = ([p.strip() for p in planners.split(",") if p.strip()] if planners
             else planners_for(sc.vehicle, PLANNERS))   # default: every planner that fits the vehicle
    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "compare")
    echo = None if quiet or not sys.stderr.isatty() else (lambda m: click.echo(m, err=True))
    rows, maps = compare_planners(sc, names, cache=Cache(cache_dir), scheduler=scheduler, echo=echo)
    files = write_compare(rows, maps, out_dir, title=f"{sc.name}: planners compared")
    section = {"planners": [json_safe(r.values) for r in rows]}
    write_folder_summary(out_dir, "compare", maps, [str(p) for p in files.values()], {"compare": section})
    for r in rows:
        click.echo(row_line(r))
    click.echo(f"compare: {len(rows)} planners -> {shown(out_dir)}")
    if not any(r.flyable for r in rows):
        click.echo("no flyable plan: no planner found one (compare.csv lists why)", err=True)
        raise SystemExit(3)


def row_line(r: CompareRow) -> str:
    """The console line of a :class:`~skyroute.pipeline.compare.CompareRow`: ``compute`` is the
    time [s] the plan took when it was computed, followed by ``(cached)`` when this command read
    it from the stage cache (``plan_cached`` in compare.csv) instead of computing it."""
    v = r.values
    if r.xyz_m is None:
        return f"{r.planner:>10}: {v.get('reason', 'no plan')}"
    return (f"{r.planner:>10}: f {v['f_m']:.1f} m, length {v['length_m']:.1f} m, energy "
            f"{v['energy_Wh']:.2f} Wh, min clearance {v['min_clearance_m']:.2f} m, "
            f"compute {v['compute_s']:.2f} s{' (cached)' if v.get('plan_cached') else ''}")

"""``skyroute fly``: fly a scenario's strategic plan through its events (tactical replay)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from skyroute.pipeline.cli import (
    QUIET_HELP,
    SCHEDULER_HELP,
    SEED,
    FiniteFloat,
    OutPath,
    max_memory_option,
    show_progress,
)
from skyroute.pipeline.fly_outputs import fly_folder, write_fly_folder  # noqa: F401  (write_fly_folder: its old home)


@click.command("fly")
@click.argument("scenario", required=False, default=None)
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/fly).")
@click.option("--events", "events_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A YAML file of events (a top-level `events:` list) added to the scenario's.")
@click.option("--t-rep", "t_rep_s", type=FiniteFloat(), default=None,
              help="Replanning timeout t_rep [s] (default: tactical.t_rep_s, 5 s).")
@click.option("--tick", "tick_s", type=FiniteFloat(), default=None, help="Simulation and output step [s] (default 0.1 s).")
@click.option("--seed", type=SEED, default=None, help="Seed of the RRTs and the intruder report noise.")
@click.option("--tactical", "method", type=click.Choice(["levels", "octant", "local"]), default=None,
              help="How conflicts are resolved: levels 1-3 (seed 001) or the octant manoeuvre with dense-traffic "
                   "zones (seed 004) for rotorcraft; local (seed 002: climb over obstacles, turn right for UAVs) "
                   "for fixed-wing (default: tactical.method; levels, or local for a fixed-wing vehicle).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("-q", "--quiet", is_flag=True, help=QUIET_HELP)
@max_memory_option
def fly_command(scenario, out_dir, events_file, t_rep_s, tick_s, seed, method, cache_dir, scheduler, quiet) -> None:
    """Fly the strategic plan of SCENARIO (default helsinki-tactical) in simulated time through
    its events (seed 001 section 3.2): at each event the rest of the plan is checked; when it
    is compromised, levels 1-3 replan (with --tactical octant an intruder conflict is resolved
    by the seed 004 octant manoeuvre instead), or the vehicle lands at the nearest reachable
    landing site. Writes tactical.csv, flown.geojson, flown.csv, intruders.geojson, figures and
    summary.json. Exit code 3 when the flight ends neither at the goal nor on a landing site."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.fly import fly_params
    from skyroute.pipeline.outputs import ensure_writable_dir
    from skyroute.pipeline.settings import load_scenario, with_events

    sc = load_scenario(scenario or "helsinki-tactical")
    if events_file is not None:
        sc = with_events(sc, events_file)
    if not sc.events:
        raise InputError(f"scenario {sc.name!r} has no events to fly through: add an `events:` list to it or "
                         "give --events FILE")
    from skyroute.pipeline.fly import check_intruders, tactical_method

    check_intruders(sc)      # more intruder tracks than one replay takes: exit 2 before any work
    if tactical_method(sc, method) != "local":
        fly_params(sc, t_rep_s, tick_s, seed, method)  # bad --t-rep / --tick: exit 2 before any work
    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "fly")
    section = fly_folder(sc, out_dir, cache=Cache(cache_dir), scheduler=scheduler,
                         progress=show_progress(quiet), t_rep_s=t_rep_s, tick_s=tick_s, seed=seed,
                         method=method)
    from skyroute.stages.tactical.log import fly_summary_line

    click.echo(fly_summary_line(section))
    if section["outcome"] == "failed" or section.get("separation_lost"):
        if section.get("separation_lost"):
            lost = [r for r in section["min_separation"] if r["clearance_m"] is not None and r["clearance_m"] < 0]
            why = "; ".join(u["why"] for u in section.get("unavoidable_losses", [])) or "no escape kept it"
            click.echo(f"loss of separation: {', '.join(r['id'] for r in lost)} (closest "
                       f"{min(r['min_distance_m'] for r in lost):.1f} m): {why}", err=True)
        sys.exit(3)

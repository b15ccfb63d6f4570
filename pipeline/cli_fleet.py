"""``skyroute fleet``: first-come-first-served strategic deconfliction of many missions."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from pathlib import Path

import click

from skyroute.pipeline.cli import SCHEDULER_HELP, SEED, FiniteFloat, OutPath, max_memory_option
from skyroute.pipeline.outfolder import folder_of, shown
from skyroute.stages.base import note_input

MAX_ATTEMPTS = 1000   # departures tried per mission (--max-delay-min / --delay-step-s + 1), each one plan


def default_window_min(gnss_window_min: float, max_delay_min: float) -> float:
    """Default ``--window-min`` [min]: the departures window the GNSS maps cover,
    ``gnss.window_min`` minus the longest delay (the latest delayed departure still lies in the
    maps); the GNSS window itself when the delay alone is as long, 1 min for a one-epoch map."""
    w = gnss_window_min - max_delay_min
    return w if w > 0 else gnss_window_min if gnss_window_min > 0 else 1.0


@click.command("fleet")
@click.argument("scenario", required=False, default=None)
@click.option("--fleet", "fleet_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Fleet file (YAML 'missions: [...]' or CSV): id, operator, start, goal, departure, priority, "
                   "vehicle, dop_level.")
@click.option("--missions", type=click.IntRange(min=1), default=None,
              help="Draw N missions between the scenario's landing sites instead of --fleet.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the draw and of STEP II.")
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/fleet).")
@click.option("--window-min", type=FiniteFloat(min=0.0, min_open=True), default=None,
              help="Departures of drawn missions uniform over this window [min] (default: what the scenario's GNSS "
                   "maps cover, gnss.window_min minus --max-delay-min, so that a delayed departure still lies in the "
                   "maps; a longer window warns that later missions use the last GNSS epoch).")
@click.option("--min-km", type=FiniteFloat(min=0.0), default=0.2, show_default=True,
              help="Shortest drawn mission (start-goal distance) [km].")
@click.option("--max-km", type=FiniteFloat(min=0.0, min_open=True), default=1.5, show_default=True,
              help="Longest drawn mission [km] (a city-wide day: --min-km 1 --max-km 15).")
@click.option("--max-delay-min", type=FiniteFloat(min=0.0), default=10.0, show_default=True,
              help="Longest departure delay before a mission is rejected [min].")
@click.option("--delay-step-s", type=FiniteFloat(min=1.0), default=60.0, show_default=True,
              help="Departure delay step [s].")
@click.option("--ground-m", type=FiniteFloat(min=-500.0, max=9000.0), default=None,
              help="Height of the scenario's flat local ground above the EGM96 geoid [m] (sets data.ground when the "
                   "scenario has none; intents need absolute heights).")
@click.option("--no-preempt", is_flag=True, help="Priorities do not preempt accepted missions.")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True,
              help=SCHEDULER_HELP + "; with distributed / tcp:// the missions are planned speculatively in parallel")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Workers of --scheduler distributed.")
@click.option("--depth", type=click.IntRange(min=0), default=4, show_default=True,
              help="With --scheduler distributed / tcp://: the next missions planned ahead on the workers (the "
                   "decisions are the sequential ones at any depth).")
@click.option("--airspace", "airspace_file", type=click.Path(path_type=Path), default=None,
              help="Airspace file (SQLite, see `skyroute airspace`): plan against every intent already accepted there "
                   "and add this run's; missions already decided there are skipped (a killed run continues). Drawn "
                   "missions get ids s<SEED>-m0001... Default: a new OUT/airspace.sqlite.")
@click.option("-q", "--quiet", is_flag=True, help="No per-mission lines.")
@max_memory_option
def fleet_command(scenario, fleet_file, missions, seed, out_dir, window_min, min_km, max_km, max_delay_min,
                  delay_step_s, ground_m,
                  no_preempt, cache_dir, scheduler, workers, depth, airspace_file, quiet) -> None:
    """Plan many operators' missions in SCENARIO first-come-first-served (issue 15): each at one
    DOP level, every accepted mission's ASTM F3548 intent volumes as traffic in STEP II; a
    mission whose volumes would intersect an accepted one is delayed (--delay-step-s up to
    --max-delay-min) or rejected, and may preempt lower-priority missions (re-planned). Writes
    fleet.csv, intents/<mission>.json, fleet.geojson, tracks.csv, fleet.png, summary.json and
    the accepted intents into the airspace file (--airspace; each decision one transaction)."""
    from skyroute.pipeline.budget import check_fleet
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.fleet import (
        MAX_FLEET_MISSIONS,
        FleetFileError,
        FleetOptions,
        check_fleet_vehicle,
        default_level,
        draw_missions,
        fleet_maps,
        load_fleet,
        run_fleet,
    )
    from skyroute.pipeline.fleet_outputs import write_fleet
    from skyroute.pipeline.graph import scheduler_context
    from skyroute.pipeline.outputs import ensure_writable_dir, write_folder_summary
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, GroundReference, load_scenario
    from skyroute.stages.airspace_store import AirspaceStore

    if (fleet_file is None) == (missions is None):
        raise InputError("give either --fleet FILE or --missions N (with --seed S)")
    if min_km > max_km:
        raise InputError(f"--min-km {min_km:g} is above --max-km {max_km:g}: give the shortest mission first")
    if missions is not None and missions > MAX_FLEET_MISSIONS:
        raise InputError(f"--missions {missions:,}: one fleet run plans at most {MAX_FLEET_MISSIONS:,} missions; "
                         "split the day into runs that add to one airspace (--airspace FILE, --seed 1, 2, ...)")
    attempts = max_delay_min * 60.0 / delay_step_s + 1.0
    if attempts > MAX_ATTEMPTS:
        raise InputError(f"--max-delay-min {max_delay_min:g} / --delay-step-s {delay_step_s:g} is {attempts:,.0f} "
                         f"departures tried per mission (at most {MAX_ATTEMPTS:,}, each one plan): raise "
                         "--delay-step-s or lower --max-delay-min")
    if scheduler.startswith("tcp://"):    # not a dask scheduler: one line now, not after the maps
        from skyroute.pipeline.graph import check_scheduler_address

        check_scheduler_address(scheduler)
    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    if window_min is None:
        window_min = default_window_min(sc.gnss.window_min, max_delay_min)
    if ground_m is not None:
        sc = sc.model_copy(update={"data": sc.data.model_copy(
            update={"ground": GroundReference(height_m=ground_m, vertical_datum="EGM96 geoid")})})
    tasks = None
    if fleet_file is not None:
        try:    # read within a size limit, parsed strictly; every mission checked before the maps
            tasks = load_fleet(fleet_file, sc, sc.gnss.dop_thresholds)
        except FleetFileError as exc:
            for p in exc.problems:
                click.echo(f"error: {p}", err=True)
            sys.exit(2)
        longest_km = max(math.hypot(t.goal_xy[0] - t.start_xy[0], t.goal_xy[1] - t.start_xy[1]) for t in tasks) / 1e3
        check_fleet(sc, len(tasks), longest_km, key=f"the missions of {fleet_file}")
    else:
        check_fleet_vehicle(sc.vehicle)        # drawn missions fly the scenario's vehicle
        check_fleet(sc, missions, max_km)      # before the maps and the draw
    if tasks is not None and sc.data.almanacs:
        from skyroute.stages.orbits import AGE_LIMITS_S

        limit_s = AGE_LIMITS_S["almanac"][1]
        late = [t for t in tasks if t.earliest_s > limit_s]
        if late:
            raise InputError(f"{fleet_file}: mission {late[0].id} departs {late[0].earliest_s / 86400:.0f} days "
                             f"after the scenario start ({len(late)} mission(s) beyond {limit_s / 86400:.0f} days): the "
                             "scenario's almanacs do not hold that far; move the departures or the scenario's "
                             "mission.start_time_utc (with an almanac of that time)")
    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "fleet")
    if airspace_file is not None:      # a bad FILE: one error line before any planning
        note_input(airspace_file)      # never replaced by an output, never removed as stale
        store = AirspaceStore.open(airspace_file) if airspace_file.exists() or airspace_file.is_symlink() else None
    cache = Cache(cache_dir)
    maps = fleet_maps(sc, cache.root)
    crs = maps["surface"]["surface"].rio.crs
    if airspace_file is None:
        store = AirspaceStore.create(out_dir / "airspace.sqlite", crs, sc.mission.start_time_utc, replace=True)
    elif store is None:
        store = AirspaceStore.create(airspace_file, crs, sc.mission.start_time_utc)
    warnings: list[str] = []
    if tasks is None:
        tasks = draw_missions(sc, maps, missions, seed, window_min * 60.0, min_km=min_km, max_km=max_km,
                              notes=warnings)
        if airspace_file is not None:   # ids unique across the draws added to one airspace
            tasks = [dataclasses.replace(t, id=f"s{seed}-{t.id}") for t in tasks]
    level = default_level(maps)
    opt = FleetOptions(delay_step_s=delay_step_s, max_delay_s=max_delay_min * 60.0, seed=seed, preempt=not no_preempt)
    gnss_min = sc.gnss.window_min
    last = max(t.earliest_s for t in tasks) / 60.0 + max_delay_min
    if last > gnss_min:
        warnings.append(f"fleet: departures reach {last:.0f} min after the scenario start but the GNSS maps cover "
                        f"gnss.window_min = {gnss_min:g} min: later missions use the last epoch (coverage floors are "
                        "the worst case over the window)")
    echo = None if quiet else (lambda s: click.echo(s, err=True))
    if scheduler in ("threads", "synchronous", "sync"):
        res = run_fleet(sc, tasks, cache_dir=cache.root, options=opt, default_dop=level, echo=echo, airspace=store)
    else:
        with scheduler_context(scheduler, workers) as client:
            if client is None:
                raise InputError(f"--scheduler {scheduler}: the fleet runs sequentially (threads) or on "
                                 "dask.distributed (distributed, tcp://HOST:PORT)")
            res = run_fleet(sc, tasks, cache_dir=cache.root, options=opt, default_dop=level, client=client, echo=echo,
                            airspace=store, depth=depth)
    res.warnings.extend(warnings)
    files, section = write_fleet(res, sc, maps, out_dir)
    shift = store.time_shift_s(sc.mission.start_time_utc)
    air_conf = sorted({tuple(sorted((o.task.id, m))) for o in res.outcomes if o.attempt is not None
                       and o.status != "rejected" for _, m in store.conflicts(
                           [dataclasses.replace(v, t_start_s=v.t_start_s + shift, t_end_s=v.t_end_s + shift)
                            for v in o.attempt.volumes], exclude=(o.task.id,))})
    section["airspace"] = {**res.airspace, "conflicts_with_the_airspace": len(air_conf),
                           "conflicting_pairs": [list(c) for c in air_conf]}
    store.close()
    store_abs = Path(os.path.abspath(store.path))
    staged = folder_of(out_dir)
    if store_abs.is_relative_to(os.path.abspath(out_dir)):   # listed: never removed as stale
        files.append(store_abs)
    elif staged is not None and store_abs.is_relative_to(staged.final):   # --airspace OUT/x.sqlite: changed in place
        files.append(Path(out_dir) / staged.adopt_in_place(store_abs))
    section.update({"default_dop_level": level, "scheduler": scheduler,
                    "source": str(fleet_file) if fleet_file else (f"--missions {missions} --seed {seed} "
                                                                  f"--min-km {min_km:g} --max-km {max_km:g}"),
                    "window_min": window_min, "max_delay_min": max_delay_min, "delay_step_s": delay_step_s,
                    "options": dataclasses.asdict(opt)})
    for w in warnings:
        click.echo(f"warning: {w}", err=True)
    doc = write_folder_summary(out_dir, "fleet", maps["_result"], [str(f) for f in files], {"fleet": section})
    if warnings:
        import json

        doc["warnings"] = [*doc["warnings"], *warnings]
        (out_dir / "summary.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    c = section["counts"]
    click.echo(f"fleet: {section['missions']} missions: {c['accepted']} accepted, {c['delayed']} delayed, "
               f"{c['preempted-replanned']} preempted-replanned, {c['rejected']} rejected; mean delay "
               f"{section['mean_delay_s'] or 0:.0f} s; {section['throughput_plans_per_min']} plans/min; "
               f"conflicts (independent check) {section['conflicts_independent_check']} -> {shown(out_dir)}")
    if res.airspace.get("already_decided"):
        click.echo(f"airspace: {len(res.airspace['already_decided'])} mission(s) already decided in "
                   f"{res.airspace['file']} (skipped); it holds {res.airspace['intents_after']} intents", err=True)
    if section["accepted_total"] == 0 and res.outcomes:   # an honest result: nothing flies (reasons in fleet.csv)
        reasons = sorted({o.reason for o in res.outcomes if o.reason})
        click.echo("no mission accepted: " + (" | ".join(reasons[:3]) or "no mission was given"), err=True)
        sys.exit(3)

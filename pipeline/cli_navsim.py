"""``skyroute navsim``: Monte Carlo of the proposed and weak GNSS/INS filters along a plan."""

from __future__ import annotations

from pathlib import Path

import click

from skyroute.pipeline.budget import MAX_NAVSIM_RUNS
from skyroute.pipeline.cli import (
    QUIET_HELP,
    SCHEDULER_HELP,
    SEED,
    OutPath,
    max_memory_option,
    show_progress,
)
from skyroute.pipeline.outfolder import shown


@click.command("navsim")
@click.argument("scenario", required=False, default=None)
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/navsim).")
@click.option("--runs", type=click.IntRange(min=1, max=MAX_NAVSIM_RUNS), default=None,
              help=f"Monte Carlo runs (default: navsim.runs, 50; at most {MAX_NAVSIM_RUNS:,}, and as many as fit "
                   "--max-memory, estimated before any work).")
@click.option("--seed", type=SEED, default=None, help="Seed of every random draw (default: navsim.seed).")
@click.option("--trajectory", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A flown.csv of `skyroute fly` to simulate instead of the strategic plan.")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("-q", "--quiet", is_flag=True, help=QUIET_HELP)
@max_memory_option
def navsim_command(scenario, out_dir, runs, seed, trajectory, cache_dir, scheduler, quiet) -> None:
    """Navigation Monte Carlo of SCENARIO's chosen plan (seed 003 section III): each run
    simulates the IMU, the receiver clock and the pseudoranges (satellites hidden by the
    surface arrive by reflection with a positive bias, or not at all) and runs two EKFs: the
    proposed one (line-of-sight satellites only, R scaled by the local DOP) and the weak one
    (every received satellite). Writes navsim.csv, figures and summary.json with the
    containment of the k-sigma safety bubble (k = 1, 2, 3) per filter, the single-fault
    solution-separation protection levels (HPL/VPL, ARAIM style) with their containment, and
    the digital morphing map: the coverage floor per epoch over the flight (morphing.zarr) and
    a GIF of it under the moving vehicle."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.navsim import navsim_scenario, write_morphing
    from skyroute.pipeline.outputs import ensure_writable_dir, write_folder_summary
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario
    from skyroute.stages.navsim_outputs import navsim_section, write_navsim

    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "navsim")
    r = navsim_scenario(sc, cache=Cache(cache_dir), runs=runs, seed=seed, trajectory=trajectory, scheduler=scheduler,
                        progress=show_progress(quiet))
    from skyroute.pipeline.progress import phase

    with phase("navsim: navsim.csv and figures"):
        files = list(write_navsim(r.ds, out_dir, r.surface_uncertainty_m).values())
    morph = write_morphing(sc, r, out_dir)
    section = navsim_section(r.ds, r.surface_uncertainty_m)
    section["morphing"] = {"files": [p.name for p in morph], "step_s": sc.navsim.morphing_step_s,
                           "dop_threshold": r.dop_threshold}
    write_folder_summary(out_dir, "navsim", r.result, [str(p) for p in [*files, *morph]], {"navsim": section})
    c = section["containment"]
    click.echo(f"navsim: {section['runs']} runs x {section['epochs']} epochs; 3-sigma containment proposed "
               f"{c['proposed']['3sigma']:.3f}, weak {c['weak']['3sigma']:.3f}; proposed error smaller "
               f"{section['proposed_beats_weak']:.1%} of the time -> {shown(out_dir)}")
    pl = section.get("protection_level")
    if pl is not None and pl["hpl_median_m"] is not None:
        click.echo(f"navsim: protection level (solution separation) median HPL {pl['hpl_median_m']:.1f} m, "
                   f"VPL {pl['vpl_median_m']:.1f} m, available {pl['availability']:.1%}; proposed error "
                   f"contained {pl['containment_h']:.3f} (h) / {pl['containment_v']:.3f} (v)")

"""``skyroute diff``: what changed between two output folders (:mod:`skyroute.pipeline.diff`)."""

from __future__ import annotations

import json
from pathlib import Path

import click


@click.command("diff")
@click.argument("run_a", type=click.Path(path_type=Path))
@click.argument("run_b", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="One JSON document on stdout instead of the table.")
@click.option("--no-maps", is_flag=True, help="Do not compare the rasters (datasets/*.zarr, *.tif).")
def diff_command(run_a: Path, run_b: Path, as_json: bool, no_maps: bool) -> None:
    """What changed between two skyroute output folders RUN_A and RUN_B (of run, plan, fly,
    navsim, compare, maps or coverage): scenario and settings, the chosen plan (label, f and
    its terms, length, energy, flight time; B - A in units), candidates per coverage level,
    stage cache keys, the flight's outcome and levels, navsim containment, and per raster
    the largest difference and the number of cells changed. Exit code 0 whatever differs;
    2 (one `error:` line) when a folder is not a skyroute output folder."""
    from skyroute.pipeline.diff import diff_folders, format_diff

    res = diff_folders(run_a, run_b, maps=not no_maps)
    if as_json:
        click.echo(json.dumps(res.to_json(), indent=1, allow_nan=False))
    else:
        click.echo(format_diff(res))

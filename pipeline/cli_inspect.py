"""``skyroute inspect``: what skyroute will make of a data file or a scenario (:mod:`skyroute.pipeline.inspect`)."""

from __future__ import annotations

import sys

import click

from skyroute.pipeline.cli import max_memory_option


@click.command("inspect")
@click.argument("target")
@click.option("--json", "as_json", is_flag=True, help="One JSON document on stdout instead of the screen.")
@max_memory_option
def inspect_command(target: str, as_json: bool) -> None:
    """What skyroute will make of TARGET, in seconds, computing nothing heavy: a DSM or DEM
    (GeoTIFF, VRT), a CityJSON file, an OSM extract, or a scenario (catalog name or YAML) for its
    AOI. One screen: CRS and vertical datum, extent against the AOI, how cells are read (DSM:
    footprint max; DEM: the surface through its samples, AREA_OR_POINT), NoData share and how it
    is filled, height range, buildings and parts, the ground source, absolute heights and the
    pilot files they allow (plan.kml, plan.plan, intent.json), landing sites; then every problem
    as one `error:` or `warning:` line naming the YAML key to change. Exit code 2 when there is
    an error, else 0."""
    from skyroute.pipeline.inspect import format_inspection, inspect_target, inspection_json

    ins = inspect_target(target)
    click.echo(inspection_json(ins) if as_json else format_inspection(ins))
    if not ins.ok:
        sys.exit(2)

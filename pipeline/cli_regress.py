"""``skyroute regress``: the catalog's key figures against golden values (see
:mod:`skyroute.pipeline.regress`)."""

from __future__ import annotations

from pathlib import Path

import click

from skyroute.pipeline.cli import SCHEDULER_HELP, OutPath


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    s = str(v)
    return s if len(s) <= 40 else s[:37] + "..."


@click.command("regress")
@click.argument("scenarios", nargs=-1)
@click.option("--update", is_flag=True, help="Rewrite the golden files with this run's figures (review the diff).")
@click.option("--golden-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Folder of golden JSON files (default: the packaged catalogs/golden).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True,
              help=SCHEDULER_HELP + "; with a cluster each scenario is one task")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="LocalCluster workers (--scheduler distributed).")
@click.option("--all", "show_all", is_flag=True, help="List every figure, not only failures and new ones.")
def regress_command(scenarios, update, golden_dir, cache_dir, scheduler, workers, show_all) -> None:
    """Run every catalog scenario (or SCENARIOS) through the cache: the plan, `fly` for
    scenarios with events and `navsim` for the others with almanacs; compare each key figure
    (costs, lengths, energy, outcomes, containment; never timings) with the golden values
    within its stated tolerance. Prints pass / fail / new per figure and exits 1 on a failure.
    Only stages whose inputs, settings or code changed recompute."""
    import sys

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.regress import regress

    echo = (lambda m: click.echo(m, err=True)) if sys.stderr.isatty() else None
    res = regress(list(scenarios) or None, cache=Cache(cache_dir), golden=golden_dir, update=update,
                  scheduler=scheduler, workers=workers, echo=echo)
    rows = [c for c in res.checks if show_all or c.status != "pass"]
    if rows:
        w = max(len(f"{c.scenario} {c.name}") for c in rows)
        click.echo(f"{'scenario figure':<{w}}  {'status':<6}  {'value':>14}  {'golden':>14}  tolerance")
        for c in rows:
            tol = "equal" if c.tolerance is None else f"{c.tolerance:g}"
            click.echo(f"{c.scenario + ' ' + c.name:<{w}}  {c.status:<6}  {_fmt(c.value):>14}  {_fmt(c.golden):>14}  {tol}")
    n = res.counts()
    secs = sum(res.seconds.values())
    verb = "golden files written" if update else "checked"
    click.echo(f"regress: {len(res.seconds)} scenarios, {len(res.checks)} figures {verb}: {n['pass']} pass, "
               f"{n['fail'] + n['gone']} fail, {n['new']} new ({secs:.1f} s)")
    if res.failed:
        raise SystemExit(1)

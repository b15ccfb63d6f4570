"""The ``skyroute`` command line.

Every :class:`~skyroute.pipeline.errors.SkyrouteError` becomes a one-line ``error: ...`` on
stderr with exit code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import sys
import time
from pathlib import Path

import click

from skyroute.pipeline.errors import SkyrouteError
from skyroute.stages.planning.registry import PLANNERS, planner_help

_T0 = time.perf_counter()     # when the CLI was imported (the wall clock's start)
_CPU0 = time.process_time()   # CPU time [s] of the process by then: the interpreter's start-up
_COMMANDS = [0, _T0]          # commands started in this process, start of the latest one


def _command_started() -> None:
    _COMMANDS[0] += 1
    _COMMANDS[1] = time.perf_counter()


STARTUP_LOAD_FACTOR = 3.0     # the interpreter's start-up takes at most this x its CPU time [1]


def wall_s() -> float:
    """Seconds of the running command [s]: for a later command in the same process (a notebook
    or a test calling ``main`` again), since that command started; for the first one, since the
    interpreter started: the time since this module was imported plus the start-up before it
    (interpreter, ``site``, the imports above: 0.16-0.22 s of CPU, 0.25-0.47 s of wall at load
    5 on 2 cores).  That start-up is the wall time since the process started (Linux
    ``/proc/self/stat``) when it is at most :data:`STARTUP_LOAD_FACTOR` x the CPU time the
    process had used by the import, else that CPU time (a lower bound): the process may have
    started long before the interpreter, as with ``bash -c 'sleep 5 && skyroute run'``, where
    bash execs skyroute in its own process, started 5 s earlier."""
    if _COMMANDS[0] > 1:
        return time.perf_counter() - _COMMANDS[1]
    since_import = time.perf_counter() - _T0
    startup = _CPU0
    try:
        with open("/proc/self/stat", "rb") as f:
            start_ticks = int(f.read().rsplit(b")", 1)[1].split()[19])   # field 22: starttime [ticks]
        with open("/proc/uptime", "rb") as f:
            uptime_s = float(f.read().split()[0])
        before = uptime_s - start_ticks / os.sysconf("SC_CLK_TCK") - since_import   # 10 ms resolution
        if before <= STARTUP_LOAD_FACTOR * _CPU0:
            startup = max(before, 0.0)
    except (OSError, ValueError, IndexError):
        pass
    return since_import + startup


SCHEDULER_HELP = ("dask scheduler: threads (default), processes, synchronous, distributed "
                  "(a new LocalCluster, see --workers) or the address of a running cluster tcp://HOST:PORT")


class FiniteFloat(click.FloatRange):
    """A float option that refuses nan and +-inf (``click.FloatRange`` lets nan through every
    bound and inf through an open upper bound)."""

    def convert(self, value, param, ctx):
        import math

        v = super().convert(value, param, ctx)
        if v is not None and not math.isfinite(v):
            self.fail(f"{value!r} is not a finite number; give a number such as 1.5", param, ctx)
        return v

    def _describe_range(self) -> str:
        """The range shown in ``--help``: none without bounds (click would print ``[x<=None]``)."""
        if self.min is None and self.max is None:
            return ""
        return super()._describe_range()


class OutPath(click.Path):
    """An output path option (``--out``, ``--cache-dir``) that refuses an empty or blank value
    (``--out ""`` would otherwise mean the current folder)."""

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            self.fail("an empty path; give a folder (or file) name, e.g. out/run1", param, ctx)
        return super().convert(value, param, ctx)


def _set_max_memory(ctx, param, value):
    from skyroute.pipeline.budget import set_max_memory

    set_max_memory(None if value is None else parse_size(value, "--max-memory"))
    return value


def max_memory_option(f):
    """``--max-memory SIZE`` of a command that computes: requests estimated to need more are
    refused before any work (:mod:`skyroute.pipeline.budget`)."""
    return click.option("--max-memory", default=None, metavar="SIZE", expose_value=False, callback=_set_max_memory,
                        help="Refuse, before any work, a request estimated to need more memory than this (e.g. 8G; "
                             "default: $SKYROUTE_MAX_MEMORY or 80% of the machine's memory).")(f)


SEED = click.IntRange(min=0, max=2**32 - 1)   # numpy and OMPL seeds: 0 .. 2**32 - 1


class SkyrouteGroup(click.Group):
    """A click group that reports SkyrouteError, and click's own usage errors (a bad option
    value, an unknown option), as one clean ``error: ...`` line (exit code 2).  Every command
    added takes ``-v`` and ``-q`` (:func:`add_verbosity_options`)."""

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        super().add_command(cmd, name)
        add_verbosity_options(cmd)

    def invoke(self, ctx: click.Context):
        from skyroute.pipeline import control, outfolder
        from skyroute.pipeline.budget import set_max_memory
        from skyroute.stages.base import forget_inputs

        # a callable default scheduler: reading a lazy array outside a command's own
        # --scheduler context would otherwise look for a distributed client (importing
        # distributed, ~0.1-0.5 s); --scheduler still overrides it inside
        forget_inputs()            # the files this command reads, as it reads them (outfolder)
        with control.signal_handlers(), threaded_dask_default():
            try:
                try:
                    rv = super().invoke(ctx)
                except (click.exceptions.Exit, SystemExit) as done:
                    code = done.exit_code if isinstance(done, click.exceptions.Exit) else done.code
                    if code in (0, 3, None):   # 3: written, but no flyable plan / nothing accepted
                        outfolder.commit_all()
                    raise
                outfolder.commit_all()   # the outputs are put into place only now
                return rv
            except SkyrouteError as exc:
                msg = str(exc)
                click.echo(f"error: {msg}", err=True)
                ctx.exit(2)
            except OSError as exc:
                import errno

                if exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
                    raise
                where = f" writing {exc.filename}" if exc.filename else ""
                click.echo(f"error: {exc.strerror or exc}{where}: free some space or choose another --out / "
                           "--cache-dir", err=True)
                ctx.exit(2)
            except click.UsageError as exc:
                where = exc.ctx.command_path if exc.ctx is not None else ctx.command_path
                msg = " ".join(exc.format_message().split())
                click.echo(f"error: {msg} (see `{where} -h`)", err=True)
                ctx.exit(2)
            except KeyboardInterrupt:
                _interrupted(ctx, control)
            except Exception:
                # a signal that reaches Python while a compiled kernel or numba's dispatcher is on
                # the stack can surface as another exception (numba: SystemError "returned a
                # result with an exception set"): once a cancel was requested, it is the interrupt
                if not control.cancelled():
                    raise
                _interrupted(ctx, control)
            finally:
                from skyroute.pipeline import progress

                progress.close()          # no progress line left behind
                outfolder.discard_all()   # a failed or interrupted command leaves --out as it was
                set_max_memory(None)   # --max-memory holds for this command only (a session may run more)


@contextlib.contextmanager
def threaded_dask_default():
    """For the ``with`` block: dask's default scheduler is the threaded one, as a callable (a
    named default makes dask look for a distributed client, importing distributed), set once
    dask is imported: a command that never imports dask (a warm run) does not import it for this."""
    state: dict = {}

    def configure(dask) -> None:
        import dask.threaded

        state["set"] = dask.config.set(scheduler=dask.threaded.get)

    hook = None
    if "dask" in sys.modules:
        configure(sys.modules["dask"])
    else:
        hook = _AfterImport("dask", configure)
        sys.meta_path.insert(0, hook)
    try:
        yield
    finally:
        if hook is not None and hook in sys.meta_path:
            sys.meta_path.remove(hook)
        if "set" in state:
            state["set"].__exit__(None, None, None)


class _AfterImport:
    """A one-shot meta path finder: ``then(module)`` runs right after the module ``name`` is
    first imported (its own finder and loader do the import)."""

    def __init__(self, name: str, then):
        self.name, self.then = name, then

    def find_spec(self, fullname, path=None, target=None):
        if fullname != self.name:
            return None
        sys.meta_path.remove(self)
        import importlib.util

        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        loader, then = spec.loader, self.then

        class _Loader:
            def create_module(self, spec):
                return loader.create_module(spec)

            def exec_module(self, module):
                module.__spec__.loader = module.__loader__ = loader
                loader.exec_module(module)
                then(module)

        spec.loader = _Loader()
        return spec


def _interrupted(ctx: click.Context, control) -> None:
    """SIGINT -> 130, SIGTERM -> 143 with one ``interrupted`` line; every stage output is either
    complete in the cache or an orphan under its tmp/ folder (never trusted)."""
    code = control.exit_code()
    control.request_cancel()
    control.mark_reported()
    click.echo("interrupted", err=True)
    if control.signal_received() is not None:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)   # do not wait for dask's worker threads to drain their queue
    ctx.exit(code)


def check_stage_names(names, option: str, also=()) -> None:
    """InputError naming ``option`` when a name is not a pipeline stage (``run --force bogus``
    used to succeed silently)."""
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.graph import REGISTRY, _load_registry

    _load_registry()
    known = sorted(set(REGISTRY) | set(also))
    bad = [n for n in names if n not in known]
    if bad:
        raise InputError(f"{option} {', '.join(bad)}: not a stage; give one of {', '.join(known)}")


def _report_warnings(warnings: list[str]) -> None:
    """The ``warning:`` lines of ``warnings`` not printed yet by this command (a warning raised
    while a stage computed was printed then; a warm run prints it from the stage's dataset)."""
    from skyroute.pipeline.outputs import PRINTED_WARNINGS, report_warnings

    report_warnings([w for w in warnings if w not in PRINTED_WARNINGS])


def _exit_if_no_plan(plan: dict | None) -> None:
    """Exit code 3 with one line when the plan section says no candidate is flyable."""
    from skyroute.pipeline.outputs import plan_summary_line

    if plan is not None and plan["status"] != "flyable":
        click.echo(plan_summary_line(plan), err=True)
        sys.exit(3)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Python warnings as one clean ``warning: <text>`` line (no source line, no category).

    A ``DeprecationWarning`` / ``PendingDeprecationWarning`` is a library telling its developers
    about their code (numpy's "Use `@` matmul instead of `*`" from a dependency), not a warning
    about the user's request: it is not shown (nor counted); ``-vv`` shows it in Python's own
    format (this function is not installed then)."""
    from skyroute.pipeline.outputs import note_printed_warning

    if isinstance(category, type) and issubclass(category, DeprecationWarning | PendingDeprecationWarning):
        return
    text = " ".join(str(message).split())
    note_printed_warning(text)
    print(f"warning: {text}", file=file or sys.stderr, flush=True)


class _StderrHandler(logging.StreamHandler):
    """Log records on ``sys.stderr`` as it is at each record (a test runner's capture, or the
    progress display's guard, which clears the progress line first)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


_SHOWWARNING: list = []   # Python's own warnings.showwarning, while ours is installed


def _setup_logging(verbose: int) -> None:
    """Log level and warning format of ``-v`` (0: warnings only, 1: info, 2+: debug); called again
    when a command's own ``-v`` adds to the group's."""
    import warnings

    if verbose < 2:  # -vv keeps Python's own format (file and line) for debugging
        if warnings.showwarning is not _show_warning:
            _SHOWWARNING[:] = [warnings.showwarning]
            warnings.showwarning = _show_warning
    elif warnings.showwarning is _show_warning and _SHOWWARNING:
        warnings.showwarning = _SHOWWARNING[0]
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s level=%(levelname)s logger=%(name)s %(message)s"))
    logging.basicConfig(level=level, handlers=[handler])   # once a process (a root without handlers)
    root = logging.getLogger()
    if any(isinstance(h, _StderrHandler) for h in root.handlers):
        root.setLevel(level)
    logging.getLogger("skyroute").setLevel(level)
    # other libraries' info lines (pyogrio's "Created N records" per layer) only with -vv
    logging.getLogger("pyogrio").setLevel(logging.DEBUG if verbose >= 2 else logging.WARNING)


# -v / -q: the same options, the same meaning, before or after the command name (`skyroute -q
# plan`, `skyroute plan -q`): the group and every command take both, and what is given in either
# place adds up (-v counts, -q is set by either); each command's own `quiet` parameter (run's
# JSON line, fleet's per-mission lines) receives the merged value.
QUIET_HELP = "No progress display on stderr."
VERBOSE_HELP = ("Log lines on stderr (-v info, -vv debug); when stderr is no terminal, also one progress "
                "line per phase.")
_VERBOSITY = "skyroute.verbosity"


def _verbosity(ctx: click.Context, param: click.Parameter, value):
    """Callback of every -v / -q: adds the value to the command line's verbosity (kept in the root
    context) and applies it (log level, progress display); returns the merged value."""
    st = ctx.find_root().meta.setdefault(_VERBOSITY, {"verbose": 0, "quiet": False})
    if param.name == "verbose":
        st["verbose"] += int(value or 0)
        value = st["verbose"]
    else:
        st["quiet"] = st["quiet"] or bool(value)
        value = st["quiet"]
    from skyroute.pipeline import progress

    _setup_logging(st["verbose"])
    progress.configure(quiet=st["quiet"], verbose=st["verbose"])
    return value


def verbosity_options(f):
    """``-v/--verbose`` (count) and ``-q/--quiet`` of the group (the commands get them from
    :func:`add_verbosity_options`)."""
    f = click.option("-q", "--quiet", is_flag=True, expose_value=False, callback=_verbosity,
                     help=QUIET_HELP + " Before or after the command name (skyroute -q CMD = skyroute CMD -q).")(f)
    return click.option("-v", "--verbose", count=True, expose_value=False, callback=_verbosity,
                        help=VERBOSE_HELP + " Before or after the command name.")(f)


def add_verbosity_options(cmd: click.Command) -> None:
    """Give ``cmd`` (and, for a group, its commands) ``-v`` and ``-q``: a command's own ``quiet``
    option gets the merged value (its help is its own); options it lacks are added."""
    flags = {o for p in cmd.params for o in (*getattr(p, "opts", ()), *getattr(p, "secondary_opts", ()))}
    names = {p.name for p in cmd.params}
    if "verbose" not in names and not flags & {"-v", "--verbose"}:
        cmd.params.append(click.Option(["-v", "--verbose"], count=True, expose_value=False, callback=_verbosity,
                                       help=VERBOSE_HELP))
    own = next((p for p in cmd.params if p.name == "quiet" and isinstance(p, click.Option)), None)
    if own is not None:
        if own.callback is None:
            own.callback = _verbosity
    elif not flags & {"-q", "--quiet"}:
        cmd.params.append(click.Option(["-q", "--quiet"], is_flag=True, expose_value=False, callback=_verbosity,
                                       help=QUIET_HELP))
    if isinstance(cmd, click.Group):
        for sub in cmd.commands.values():
            add_verbosity_options(sub)


def show_progress(quiet: bool) -> bool:
    """Whether a command with ``-q`` = ``quiet`` shows its progress (:func:`skyroute.pipeline.progress.wanted`)."""
    from skyroute.pipeline import progress

    return progress.wanted(quiet)


@click.group(cls=SkyrouteGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@verbosity_options
@click.version_option(package_name="skyroute")
def main() -> None:
    """skyroute: plan safe, GNSS-aware, risk-aware and energy-aware drone flights from real maps,
    real satellite almanacs and real wind.

    \b
    Typical use:
      skyroute scenarios                      list the catalog
      skyroute run                            run the default scenario (helsinki-medical)
      skyroute run rotterdam-canyon --out out/rotterdam
      skyroute cache ls                       show cached stage outputs

    Long work shows its progress on stderr (stages, Monte Carlo runs, the flight replay, outputs
    being written): one line updated in place on a terminal, one line per phase with -v
    otherwise, nothing with -q.  -v and -q mean the same before or after the command name.
    """
    _command_started()
    from skyroute.pipeline.outputs import PRINTED_WARNINGS

    PRINTED_WARNINGS.clear()                    # one command's warnings (a Python session may run several)
    from skyroute.pipeline.budget import set_max_memory

    set_max_memory(None)                        # --max-memory of an earlier command in this session
    # (-v / -q: applied by their callbacks, the group's and then the command's)


@main.command("scenarios")
@click.option("--copy", "copy", nargs=2, type=(str, click.Path(file_okay=False, path_type=Path)), default=None,
              metavar="NAME DIR", help="Write catalog scenario NAME as DIR/NAME.yaml with its data paths made "
              "absolute, ready to edit (an existing file is not replaced).")
def scenarios_command(copy) -> None:
    """List the scenario catalog, one line each (or copy one with --copy NAME DIR)."""
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario, scenario_paths

    if copy is not None:
        from skyroute.pipeline.settings.io import copy_scenario

        dest, n = copy_scenario(*copy)
        click.echo(f"{copy[0]} -> {dest} ({n} data path(s) made absolute); edit it, then: skyroute run {dest}")
        return
    for name, path in scenario_paths().items():
        try:
            sc = load_scenario(path)
            g = sc.grid
            desc = " ".join(sc.description.split())
            if len(desc) > 70:
                desc = desc[:67] + "..."
            mark = "*" if name == DEFAULT_SCENARIO else " "
            click.echo(f"{mark} {name:24s} {g.nx}x{g.ny} cells @ {g.resolution_m:g} m  {g.crs_wkt[:12]:12s} {desc}")
        except SkyrouteError as exc:
            click.echo(f"! {name:24s} INVALID: {str(exc).splitlines()[0]}")


@main.command("run")
@click.argument("scenario", required=False, default=None)
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Workers for processes/distributed.")
@click.option("--stage", "targets", multiple=True, help="Run only these stages (and what they need).")
@click.option("--force", multiple=True, help="Recompute these stages even if cached.")
@click.option("--link", is_flag=True, help="Link DIR/datasets/*.zarr into the cache instead of copying them "
              "(saves space; the links break when the cache is cleared).")
@click.option("--no-report", "no_report", is_flag=True, help="Do not write DIR/report.html.")
@click.option("-q", "--quiet", is_flag=True,
              help="No progress display; print one JSON line (out, seconds, stages_seconds, plan) instead of the "
                   "stage table.")
@max_memory_option
def run_command(scenario, out_dir, cache_dir, scheduler, workers, targets, force, link, no_report, quiet) -> None:
    """Run every stage that applies to SCENARIO (a catalog name or a YAML path; default
    helsinki-medical) and write datasets, GeoTIFFs, figures, summary.json, the interactive map
    plan/plan.html and the one-page report.html (see `skyroute report`) to --out.
    Prints the chosen plan's summary line; exit code 3 (after writing every output) when no
    candidate is flyable."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.outputs import ensure_writable_dir, plan_summary_line, write_run_outputs
    from skyroute.pipeline.report import REPORT_NAME, build_report
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario

    check_stage_names(force, "--force")
    check_stage_names(targets, "--stage")
    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name)
    result = run_scenario(sc, cache=Cache(cache_dir), targets=targets or None, scheduler=scheduler,
                          workers=workers, progress=show_progress(quiet), force=force)
    fly = None
    if getattr(sc, "events", ()) and "plan" in result.datasets:
        fly = _run_fly(sc, result, out_dir, scheduler, quiet, cache_dir)
    summary = write_run_outputs(result, out_dir, link=link, extra=fly,
                                also_files=() if no_report else (REPORT_NAME,))
    if not no_report:
        from skyroute.pipeline import progress

        with progress.phase("run: report.html"):
            build_report(out_dir)
    _report_warnings(summary["warnings"])
    plan = summary.get("plan")
    if not quiet:
        for rec in result.records:
            click.echo(f"  {rec.name:12s} {'cache' if rec.cache_hit else 'computed':8s} {rec.seconds:7.2f} s")
        click.echo(f"{sc.name}: {len(result.records)} stages, {result.cache_hits} from cache "
                   f"({result.seconds:.2f} s), {wall_s():.2f} s wall in all -> {shown(out_dir)}")
        if plan is not None and plan["status"] == "flyable":
            click.echo(plan_summary_line(plan))
        if fly is not None:
            from skyroute.stages.tactical.log import fly_summary_line

            click.echo(fly_summary_line(fly["section"]))
    else:
        # seconds: the wall time of the whole command (start-up, imports, outputs and report included)
        doc = {"out": str(shown(out_dir)), "seconds": round(wall_s(), 3),
               "stages_seconds": round(summary["seconds"], 3)}
        if plan is not None:
            doc["plan"] = plan["status"]
        click.echo(json.dumps(doc))
    _exit_if_no_plan(plan)


def _run_fly(sc, result, out_dir: Path, scheduler: str, quiet: bool, cache_dir=None) -> dict | None:
    """``skyroute run`` of a scenario with events: the flight replay into ``DIR/fly/`` (its
    own summary.json); returns the files and the section for the run's summary.  Not done
    when the strategic plan is not flyable (the run then exits 3 for that)."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fly_outputs import fly_folder
    from skyroute.pipeline.graph import stage_attrs

    if int(stage_attrs(result, "plan").get("chosen_level", -1)) < 0:
        return None
    fly_dir = Path(out_dir) / "fly"
    section = fly_folder(sc, fly_dir, cache=Cache(cache_dir), scheduler=scheduler, result=result)
    doc = json.loads((fly_dir / "summary.json").read_text())
    return {"files": [f"fly/{f}" for f in doc["files"]], "section": section}


@main.command("maps")
@click.argument("scenario", required=False, default=None)
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/maps).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("-q", "--quiet", is_flag=True, help=QUIET_HELP)
@max_memory_option
def maps_command(scenario, out_dir, cache_dir, scheduler, quiet) -> None:
    """Environment maps of SCENARIO: GeoTIFFs of risk, landing, no-fly and clearance layers
    and a PNG panel (risk, landing cost, wind over buildings, no-fly, a traffic slice)."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.maps import plot_maps_panel, write_map_geotiffs
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario

    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    from skyroute.pipeline.outputs import ensure_writable_dir

    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "maps")
    from skyroute.pipeline.graph import stages_for

    wanted = ("surface", "environment", "wind", "clearance", "traffic")
    targets = [s.name for s in stages_for(sc) if s.name in wanted]
    result = run_scenario(sc, cache=Cache(cache_dir), targets=targets, scheduler=scheduler,
                          progress=show_progress(quiet))
    files = write_map_geotiffs(result, out_dir)
    files.append(plot_maps_panel(result, out_dir / "maps.png"))
    _folder_summary(out_dir, "maps", result, files, {"maps": {"stages": targets}})
    for f in files:
        click.echo(str(shown(f)))


@main.command("plan")
@click.argument("scenario", required=False, default=None)
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/plan).")
@click.option("--weights", default=None, metavar="W_L,W_R,W_D,W_E",
              help="Cost weights of eq. 11: length, risk, landing, energy (overrides planner.weights).")
@click.option("--planner", "planner_name", default=None, metavar="|".join(PLANNERS),
              help=f"STEP I planner ({planner_help()}; overrides planner.name).")
@click.option("--seed", type=SEED, default=None, help="Random seed of BIT* and the RRT (overrides planner.seed).")
@click.option("--time-budget", "time_budget_s", type=FiniteFloat(), default=None,
              help="BIT* time per coverage level [s] (overrides planner.time_budget_s).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("-q", "--quiet", is_flag=True, help=QUIET_HELP)
@max_memory_option
def plan_command(scenario, out_dir, weights, planner_name, seed, time_budget_s, cache_dir, scheduler, quiet) -> None:
    """Strategic plan of SCENARIO (seed 000 III): for every GNSS coverage level D_j, STEP I
    (BIT* or A*), STEP II (deconfliction against known traffic) and STEP III (min-snap, navigation
    error, eq. 15 costs); writes plan.geojson, waypoints.csv, candidates.csv, figures and the
    pilot exports (plan.kml, plan.plan for QGroundControl, plan.gpkg, intent.json: ASTM F3548)
    of the flyable candidate with minimum f (or candidates.csv with every reason when none is flyable,
    exit code 3)."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.errors import InputError
    from skyroute.pipeline.outputs import (
        ensure_writable_dir,
        plan_output_key,
        plan_outputs,
        plan_summary_line,
    )
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario

    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    upd = {}
    if weights is not None:
        try:
            w = tuple(float(v) for v in weights.split(","))
        except ValueError:
            raise InputError(f"--weights {weights!r}: give four numbers W_L,W_R,W_D,W_E, e.g. 1,1,1,1") from None
        if len(w) != 4:
            raise InputError(f"--weights {weights!r}: give four numbers W_L,W_R,W_D,W_E, e.g. 1,1,1,1")
        upd["weights"] = w
    if planner_name is not None:
        upd["name"] = planner_name
    if seed is not None:
        upd["seed"] = seed
    if time_budget_s is not None:
        upd["time_budget_s"] = time_budget_s
    if upd:
        from skyroute.pipeline.settings import PLANNERS, PlannerSettings, parse_planner

        planner = parse_planner({**sc.planner.model_dump(), **upd})
        assert isinstance(planner, PlannerSettings)
        sc = sc.model_copy(update={"planner": planner})
        from skyroute.stages.planning.kinds import check_planner_vehicle

        check_planner_vehicle(planner.name, sc.vehicle, PLANNERS)   # InputError naming the planners that fit
    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "plan")
    result = run_scenario(sc, cache=Cache(cache_dir), targets=["plan"], scheduler=scheduler,
                          progress=show_progress(quiet))
    cached = all(r.path for r in result.records if r.name == "plan")
    rel, plan, exports = plan_outputs(result, out_dir, "", plan_output_key(result) if cached else None)
    files = [out_dir / f for f in rel]
    _folder_summary(out_dir, "plan", result, files, {"plan": plan, "exports": exports})
    for f in files:
        click.echo(str(shown(f)))
    if plan["status"] == "flyable":
        click.echo(plan_summary_line(plan))
    _exit_if_no_plan(plan)


@main.command("report")
@click.argument("run_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", "out_path", type=OutPath(dir_okay=False, path_type=Path), default=None,
              help="The HTML file to write (default: RUN_DIR/report.html).")
@click.option("--no-maps", "no_maps", is_flag=True,
              help="Do not draw the scenario's maps into a plan, fly or navsim folder that has none.")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
def report_command(run_dir, out_path, no_maps, cache_dir) -> None:
    """One self-contained HTML page (figures embedded, nothing loaded from the network) of a
    folder written by `skyroute run`, `plan`, `fly` or `navsim`: the scenario, the outcome (or
    why no plan flies), maps, the chosen path, the candidates' costs, tactical events, the
    navigation Monte Carlo, stage timings and cache hits, data attribution.  A plan, fly or
    navsim folder without maps gets them in the page (surface, risk / landing / wind / no-fly
    panel, coverage floors per D_j, drawn from its scenario's map stages in the cache; nothing
    is written into RUN_DIR but the report itself); a fly folder without its interactive map
    gets one (fly.html)."""
    import tempfile

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.outfolder import add_to_manifest, check_replaceable, owned_by_skyroute
    from skyroute.pipeline.outputs import check_writable_dir
    from skyroute.pipeline.report import (
        REPORT_NAME,
        add_to_summary,
        build_report,
        draw_missing_maps,
        write_fly_map,
    )

    check_writable_dir(Path(out_path).parent if out_path is not None else run_dir, "--out")  # before any drawing
    page = Path(out_path) if out_path is not None else Path(run_dir) / REPORT_NAME
    for p in (page, Path(run_dir) / "fly.html"):
        check_replaceable(p, "--out" if p == page and out_path is not None else "report")   # never a user's file
    own_summary = owned_by_skyroute(Path(run_dir) / "summary.json")   # else it is read, never rewritten
    added = []
    fly_map = write_fly_map(run_dir)
    if fly_map is not None:
        added.append(fly_map)
    with tempfile.TemporaryDirectory(prefix="skyroute-report-") as tmp:
        drawn = [] if no_maps else draw_missing_maps(run_dir, Cache(cache_dir), into=Path(tmp))
        path = build_report(run_dir, out_path, maps_dir=Path(tmp) if drawn else None)
    inside = [p for p in (path, *added) if Path(p).resolve().parent.is_relative_to(Path(run_dir).resolve())]
    if own_summary and inside:
        add_to_summary(run_dir, inside)
    add_to_manifest(run_dir, [*inside, *([Path(run_dir) / "summary.json"] if own_summary else [])])
    if path not in inside:
        add_to_manifest(path.parent, [path])   # a page elsewhere (--out): the next report may replace it
    click.echo(str(path))


@main.command("coverage")
@click.argument("scenario", required=False, default=None)
@click.option("--out", "out_dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: ./skyroute-out/SCENARIO/coverage).")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None,
              help="Stage cache folder (default: $SKYROUTE_CACHE_DIR or ~/.cache/skyroute).")
@click.option("--scheduler", default="threads", show_default=True, help=SCHEDULER_HELP)
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Workers for processes/distributed.")
@click.option("-q", "--quiet", is_flag=True, help=QUIET_HELP)
@max_memory_option
def coverage_command(scenario, out_dir, cache_dir, scheduler, workers, quiet) -> None:
    """GNSS coverage maps of SCENARIO: for each DOP threshold D_j (scenario gnss.dop_thresholds)
    the altitude above which DOP < D_j, worst case over the mission window, as one GeoTIFF per
    D_j plus a PNG figure."""
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.cli_coverage import write_coverage_outputs
    from skyroute.pipeline.runner import run_scenario
    from skyroute.pipeline.settings import DEFAULT_SCENARIO, load_scenario

    sc = load_scenario(scenario or DEFAULT_SCENARIO)
    from skyroute.pipeline.outputs import ensure_writable_dir

    out_dir = ensure_writable_dir(out_dir or Path("skyroute-out") / sc.name / "coverage")
    result = run_scenario(sc, cache=Cache(cache_dir), targets=["coverage"], scheduler=scheduler, workers=workers,
                          progress=show_progress(quiet))
    cov = result["coverage"]   # lazy: the GeoTIFFs are written chunk by chunk, the figure from a reduced view
    files = write_coverage_outputs(cov, out_dir)
    _folder_summary(out_dir, "coverage", result, files, {"coverage": {
        "dop_kind": str(cov.attrs.get("dop_kind", "")),
        "thresholds": [float(t) for t in cov["coverage_floor"]["threshold"].values]}})
    for f in files:
        click.echo(str(shown(f)))


@main.group("cache")
def cache_group() -> None:
    """Show or remove cached stage outputs."""


@cache_group.command("ls")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None)
def cache_ls(cache_dir) -> None:
    """List cache entries: stage, key, scenario, size, creation time."""
    from skyroute.pipeline.cache import Cache

    c = Cache(cache_dir)
    entries = c.entries()
    click.echo(f"cache: {c.root} ({len(entries)} entries)")
    for e in entries:
        click.echo(f"  {e.stage:12s} {e.key}  {e.manifest.get('scenario', '?'):24s} "
                   f"{e.size_bytes / 1e6:8.2f} MB  {e.manifest.get('created_utc', '')}")


@cache_group.command("clear")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None)
@click.option("--stage", default=None, help="Remove only the entries of this stage.")
def cache_clear(cache_dir, stage) -> None:
    """Remove cache entries (all, or one stage's) and orphaned temporaries."""
    from skyroute.pipeline.cache import Cache

    c = Cache(cache_dir)
    if stage is not None:
        check_stage_names([stage], "--stage", also=[e.stage for e in c.entries()])
    n = c.clear(stage)
    click.echo(f"removed {n} entr{'y' if n == 1 else 'ies'} from {c.root}")


from skyroute.pipeline.budget import parse_size  # noqa: E402  (its home; the CLI's name)


@cache_group.command("prune")
@click.option("--cache-dir", type=OutPath(file_okay=False, path_type=Path), default=None)
@click.option("--max-size", required=True, help="Keep at most this much (e.g. 10G, 500M): the least "
              "recently used entries go first.")
def cache_prune(cache_dir, max_size) -> None:
    """Remove least-recently-used cache entries until the cache fits in --max-size."""
    from skyroute.pipeline.cache import Cache

    limit = parse_size(max_size)
    c = Cache(cache_dir)
    removed = c.prune(limit)
    left = sum(e.size_bytes for e in c.entries())
    click.echo(f"removed {len(removed)} entr{'y' if len(removed) == 1 else 'ies'} "
               f"({', '.join(f'{e.stage}-{e.key}' for e in removed) or 'none'}); "
               f"{left / 1e6:.2f} MB left in {c.root}")


# Commands contributed by the stage modules (each file defines one click command).
_PLUGINS = {
    "skyroute.pipeline.cli_gnss": "sky_command",
    "skyroute.pipeline.cli_occlusion": "visibility_height_command",
    "skyroute.pipeline.cli_fly": "fly_command",
    "skyroute.pipeline.cli_navsim": "navsim_command",
    "skyroute.pipeline.cli_regress": "regress_command",
    "skyroute.pipeline.cli_compare": "compare_command",
    "skyroute.pipeline.cli_diff": "diff_command",
    "skyroute.pipeline.cli_fleet": "fleet_command",
    "skyroute.pipeline.cli_airspace": "airspace_group",
    "skyroute.pipeline.cli_inspect": "inspect_command",
}


def _register_plugins() -> None:
    for mod, attr in _PLUGINS.items():
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name == mod:
                continue
            raise
        cmd = getattr(m, attr, None)
        if isinstance(cmd, click.Command):
            main.add_command(cmd)


_register_plugins()
add_verbosity_options(main)    # every command, the plugins' and the nested groups' ones too


def shown(path) -> Path:
    """Where an output written into the command's staging folder is once the command ends."""
    from skyroute.pipeline.outfolder import shown as _shown

    return _shown(path)


def _folder_summary(*args, **kwargs) -> dict:
    from skyroute.pipeline.outputs import write_folder_summary

    return write_folder_summary(*args, **kwargs)


if __name__ == "__main__":  # pragma: no cover  (last: `python -m skyroute.pipeline.cli` needs the whole module)
    main()

"""One progress display for every long command (issue 35 item 9): -v / -q before or after the
command name, phase lines of the stages, the navsim Monte Carlo and the flight replay on a
forced stream, nothing with -q, a terminal line rewritten in place at a bounded rate."""

from __future__ import annotations

import io
import json
import logging
import time

import click
import numpy as np
import pandas as pd
import pytest
import xarray as xr
from click.testing import CliRunner

from skyroute.pipeline import progress
from skyroute.pipeline.cli import main
from skyroute.pipeline.settings import catalog_dir, load_scenario


@pytest.fixture(autouse=True)
def _reset(monkeypatch):
    monkeypatch.delenv(progress.ENV, raising=False)
    yield
    progress.configure()          # the next test starts with the display off


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def _one_error(res) -> str:
    errors = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in res.output, res.output
    return errors[0]


# ------------------------------------------------------------------ -v / -q before or after
@pytest.mark.parametrize("argv", [["-q", "plan"], ["plan", "-v"], ["-v", "plan", "-q"], ["plan", "-vv", "-q"]])
def test_verbosity_before_or_after_the_command(tmp_path, argv):
    """`skyroute -q plan` and `skyroute plan -v` used to be refused (no such option): now the
    command starts and refuses only the memory budget (before any stage)."""
    res = CliRunner().invoke(main, [*argv, "helsinki-medical", "--max-memory", "1", "--out", str(tmp_path / "o"),
                                    "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 2
    err = _one_error(res)
    assert "--max-memory" in err and "No such option" not in err


def test_every_command_takes_v_and_q():
    def walk(cmd, path):
        yield path, cmd
        for name, sub in getattr(cmd, "commands", {}).items():
            yield from walk(sub, [*path, name])

    for path, cmd in walk(main, []):
        opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
        assert {"-v", "-q"} <= opts, path
    assert "before or after the command name" in CliRunner().invoke(main, ["--help"]).output


def test_group_and_command_options_merge():
    """A command's own `quiet` receives -q given before the command name; -v counts add up."""
    seen = {}

    @click.command("probe-verbosity")
    @click.option("-q", "--quiet", is_flag=True, help="probe")
    def probe(quiet):
        seen.update(quiet=quiet, progress=progress.enabled(), level=logging.getLogger("skyroute").level)
        click.echo(json.dumps({"quiet": quiet}))       # a -q command's JSON on stdout

    main.add_command(probe)
    try:
        r = CliRunner()
        for argv, quiet in ((["-q", "probe-verbosity"], True), (["probe-verbosity", "-q"], True),
                            (["probe-verbosity"], False)):
            res = r.invoke(main, argv)
            assert res.exit_code == 0, res.output
            assert json.loads(res.stdout) == {"quiet": quiet} and seen["quiet"] is quiet
        assert r.invoke(main, ["-v", "probe-verbosity"]).exit_code == 0 and seen["level"] == logging.INFO
        assert r.invoke(main, ["-v", "probe-verbosity", "-v"]).exit_code == 0 and seen["level"] == logging.DEBUG
        # -v without a terminal: progress lines; -q wins over -v
        assert r.invoke(main, ["probe-verbosity", "-v"]).exit_code == 0 and seen["progress"] is True
        assert r.invoke(main, ["-v", "probe-verbosity", "-q"]).exit_code == 0 and seen["progress"] is False
        assert r.invoke(main, ["probe-verbosity"]).exit_code == 0 and seen["progress"] is False   # no terminal
    finally:
        main.commands.pop("probe-verbosity")


# ------------------------------------------------------------------ the display itself
def test_lines_without_a_terminal_and_nothing_when_quiet(monkeypatch):
    buf = io.StringIO()
    assert progress.configure(stream=buf) is False            # not a terminal, no -v: nothing
    with progress.phase("x") as ph:
        ph.update(1, 2)
    assert buf.getvalue() == ""
    assert progress.configure(verbose=1, stream=buf) is True   # -v: one line per phase
    with progress.phase("fly: replay", unit="s simulated") as ph:
        ph.update(30.0, 120.0)
        with progress.phase("plan files"):
            progress.note("plan.html")
    assert buf.getvalue().splitlines() == ["fly: replay > plan files: done in 0.0 s (plan.html)",
                                           "fly: replay: done in 0.0 s (30/120 s simulated)"]
    monkeypatch.setenv(progress.ENV, "1")
    quiet = io.StringIO()
    assert progress.configure(quiet=True, stream=quiet) is False   # -q wins over the environment
    with progress.phase("x"), progress.shown(True), progress.phase("y"):
        pass
    assert quiet.getvalue() == ""


def test_terminal_line_in_place_at_a_bounded_rate():
    tty = _Tty()
    assert progress.configure(stream=tty) is True
    t0 = time.perf_counter()
    with progress.phase("navsim: Monte Carlo", total=100_000, unit="runs") as ph:
        for i in range(100_000):           # updates cost no output: the display polls them
            ph.update(i + 1)
        time.sleep(0.5)
    seconds = time.perf_counter() - t0
    out = tty.getvalue()
    assert "\n" not in out                                # one line, rewritten with \r
    draws = out.count("\r")
    assert 2 <= draws <= 2 * (progress.MAX_RATE_HZ * seconds + 2)   # (a draw and its clear)
    assert "100,000/100,000 runs (100%)" in out
    assert out.endswith("\r")                             # cleared at the end: nothing left on the line
    from skyroute.stages import control

    tty.seek(0)
    tty.truncate()
    with control.progress(True), progress.phase("[9/9] plan") as ph:
        control.note("plan: 2 s elapsed; running: D=2 STEP I (astar) 2 s")   # the planner's notes
        assert ph.detail.startswith("plan: 2 s elapsed")
    assert "\n" not in tty.getvalue()                     # the note is the line's, not a line of its own


def test_stage_phases_count_dask_tasks(monkeypatch):
    import dask.array as da

    monkeypatch.setenv(progress.ENV, "1")
    buf = io.StringIO()
    progress.configure(stream=buf)
    with progress.stage_phases(True, 2) as phases:
        phases.start(1, "surface", "the surface model")
        with progress.dask_tasks():
            total = float(da.ones((40, 40), chunks=10).sum().compute())
        phases.end()
    assert total == 1600.0
    (line,) = buf.getvalue().splitlines()
    assert line.startswith("[1/2] surface: done in ") and " tasks; the surface model)" in line
    with progress.stage_phases(False, 1) as phases:       # run_scenario(progress=False): not shown
        phases.start(1, "plan")
    assert len(buf.getvalue().splitlines()) == 1


# ------------------------------------------------------------------ navsim and fly
def _sky(sc, lon_lat):
    with pytest.warns(UserWarning, match="unhealthy"):
        from skyroute.stages.almanac import sky_geometry

        t0 = pd.Timestamp(sc.mission.start_time_utc)
        return sky_geometry(catalog_dir() / "data" / "yuma_2020-01-03.txt",
                            pd.date_range(t0, periods=3, freq="60s"), lon_lat[1], lon_lat[0])


@pytest.mark.parametrize("quiet", [False, True])
def test_navsim_phases(tmp_path, monkeypatch, quiet):
    """navsim's phases (line of sight, Monte Carlo, protection levels) on a 20 s flown track over
    flat ground, the stages stubbed: lines on a forced stream, nothing with -q."""
    import skyroute.pipeline.navsim as nav
    from skyroute.pipeline.graph import RunResult
    from skyroute.stages.grid import Grid

    sc = load_scenario("helsinki-medical")
    x0, y0 = sc.point_xy(sc.mission.start)
    g = Grid.from_bounds(sc.grid.crs_wkt, x0 - 100, y0 - 100, x0 + 100, y0 + 100, 10.0)
    zero = g.dataarray(np.zeros(g.shape), "terrain", units="m")
    surface = xr.Dataset({"terrain": zero, "surface": zero.rename("surface")})
    result = RunResult(sc, {"surface": surface, "satellites": _sky(sc, g.to_lonlat(x0, y0))})
    monkeypatch.setattr(nav, "run_scenario", lambda *a, **k: result)
    flown = tmp_path / "flown.csv"
    t = np.arange(0.0, 20.01, 0.5)
    flown.write_text("t_s,x_m,y_m,z_m\n" + "".join(f"{s},{x0 + 2 * s},{y0},{40.0}\n" for s in t))
    monkeypatch.setenv(progress.ENV, "1")
    buf = io.StringIO()
    progress.configure(quiet=quiet, stream=buf)
    r = nav.navsim_scenario(sc, runs=3, seed=1, trajectory=flown, progress=progress.wanted())
    assert r.ds.sizes["run"] == 3
    lines = buf.getvalue().splitlines()
    if quiet:
        assert lines == []
        return
    assert [ln.split(": done")[0] for ln in lines] == ["navsim: line of sight", "navsim: Monte Carlo",
                                                       "navsim: protection levels"]
    n = r.ds.sizes["time"]
    assert f"(3 runs x {n:,} epochs, 2 filters)" in lines[1]


def test_replay_reports_simulated_time():
    """The replay calls its progress hook at each event with the mission time and the flight's
    end; fly's phase shows them as seconds simulated of the flight."""
    from test_tactical_replay import CHAIN, START, VEH, X0, Y0, grid, world

    from skyroute.stages.almanac import sky_geometry
    from skyroute.stages.planning.deconflict import Step2Result, chain_timing
    from skyroute.stages.planning.problem import build_problem
    from skyroute.stages.planning.step3 import step3
    from skyroute.stages.tactical.log import NoFlyZone
    from skyroute.stages.tactical.replay import FlyParams, TacticalEvent, replay

    g = grid()
    lon, lat = g.to_lonlat(float(CHAIN[1][0]), float(CHAIN[1][1]))
    with pytest.warns(UserWarning, match="unhealthy"):
        sky = sky_geometry(catalog_dir() / "data" / "yuma_2020-01-03.txt",
                           pd.date_range(START, periods=5, freq="60s"), lat, lon)
    w = world(sky)
    prob = build_problem(w.surface, w.clearance["min_altitude_m"], None, None, None, None, VEH, (1, 0, 0, 1),
                         tuple(CHAIN[0]), tuple(CHAIN[-1]), 0.0, 80.0)
    t, e, _ = chain_timing(prob, CHAIN)
    cand = step3(prob, Step2Result(CHAIN, t, e, "unchanged"), sky, w.surface["surface"].values, start_time_utc=START)
    t0 = float(cand.t_s[0])
    far = NoFlyZone("far", np.array([[0, 0], [10, 0], [10, 10.0]]) + [X0, Y0], -1.0, 200.0, 0.0, 1.0)  # no conflict
    events = [TacticalEvent(s, "nofly", f"zone {s:g}", zone=far) for s in (10.0, 30.0, 50.0)]
    buf = io.StringIO()
    progress.configure(verbose=1, stream=buf)
    seen = []
    with progress.phase("fly: replay", unit="s simulated") as ph:
        def hook(t_s, t_end_s):
            seen.append((t_s, t_end_s))
            ph.update(t_s - t0, t_end_s - t0)

        log = replay(cand.trajectory, t0, goal_xyz=CHAIN[-1], world=w, world_at=lambda s: w, events=events,
                     strategic_intruders=[], vehicle=VEH, params=FlyParams(), start_time_utc=START,
                     dop_threshold=None, scenario="synthetic", progress=hook)
    assert log.outcome == "goal"
    end = t0 + cand.trajectory.duration_s
    assert [s for s, _ in seen] == [10.0, 30.0, 50.0, end] and all(abs(e - end) < 1e-6 for _, e in seen)
    (line,) = buf.getvalue().splitlines()
    assert line.startswith("fly: replay: done in ") and f"({end - t0:.1f} s simulated)" in line   # 83.3 s

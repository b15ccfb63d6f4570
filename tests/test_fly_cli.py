"""``skyroute fly`` refuses bad input with one ``error:`` line (exit 2) before any stage runs."""

from __future__ import annotations

from click.testing import CliRunner

from skyroute.pipeline.cli import main


def _fly(tmp_path, *args):
    cache = tmp_path / "cache"
    res = CliRunner().invoke(main, ["fly", *args, "--out", str(tmp_path / "out"), "--cache-dir", str(cache)])
    ran = cache.is_dir() and any((cache / "stages").glob("*")) if (cache / "stages").exists() else False
    return res, ran


def test_scenario_without_events(tmp_path):
    res, ran = _fly(tmp_path, "helsinki-medical")
    assert res.exit_code == 2 and not ran
    assert "error: scenario 'helsinki-medical' has no events" in res.output and "--events FILE" in res.output


def test_bad_replanning_timeout(tmp_path):
    res, ran = _fly(tmp_path, "helsinki-tactical", "--t-rep", "0")
    assert res.exit_code == 2 and not ran
    assert res.output.startswith("error:") and "t_rep_s" in res.output


def test_bad_events_file_names_the_file(tmp_path):
    f = tmp_path / "ev.yaml"
    f.write_text("events:\n  - {t_s: 5, kind: fog}\n")
    res, ran = _fly(tmp_path, "helsinki-medical", "--events", str(f))
    assert res.exit_code == 2 and not ran
    assert "ev.yaml" in res.output and "unknown kind 'fog'" in res.output
    assert "Traceback" not in res.output


def test_navsim_bad_trajectory_file(tmp_path):
    bad = tmp_path / "flown.csv"
    bad.write_text("a,b\n1,2\n")
    cache = tmp_path / "cache"
    res = CliRunner().invoke(main, ["navsim", "helsinki-medical", "--trajectory", str(bad), "--out",
                                    str(tmp_path / "o"), "--cache-dir", str(cache)])
    assert res.exit_code == 2 and res.output.startswith("error: --trajectory") and "t_s, x_m, y_m" in res.output
    assert not (cache / "stages").exists()


def test_protection_level_budgets_from_the_scenario():
    """navsim.pl_p_hmi / pl_p_fa / pl_p_sat set the protection level's budgets; the defaults
    are the documented IntegrityBudget."""
    from skyroute.pipeline.navsim import integrity_budget
    from skyroute.pipeline.settings import NavsimSettings, load_scenario
    from skyroute.stages.integrity import IntegrityBudget

    sc = load_scenario("helsinki-medical")
    assert integrity_budget(sc) == IntegrityBudget()
    sc = sc.model_copy(update={"navsim": NavsimSettings(pl_p_hmi=1e-5, pl_p_fa=1e-4, pl_p_sat=1e-4)})
    b = integrity_budget(sc)
    assert (b.p_hmi_hor, b.p_hmi_vert, b.p_fa_hor, b.p_fa_vert, b.p_sat) == (5e-6, 5e-6, 5e-5, 5e-5, 1e-4)

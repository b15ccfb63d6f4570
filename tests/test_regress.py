"""``skyroute regress`` (issue 16): golden comparison with physical tolerances, the packaged
goldens cover the catalog, and an end-to-end run: --update writes goldens, a warm rerun
recomputes nothing and passes, a golden moved beyond its tolerance fails with exit 1."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from skyroute.pipeline.cli import main
from skyroute.pipeline.regress import (
    GOLDEN_SCHEMA,
    compare_figures,
    golden_dir,
    read_golden,
    tolerance_of,
)
from skyroute.pipeline.settings import scenario_paths


def test_tolerances_by_unit():
    assert tolerance_of("plan.f_m") == 0.5
    assert tolerance_of("fly.closest.tac-1_m") == 0.5
    assert tolerance_of("plan.energy_Wh") == 0.05
    assert tolerance_of("plan.flight_time_s") == 0.5
    assert tolerance_of("navsim.containment.weak.3sigma") == 0.02
    assert tolerance_of("navsim.proposed_smaller_share") == 0.02
    assert tolerance_of("plan.dop_threshold") == 0.0
    assert tolerance_of("plan.label") is None and tolerance_of("fly.n_replannings") is None


def test_compare_pass_fail_new_gone():
    golden = {"plan.f_m": 100.0, "plan.label": "D=2", "plan.energy_Wh": 10.0, "fly.outcome": "goal", "old_m": 1.0}
    figs = {"plan.f_m": 100.5, "plan.label": "D=2", "plan.energy_Wh": 10.06, "fly.outcome": "landed", "new_m": 2.0}
    st = {c.name: c.status for c in compare_figures("x", figs, golden)}
    assert st == {"plan.f_m": "pass", "plan.label": "pass", "plan.energy_Wh": "fail", "fly.outcome": "fail",
                  "old_m": "gone", "new_m": "new"}
    assert {c.status for c in compare_figures("x", figs, None)} == {"new"}
    # None (no plan) only equals None
    assert compare_figures("x", {"plan.f_m": None}, {"plan.f_m": 1.0})[0].status == "fail"
    assert compare_figures("x", {"plan.f_m": None}, {"plan.f_m": None})[0].status == "pass"


def test_packaged_goldens_cover_the_catalog():
    for name in scenario_paths():
        figs = read_golden(golden_dir(), name)
        assert figs is not None, f"no golden for {name}: run `skyroute regress --update {name}`"
        assert figs["plan.status"] in ("flyable", "no_flyable_plan")
        doc = json.loads((golden_dir() / f"{name}.json").read_text())
        assert doc["schema_version"] == GOLDEN_SCHEMA
        assert all(doc["tolerances"][k] == tolerance_of(k) for k in figs)


def test_bad_golden_file_is_one_error_line(tmp_path):
    (tmp_path / "helsinki-medical.json").write_text("{not json")
    res = CliRunner().invoke(main, ["regress", "helsinki-medical", "--golden-dir", str(tmp_path),
                                    "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 2 and res.output.startswith("error: golden file") and "--update" in res.output
    res = CliRunner().invoke(main, ["regress", "nowhere-city", "--cache-dir", str(tmp_path / "c")])
    assert res.exit_code == 2 and "unknown scenario" in res.output


@pytest.mark.slow
def test_regress_end_to_end(tmp_path):
    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.regress import regress

    gold, cache = tmp_path / "golden", Cache(tmp_path / "cache")
    first = regress(["helsinki-medical"], cache=cache, golden=gold, update=True)
    figs = first.figures["helsinki-medical"]
    assert figs["plan.status"] == "flyable" and "navsim.containment.proposed.3sigma" in figs
    # the packaged golden agrees with a fresh cold run (within its tolerances)
    packaged = read_golden(golden_dir(), "helsinki-medical")
    assert [c for c in compare_figures("helsinki-medical", figs, packaged) if c.status != "pass"] == []
    # warm: every stage from the cache, navsim figures from the memo, all pass
    warm = regress(["helsinki-medical"], cache=cache, golden=gold)
    info = warm.info["helsinki-medical"]
    assert info["stage_hits"] == info["stages"] and info["navsim_memo"] is True
    assert warm.counts()["pass"] == len(figs) and not warm.failed
    # a golden moved beyond its tolerance fails (exit 1) and names the figure
    doc = json.loads((gold / "helsinki-medical.json").read_text())
    doc["figures"]["plan.length_m"] += 0.6
    (gold / "helsinki-medical.json").write_text(json.dumps(doc))
    res = CliRunner().invoke(main, ["regress", "helsinki-medical", "--golden-dir", str(gold),
                                    "--cache-dir", str(cache.root)])
    assert res.exit_code == 1, res.output
    assert "plan.length_m" in res.output and "fail" in res.output and "1 fail" in res.output
    # `skyroute compare` on the same cache: the astar row is the cached plan, its clearance the
    # brute-force distance over every cell (no skyroute code), and an unknown planner is refused
    res = CliRunner().invoke(main, ["compare", "helsinki-medical", "--planners", "astar", "--out",
                                    str(tmp_path / "cmp"), "--cache-dir", str(cache.root), "-q"])
    assert res.exit_code == 0, res.output
    import csv

    import numpy as np

    from skyroute.pipeline.compare import compare_planners
    from skyroute.pipeline.settings import load_scenario
    from skyroute.stages.vehicle import load_vehicle

    (row,) = list(csv.DictReader((tmp_path / "cmp" / "compare.csv").open()))
    assert row["flyable"] == "true" and abs(float(row["f_m"]) - figs["plan.f_m"]) < 1e-3
    assert abs(float(row["length_m"]) - figs["plan.length_m"]) < 1e-3
    sc = load_scenario("helsinki-medical")
    rows, maps = compare_planners(sc, ["astar"], cache=cache)
    # compute_s is the plan stage's wall time (not a sum over the levels, which run in parallel
    # and share solutions), and the row says the plan came from the cache
    from skyroute.pipeline.runner import run_scenario

    plan_ds = run_scenario(sc, cache=cache, targets=["plan"])["plan"]
    assert float(row["compute_s"]) == pytest.approx(float(plan_ds.attrs["compute_s"]), abs=1e-3)
    assert float(row["compute_s"]) <= float(np.nansum(plan_ds["compute_time_s"].values)) + 1e-3
    assert row["plan_cached"] == "true" and rows[0].values["plan_cached"] is True
    surf = maps["surface"]["surface"]
    x, y, s = surf["x"].values, surf["y"].values, np.asarray(surf.values, float)
    h = abs(x[1] - x[0]) / 2
    d = []
    for px, py, pz in rows[0].xyz_m[::4]:
        dx = np.maximum(np.abs(px - x) - h, 0)[None, :]
        dy = np.maximum(np.abs(py - y) - h, 0)[:, None]
        d.append(np.sqrt(dx**2 + dy**2 + np.maximum(pz - s, 0) ** 2).min())
    assert min(d) >= float(row["min_clearance_m"]) - 1e-6
    assert float(row["min_clearance_m"]) >= load_vehicle(sc.vehicle).r_p_m - 1e-6
    # its report: the compare.csv table and the figure, self-contained
    from skyroute.pipeline.report import build_report

    page = build_report(tmp_path / "cmp").read_text()
    assert "<h2>Planners compared</h2>" in page and "data:image/png;base64," in page
    assert f"<td>{row['f_m']}</td>" in page and f"<td>{row['min_clearance_m']}</td>" in page
    bad = CliRunner().invoke(main, ["compare", "helsinki-medical", "--planners", "astar,warp-drive",
                                    "--out", str(tmp_path / "cmp2"), "--cache-dir", str(cache.root)])
    assert bad.exit_code == 2 and "unknown planner(s) warp-drive" in bad.output

"""`skyroute fly` on a fixed-wing scenario end to end (seed 002's local planner; the unit
tests are in tests/test_fw_local.py)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from skyroute.pipeline.cli import main


@pytest.mark.slow
def test_fly_fixed_wing_scenario_end_to_end(tmp_path):
    """`skyroute fly san-gabriel-fixedwing-local`: the balloon is climbed over (r_p kept, brute
    force vs its box), the head-on intruder makes the ownship fly the escape with the largest
    predicted separation (issue 22), outputs written."""
    import json
    import math

    from shapely.geometry import Point, Polygon

    from skyroute.stages.vehicle import load_vehicle

    def prism_distance(poly, z_top, p):
        return math.hypot(poly.distance(Point(p[0], p[1])), max(p[2] - z_top, 0.0))

    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["fly", "san-gabriel-fixedwing-local", "--out", str(out), "--cache-dir",
                                  str(tmp_path / "cache"), "-q"])
    assert r.exit_code == 0, r.output
    sec = json.loads((out / "summary.json").read_text())["fly"]
    loc = sec["local_planner"]
    assert sec["tactical_method"] == "local" and sec["outcome"] == "goal"
    climb, esc = loc["manoeuvres"]
    assert climb["kind"] == "climb" and esc["kind"] == max(esc["options"], key=lambda k: esc["options"][k])
    (obs,) = loc["obstacles"]
    poly = Polygon(obs["polygon_xy"])
    rows = np.genfromtxt(out / "flown.csv", delimiter=",", names=True, dtype=None, encoding=None)
    t = rows["t_s"].astype(float)
    x = np.column_stack([rows["x_m"], rows["y_m"], rows["z_m"]]).astype(float)
    tq = np.arange(t[0], t[-1], 0.05)
    q = np.column_stack([np.interp(tq, t, x[:, k]) for k in range(3)])
    assert min(prism_distance(poly, obs["z_top_m"], qq) for qq in q) >= load_vehicle("skywalker-x8").r_p_m
    assert sec["min_separation"][0]["clearance_m"] > 0
    for f in ("tactical.csv", "flown.geojson", "fly_top.png", "fly_profile.png"):
        assert (out / f).exists()

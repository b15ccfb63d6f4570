"""Surface stage on rotterdam-canyon (853 LoD2 buildings, 1 m grid): the conservative face-over-cell
rasteriser against the previous centre/corner sampler (``stages/surface.py`` at commit
b8fb3b5, loaded from git in the same run), and what the conservative bound costs in altitude.

    NUMBA_NUM_THREADS=1 python benchmarks/bench_surface.py
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from skyroute.pipeline.settings import load_scenario
from skyroute.stages import surface as new

BASELINE_COMMIT = "b8fb3b5"
REPO = Path(__file__).resolve().parents[1]


def load_baseline():
    try:
        src = subprocess.run(["git", "-C", str(REPO), "show", f"{BASELINE_COMMIT}:stages/surface.py"],
                             check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        sys.exit(f"error: cannot read the baseline from git ({exc}); run inside the repository")
    path = Path(tempfile.mkdtemp()) / "surface_baseline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("surface_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["surface_baseline"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    old = load_baseline()
    sc = load_scenario("rotterdam-canyon")
    kw = dict(buildings_path=sc.data.buildings.path, buildings_format="cityjson")
    for m in (old, new):
        m.build_surface(sc.grid, **kw)  # compile / warm up
    times = {"baseline": [], "conservative": []}
    for _ in range(5):  # interleaved, so both see the same machine load
        for name, m in (("baseline", old), ("conservative", new)):
            t = time.perf_counter()
            ds = m.build_surface(sc.grid, **kw)
            times[name].append(time.perf_counter() - t)
            if name == "baseline":
                s_old, t_old_ds, b_old = (ds[v].values.astype(np.float64) for v in ("surface", "terrain", "building_id"))
            else:
                s_new, t_new_ds, b_new = (ds[v].values.astype(np.float64) for v in ("surface", "terrain", "building_id"))
    t_old, t_new = np.median(times["baseline"]), np.median(times["conservative"])
    print(f"rotterdam-canyon surface stage, {sc.grid.nx} x {sc.grid.ny} cells of {sc.grid.resolution_m} m, median of 5")
    print(f"  baseline (centre/corner sampling): {t_old:.3f} s")
    print(f"  conservative (face-over-cell max): {t_new:.3f} s")
    print(f"  ratio conservative / baseline:     {t_new / t_old:.2f}x")
    # the rooftop rasteriser alone
    for name, m in (("baseline", old), ("conservative", new)):
        ts = []
        for _ in range(5):
            t = time.perf_counter()
            m.cityjson_buildings(sc.data.buildings.path, sc.grid)
            ts.append(time.perf_counter() - t)
        print(f"  cityjson_buildings {name}: {np.median(ts):.3f} s")
    d = s_new - s_old
    print("altitude cost of the conservative surface (new - old) [m]:")
    print(f"  all cells: mean {d.mean():.3f}, p99 {np.percentile(d, 99):.3f}, max {d.max():.3f}, "
          f"cells raised {np.mean(d > 1e-6) * 100:.1f} %, cells lowered {np.mean(d < -1e-6) * 100:.2f} % "
          f"(min {d.min():.3f})")
    roof = (b_old >= 0) | (b_new >= 0)
    for label, sel in (("building cells", roof), ("ground cells", ~roof)):
        x = d[sel]
        print(f"  {label} ({sel.mean() * 100:.0f} %): mean {x.mean():.3f}, p99 {np.percentile(x, 99):.3f}, "
              f"min {x.min():.3f}")
    dt = t_new_ds - t_old_ds
    print(f"  terrain: mean {dt.mean():.3f}, p1 {np.percentile(dt, 1):.3f}, p99 {np.percentile(dt, 99):.3f}")


if __name__ == "__main__":
    main()

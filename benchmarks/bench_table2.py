"""Seed 000 Table II in structure: one plan per single-term weight set on real maps.

    python benchmarks/bench_table2.py                          # the three cities
    python benchmarks/bench_table2.py --cases helsinki-medical --cache /tmp/perf-cache
    python benchmarks/bench_table2.py --plan-times helsinki-medical,helsinki-traffic,monaco-helipads,\
        rotterdam-canyon,san-gabriel-mountains         # plan stage time per shipped scenario

For each scenario and each weight set (1,0,0,0), (0,1,0,0), (0,0,1,0), (0,0,0,1) the whole
strategic plan (every GNSS level, STEP I-III, the scenario's planner) runs on the cached maps
and the chosen trajectory's eq. 15 terms C_l, C_r, C_d, C_e [m], energy [Wh] and flight time
[s] form one row of a 4 x 4 (+2) matrix.  Seed 000's claim, checked here: each single-term
plan is flyable and has the lowest value of its own term among the four plans ("diag ok":
within 2 % of the column minimum).  The last column is the plan stage's wall time [s]
(maps cached, numba kernels warm: the first plan of the process is an untimed warm-up).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_planner import case_inputs, run_plan  # noqa: E402

from skyroute.pipeline.cache import Cache  # noqa: E402

WEIGHT_SETS = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
TERMS = ("C_l", "C_r", "C_d", "C_e")
SLACK = 0.02


def table2(d: dict, s) -> tuple[np.ndarray, list[str], list[float]]:
    """Rows (4, 6): C_l, C_r, C_d, C_e [m], energy [Wh], flight time [s] of the chosen plan of
    each single-term weight set (NaN when no plan is flyable); the reasons; plan times [s]."""
    rows, why, secs = [], [], []
    for w in WEIGHT_SETS:
        plan, t = run_plan(d, s, weights=w, battery_reserve_pct=s.battery_reserve_pct)
        c = plan.chosen
        secs.append(t)
        if c is None:
            rows.append([np.nan] * 6)
            why.append(plan.reason)
        else:
            rows.append([c.C_l, c.C_r, c.C_d, c.C_e, c.energy_Wh, c.flight_time_s])
            why.append("")
    return np.array(rows), why, secs


def diagonal_ok(m: np.ndarray, slack: float = SLACK) -> list[bool]:
    """For each term j: plan j is flyable and its C_j <= (1 + slack) x the smallest C_j."""
    return [bool(np.isfinite(m[j, j]) and m[j, j] <= (1 + slack) * np.nanmin(m[:, j])) for j in range(4)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="helsinki-medical,monaco-helipads,rotterdam-canyon")
    ap.add_argument("--cache", default="/tmp/perf-cache", help="pipeline cache folder of the maps")
    ap.add_argument("--plan-times", default="", help="comma-separated scenarios: only time their plan stage "
                    "with the scenario's own settings (e.g. every catalog scenario)")
    a = ap.parse_args()
    cache = Cache(a.cache)
    if a.plan_times:
        plan_times(a.plan_times.split(","), cache)
        return
    warm = False
    for name in a.cases.split(","):
        sc, d, s, prep = case_inputs(name, cache)
        if not warm:
            run_plan(d, s, planner=s.planner)
            warm = True
        t0 = time.perf_counter()
        m, why, secs = table2(d, s)
        ok = diagonal_ok(m)
        print(f"\n# {name} (planner {s.planner}; maps in {prep:.1f} s; 4 plans in {time.perf_counter() - t0:.1f} s)")
        print(f"{'weights':>10} " + " ".join(f"{k + ' [m]':>10}" for k in TERMS)
              + f" {'energy_Wh':>10} {'flight_s':>9} {'plan_s':>7}")
        for w, r, sec in zip(WEIGHT_SETS, m, secs, strict=True):
            lab = ",".join(f"{x:g}" for x in w)
            print(f"{lab:>10} " + " ".join(f"{v:10.1f}" for v in r[:4]) + f" {r[4]:10.2f} {r[5]:9.1f} {sec:7.2f}")
        print("diag ok (own term lowest within 2 %): " + ", ".join(f"{k}={o}" for k, o in zip(TERMS, ok, strict=True)))
        for w, y in zip(WEIGHT_SETS, why, strict=True):
            if y:
                print(f"  no flyable plan for weights {w}: {y}")
        ratio = m[:, 1:4] / m[:, :1]            # C_x / C_l: constant when the map is uniform
        spread = np.nanmax(ratio, axis=0) / np.nanmin(ratio, axis=0) - 1
        flat = [k for k, sp in zip(TERMS[1:], spread, strict=True) if sp < 1e-6]
        if flat:
            print(f"  degenerate term(s) on this scenario (C_x / C_l the same in every plan: a uniform map): "
                  f"{', '.join(flat)}")


def plan_times(names: list[str], cache: Cache) -> None:
    """Wall time of the plan stage (maps cached, kernels warm) with each scenario's settings."""
    print(f"{'scenario':>24} {'maps_s':>7} {'plan_s':>7} {'flyable':>8} {'label':>6} {'f [m]':>9} {'energy_Wh':>10}")
    warm = False
    for name in names:
        sc, d, s, prep = case_inputs(name, cache)
        if not warm:
            run_plan(d, s)
            warm = True
        plan, t = run_plan(d, s, battery_reserve_pct=s.battery_reserve_pct)
        c = plan.chosen
        print(f"{name:>24} {prep:7.1f} {t:7.2f} {str(c is not None):>8} {c.label if c else '-':>6} "
              f"{c.f if c else float('nan'):9.1f} {c.energy_Wh if c else float('nan'):10.2f}"
              + ("" if c else f"  {plan.reason}"), flush=True)


if __name__ == "__main__":
    main()

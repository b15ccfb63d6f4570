"""Cold vs warm run of a scenario's whole pipeline (issue: warm < 20 % of cold).

    python benchmarks/bench_pipeline.py [SCENARIO] [--repeat N]

Runs the pipeline in a fresh temporary cache (cold: every stage computed), then again on the
same cache (warm: every stage read from zarr), in the same process and as `skyroute run`
subprocesses, and prints the per-stage times and the warm/cold ratios.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

from skyroute.pipeline.cache import Cache
from skyroute.pipeline.runner import run_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="helsinki-medical")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        cache = Cache(Path(tmp) / "c")
        cold = run_scenario(args.scenario, cache=cache)
        warm = min((run_scenario(args.scenario, cache=cache) for _ in range(args.repeat)), key=lambda r: r.seconds)
        print(f"{'stage':12s} {'cold [s]':>9s} {'warm [s]':>9s}")
        for c, w in zip(cold.records, warm.records, strict=True):
            print(f"{c.name:12s} {c.seconds:9.3f} {w.seconds:9.3f}")
        print(f"{'pipeline':12s} {cold.seconds:9.3f} {warm.seconds:9.3f}   warm/cold = {warm.seconds / cold.seconds:.3f}")
        # the CLI main job as a user runs it (includes interpreter start-up and output writing)
        exe = [sys.executable, "-m", "skyroute.pipeline.cli", "run", args.scenario, "--cache-dir",
               str(Path(tmp) / "cli"), "--out", str(Path(tmp) / "out"), "-q"]
        t0 = time.perf_counter()
        subprocess.run(exe, check=True, capture_output=True)
        t_cold = time.perf_counter() - t0
        t_warm = min(_timed(exe) for _ in range(args.repeat))
        print(f"{'skyroute run':12s} {t_cold:9.3f} {t_warm:9.3f}   warm/cold = {t_warm / t_cold:.3f}")


def _timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()

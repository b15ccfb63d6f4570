"""Fuzz the front door (issue 27): thousands of mutated scenario, vehicle, events and fleet files
and hostile CLI option values (tests/_fuzz_inputs.py), each run through the CLI in-process with
``--max-memory 1`` (a request passing every check is refused by the memory estimate, before any
stage runs).  Reports the counts per exit code and per kind, the slowest case, and every
distinct uncaught exception (a traceback) with one reproducing case.  Exit code 1 when any case
ended in a traceback or took longer than --max-seconds.

    python benchmarks/fuzz_inputs.py --cases 3000 --seed 0
"""

from __future__ import annotations

import argparse
import collections
import random
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _fuzz_inputs import KINDS, Base, build_case, run_case, short  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-seconds", type=float, default=10.0, help="a case slower than this counts as a hang")
    ap.add_argument("--kind", choices=KINDS, default=None, help="only this kind of mutation")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rnd = random.Random(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="skyroute-fuzz-"))
    base = Base.make(tmp / "base")
    codes: collections.Counter = collections.Counter()
    by_kind: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    failures: dict[str, str] = {}
    slow: list[tuple[float, str]] = []
    multi_error = 0
    t0 = time.perf_counter()
    try:
        for i in range(args.cases):
            case_dir = tmp / f"c{i % 4}"
            shutil.rmtree(case_dir, ignore_errors=True)
            argv_, desc = build_case(base, rnd, args.kind, case_dir)
            out = run_case(argv_)
            kind = desc.split(":")[0]
            label = "traceback" if out.traceback else f"exit {out.exit_code}"
            if out.exit_code == 2 and out.memory_refusal:
                label = "exit 2 (memory estimate)"   # passed every check: refused by --max-memory 1
            codes[label] += 1
            by_kind[kind][label] += 1
            if out.exit_code == 2 and out.traceback is None and out.error_lines != 1 and not kind.startswith("fleet"):
                multi_error += 1     # exit 2 without exactly one `error:` line (a fleet file: one per problem)
            if out.traceback:
                failures.setdefault(short(out.traceback), f"{desc}\n    argv: {argv_}")
            if out.seconds > args.max_seconds:
                slow.append((out.seconds, desc))
            if (i + 1) % 500 == 0:
                print(f"  {i + 1} cases, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    total = time.perf_counter() - t0
    print(f"{args.cases} cases in {total:.1f} s ({1000 * total / max(1, args.cases):.0f} ms a case), seed {args.seed}")
    for label, n in sorted(codes.items()):
        print(f"  {label:10s} {n:6d}")
    print("by kind:")
    for kind in sorted(by_kind):
        print(f"  {kind:14s} " + ", ".join(f"{lab} {n}" for lab, n in sorted(by_kind[kind].items())))
    print(f"exit 2 without exactly one error: line (fleet files excepted: one line per problem): {multi_error}")
    print(f"slower than {args.max_seconds:g} s: {len(slow)}" + (f" (slowest {max(slow)[0]:.1f} s: {max(slow)[1]})" if slow else ""))
    print(f"distinct tracebacks: {len(failures)}")
    for exc, case in failures.items():
        print(f"  {exc}\n    {case}")
    return 1 if failures or slow else 0


if __name__ == "__main__":
    sys.exit(main())

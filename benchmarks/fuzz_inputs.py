"""Fuzz the front door (issue 27) and the data readers (issue 34): thousands of mutated scenario,
vehicle, events and fleet files and hostile CLI option values (tests/_fuzz_inputs.py), each run
through the CLI in-process with ``--max-memory 1`` (a request passing every check is refused by
the memory estimate, before any stage runs), and hostile DATA files of eight families
(tests/_fuzz_files.py: rasters, CityJSON, OSM, NetCDF wind, almanacs, events numbers, airspace
files, pre-filled --out folders), each run through the command that reads it.  Reports the
counts per exit code, per family (kind), the slowest case, the rule violations (exit code,
``error:`` lines, the --out folder property) and every distinct uncaught exception (a traceback)
with one reproducing case.  Exit code 1 when any case ended in a traceback, broke a rule or took
longer than --max-seconds.

    python benchmarks/fuzz_inputs.py --cases 3000 --seed 0
    python benchmarks/fuzz_inputs.py --cases 300 --kind raster        # one family
    python benchmarks/fuzz_inputs.py --cases 300 --kind files         # every data-file family

A guard on the address space (--max-vm, default 6G: RLIMIT_AS) turns a runaway allocation into a
MemoryError (a reported traceback) instead of taking the machine down; the mutations known to
allocate tens of GB today (tests/_fuzz_files.py UNSAFE_OPS) run only with --unsafe.
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

from _fuzz_files import (  # noqa: E402
    FILE_KINDS,
    OPS,
    SLOW_OPS,
    UNSAFE_OPS,
    FileBase,
    build_file_case,
    run_file_case,
)
from _fuzz_inputs import KINDS, Base, build_case, run_case, short  # noqa: E402


def _size(text: str) -> int:
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
    t = text.strip().upper().rstrip("B")
    return int(float(t[:-1]) * units[t[-1]]) if t and t[-1] in units else int(t)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-seconds", type=float, default=10.0, help="a case slower than this counts as a hang")
    ap.add_argument("--kind", choices=(*KINDS, *FILE_KINDS, "front", "files"), default=None,
                    help="only this kind (family) of mutation; 'front': the front-door kinds, 'files': the "
                         "data-file families (default: all)")
    ap.add_argument("--max-vm", default="6G", help="address-space limit of this process (RLIMIT_AS), e.g. 6G; 0: none")
    ap.add_argument("--unsafe", action="store_true", help="also the mutations known to allocate tens of GB today")
    ap.add_argument("--no-slow", action="store_true", help="skip the mutations known to take tens of seconds")
    ap.add_argument("--repro", metavar="KIND:OP:SEED", default=None,
                    help="build this one data-file case (as printed) in --keep and run it, showing its output")
    ap.add_argument("--keep", type=Path, default=Path("fuzz-repro"), help="folder of --repro's files")
    args = ap.parse_args(argv)
    if args.repro:
        from click.testing import CliRunner

        from skyroute.pipeline.cli import main as cli_main

        kind, op, seed = args.repro.rsplit(":", 2)
        fb = FileBase.make(args.keep.resolve() / "base")
        case = build_file_case(fb, random.Random(int(seed)), kind, args.keep.resolve() / "case", op, unsafe=True)
        print(case.desc, "\n  skyroute", " ".join(case.argv))
        res = CliRunner().invoke(cli_main, case.argv)
        print(res.output, f"exit {res.exit_code}", sep="")
        if res.exception is not None and not isinstance(res.exception, SystemExit):
            import traceback

            traceback.print_exception(res.exception)
        return 0
    warnings.simplefilter("ignore")
    if _size(args.max_vm) > 0:
        import resource

        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        resource.setrlimit(resource.RLIMIT_AS, (_size(args.max_vm), hard))
    kinds = {None: (*KINDS, *FILE_KINDS), "front": KINDS, "files": FILE_KINDS}.get(args.kind, (args.kind,))
    rnd = random.Random(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="skyroute-fuzz-"))
    base = Base.make(tmp / "base")
    fbase = FileBase.make(tmp / "files") if set(kinds) & set(FILE_KINDS) else None
    codes: collections.Counter = collections.Counter()
    by_kind: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    failures: dict[str, str] = {}
    violations: dict[str, str] = {}
    slow: list[tuple[float, str]] = []
    slowest: tuple[float, str] = (0.0, "")
    multi_error = 0
    t0 = time.perf_counter()
    try:
        for i in range(args.cases):
            case_dir = tmp / f"c{i % 4}"
            shutil.rmtree(case_dir, ignore_errors=True)
            kind = rnd.choice(kinds)
            if kind in FILE_KINDS:
                ops = [o for o in OPS[kind] if (args.unsafe or (kind, o) not in UNSAFE_OPS)
                       and not (args.no_slow and (kind, o) in SLOW_OPS)]
                op, seed = rnd.choice(ops), rnd.getrandbits(32)
                case = build_file_case(fbase, random.Random(seed), kind, case_dir, op, unsafe=args.unsafe)
                argv_, desc = case.argv, f"{case.desc}\n    --repro {kind}:{op}:{seed}"
                out, problems = run_file_case(case)
            else:
                argv_, desc = build_case(base, rnd, kind, case_dir)
                out, problems = run_case(argv_), []
            label = "traceback" if out.traceback else f"exit {out.exit_code}"
            if out.exit_code == 2 and out.memory_refusal:
                label = "exit 2 (memory estimate)"   # passed every check: refused by --max-memory 1
            codes[label] += 1
            by_kind[kind][label] += 1
            if kind in KINDS and out.exit_code == 2 and out.traceback is None and out.error_lines != 1 \
                    and not kind.startswith("fleet"):
                multi_error += 1     # exit 2 without exactly one `error:` line (a fleet file: one per problem)
            for prob in problems:
                by_kind[kind]["rule broken"] += 1
                violations.setdefault(f"{kind}: {prob.split(':')[0][:80]}", f"{prob[:300]}\n    {desc}\n    argv: {argv_}")
            if out.traceback:
                failures.setdefault(short(out.traceback), f"{desc}\n    argv: {argv_}")
            if out.seconds > args.max_seconds:
                slow.append((out.seconds, desc))
            if out.seconds > slowest[0]:
                slowest = (out.seconds, f"{desc}\n    argv: {argv_}")
            if (i + 1) % 500 == 0:
                print(f"  {i + 1} cases, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    total = time.perf_counter() - t0
    print(f"{args.cases} cases in {total:.1f} s ({1000 * total / max(1, args.cases):.0f} ms a case), seed {args.seed}")
    for label, n in sorted(codes.items()):
        print(f"  {label:10s} {n:6d}")
    print("by family (kind):")
    for kind in sorted(by_kind):
        print(f"  {kind:14s} " + ", ".join(f"{lab} {n}" for lab, n in sorted(by_kind[kind].items())))
    print(f"front door: exit 2 without exactly one error: line (fleet files excepted: one line per problem): "
          f"{multi_error}")
    print(f"slowest case: {slowest[0]:.2f} s: {slowest[1]}")
    print(f"slower than {args.max_seconds:g} s: {len(slow)}")
    for sec, desc in sorted(slow, reverse=True)[:10]:
        print(f"  {sec:.1f} s: {desc}")
    print(f"distinct rule violations (data files: exit code, error: lines, --out property): {len(violations)}")
    for what, case in violations.items():
        print(f"  {what}\n    {case}")
    print(f"distinct tracebacks: {len(failures)}")
    for exc, case in failures.items():
        print(f"  {exc}\n    {case}")
    return 1 if failures or slow or violations else 0


if __name__ == "__main__":
    sys.exit(main())

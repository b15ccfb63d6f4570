"""The parallel fleet driver on real `dask worker` processes (issue 26 item 3): a small fleet of
short missions spread over helsinki-medical is decided exactly as the sequential run decides it
(status, delay, attempts, intent documents, trajectories), and attempts planned concurrently on
the workers are kept (speculation that no earlier mission's acceptance could change)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

DASK = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
WORKER = [sys.executable, "-m", "distributed.cli.dask_worker"]


@pytest.fixture
def worker_processes(tmp_path):
    """A scheduler and two single-threaded worker processes (the pattern of tests/test_cluster.py);
    yields (address, cache dir the workers read the maps from)."""
    from distributed import Client

    cache = tmp_path / "cache"
    sfile = tmp_path / "scheduler.json"
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "SKYROUTE_CACHE_DIR": str(cache)}
    procs = [subprocess.Popen([*DASK, "--scheduler-file", str(sfile), "--port", "0", "--no-dashboard"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        t_end = time.monotonic() + 60
        while not sfile.exists():
            assert time.monotonic() < t_end, "the dask scheduler did not start"
            time.sleep(0.2)
        procs += [subprocess.Popen([*WORKER, "--scheduler-file", str(sfile), "--nthreads", "1", "--no-nanny",
                                    "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
                  for _ in range(2)]
        address = json.loads(sfile.read_text())["address"]
        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=60)
        yield address, cache
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()


def test_worker_processes_decide_as_the_sequential_run(worker_processes):
    from distributed import Client

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.fleet import (
        FleetOptions,
        default_level,
        draw_missions,
        fleet_maps,
        run_fleet,
    )
    from skyroute.pipeline.settings import load_scenario

    address, cache = worker_processes
    sc = load_scenario("helsinki-medical")
    root = Cache(cache).root
    maps = fleet_maps(sc, root)          # computed here once; the workers read them from the cache
    tasks = draw_missions(sc, maps, 8, 11, 300.0, min_km=0.2, max_km=0.6)
    opt = FleetOptions(seed=11)
    level = default_level(maps)
    seq = run_fleet(sc, tasks, cache_dir=root, options=opt, default_dop=level)
    with Client(address, timeout="30s") as client:
        assert len(client.scheduler_info()["workers"]) == 2
        par = run_fleet(sc, tasks, cache_dir=root, options=opt, default_dop=level, client=client, depth=4)
    assert [(o.task.id, o.status, o.delay_s, o.attempts) for o in seq.outcomes] == \
        [(o.task.id, o.status, o.delay_s, o.attempts) for o in par.outcomes]
    for a, b in zip(seq.outcomes, par.outcomes, strict=True):
        assert (a.attempt is None) == (b.attempt is None)
        if a.attempt is not None:
            assert a.attempt.doc == b.attempt.doc
            np.testing.assert_array_equal(a.attempt.xyz_m, b.attempt.xyz_m)
    assert sum(o.status in ("accepted", "delayed") for o in seq.outcomes) >= 4
    st = par.speculative
    # attempts planned ahead on the workers and kept: the head mission's own plus missions
    # decided concurrently whose corridor no acceptance meanwhile changed
    assert st["speculative_used"] >= 4, st
    assert st["speculative_used"] + st["speculative_replanned"] <= st["attempts"], st

"""A real multi-process dask cluster (`dask scheduler` + `dask worker` processes, issue 27 item 6):
commands run on workers that already ran other skyroute tasks, and losing every worker is one
`error:` line within a bounded time, never a hang."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SKYROUTE = [sys.executable, "-m", "skyroute.pipeline.cli"]
DASK = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
WORKER = [sys.executable, "-m", "distributed.cli.dask_worker"]


@pytest.fixture
def cluster(tmp_path):
    """A scheduler and two single-threaded worker processes (no nanny: killing one kills it)."""
    from distributed import Client

    sfile = tmp_path / "scheduler.json"
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "SKYROUTE_CACHE_DIR": str(tmp_path / "cache")}
    procs = [subprocess.Popen([*DASK, "--scheduler-file", str(sfile), "--port", "0", "--no-dashboard"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    t_end = time.monotonic() + 60
    while not sfile.exists():
        assert time.monotonic() < t_end, "the dask scheduler did not start"
        time.sleep(0.2)
    workers = [subprocess.Popen([*WORKER, "--scheduler-file", str(sfile), "--nthreads", "1", "--no-nanny",
                                 "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
               for _ in range(2)]
    procs += workers
    address = json.loads(sfile.read_text())["address"]
    with Client(address, timeout="30s") as c:
        c.wait_for_workers(2, timeout=60)
    try:
        yield address, workers, env
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()


def _cmd(args, env, out: Path, timeout=900) -> subprocess.CompletedProcess:
    return subprocess.run([*SKYROUTE, *args, "--out", str(out)], capture_output=True, text=True, env=env,
                          timeout=timeout)


def test_two_commands_on_one_cluster_then_every_worker_lost(cluster, tmp_path):
    address, workers, env = cluster
    # 1. a pipeline command runs its stages on the workers, then a fleet on the same workers
    r = _cmd(["run", "helsinki-medical", "--stage", "environment", "--scheduler", address, "-q"], env,
             tmp_path / "run")
    assert r.returncode == 0, r.stderr[-3000:]
    for i in range(2):          # the second fleet meets workers that already ran a fleet's tasks
        r = _cmd(["fleet", "helsinki-medical", "--missions", "2", "--seed", str(i + 1), "--scheduler", address, "-q"],
                 env, tmp_path / f"fleet1-{i}")
        assert r.returncode == 0, r.stderr[-3000:]
        assert "Traceback" not in r.stderr
    # 2. every worker killed in the middle of a fleet: one error line within a bounded time
    p = subprocess.Popen([*SKYROUTE, "fleet", "helsinki-medical", "--missions", "80", "--seed", "2", "--scheduler",
                          address, "-q", "--out", str(tmp_path / "fleet2")], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, env=env)
    time.sleep(6.0)
    assert p.poll() is None, p.stderr.read().decode()[-3000:]
    for w in workers:
        w.send_signal(signal.SIGKILL)
    t0 = time.monotonic()
    from skyroute.pipeline.graph import WORKER_LOSS_S

    rc = p.wait(timeout=WORKER_LOSS_S + 60)
    waited = time.monotonic() - t0
    err = p.stderr.read().decode()
    assert rc == 2, (rc, err[-3000:])
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "every dask worker was lost" in lines[0], err[-3000:]
    assert "Traceback" not in err
    assert waited <= WORKER_LOSS_S + 30, waited


def _small_helsinki(folder: Path) -> Path:
    """helsinki-medical cut to a 0.45 x 1.05 km AOI round its mission, 256-cell chunks and a 5 min
    GNSS window (a fast scenario whose maps still come in several chunks)."""
    import yaml

    catalogs = Path(__file__).resolve().parents[1] / "catalogs"
    sc = yaml.safe_load((catalogs / "scenarios" / "helsinki-medical.yaml").read_text())
    sc.update(name="helsinki-small")
    sc.pop("traffic")
    sc["aoi"].update(bounds_lonlat=[24.9370, 60.1636, 24.9450, 60.1730], chunk_cells=256)
    sc["gnss"]["window_min"] = 5
    text = yaml.safe_dump(sc).replace("../data/", f"{catalogs / 'data'}/")
    (folder / "helsinki-small.yaml").write_text(text)
    return folder / "helsinki-small.yaml"


def test_maps_on_a_real_cluster_equal_the_default_scheduler(cluster, tmp_path):
    """Every map stage before `plan` (issue 23 item 3: the stages the cluster benchmark times)
    computed on two worker processes is bit-identical to the default threaded scheduler's."""
    import xarray as xr

    from skyroute.pipeline.cache import Cache
    from skyroute.pipeline.graph import run_pipeline, stages_for
    from skyroute.pipeline.settings import load_scenario

    address, _, _ = cluster
    sc = load_scenario(str(_small_helsinki(tmp_path)))
    maps = [s.name for s in stages_for(sc, ["plan"]) if s.name != "plan"]
    assert "coverage" in maps and "clearance" in maps
    a = run_pipeline(sc, cache=Cache(tmp_path / "threads"), targets=maps)
    b = run_pipeline(sc, cache=Cache(tmp_path / "cluster"), targets=maps, scheduler=address)
    assert [r.name for r in a.records] == [r.name for r in b.records] == maps
    assert not a.cache_hits and not b.cache_hits
    surf = b["surface"]["surface"]
    assert surf.encoding["chunks"][0] < surf.shape[0]     # several chunks
    for name in maps:
        xr.testing.assert_identical(a[name].load(), b[name].load())

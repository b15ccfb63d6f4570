"""A deliberately slow stage used by the SIGKILL test (imported by path, not a test module)."""

from __future__ import annotations

import os
import time

import dask.array as da
import numpy as np
import xarray as xr

from skyroute.pipeline.graph import REGISTRY, Stage, register
from skyroute.pipeline.model import FrozenModel


class SlowSettings(FrozenModel):
    n_chunks: int = 40


def _block(block, block_info=None):
    if os.environ.get("SKYROUTE_TEST_SLOW") == "1":
        time.sleep(0.25)
    i = block_info[0]["chunk-location"][0]
    return block + i


def slow_stage(surface: xr.Dataset, *, settings: SlowSettings) -> xr.Dataset:
    n = settings.n_chunks
    arr = da.zeros((n * 1000,), chunks=1000, dtype="float64").map_blocks(_block, dtype="float64")
    return xr.Dataset({"v": ("i", arr, {"units": "1"})})


def install() -> None:
    if "slow" not in REGISTRY:
        register(Stage("slow", slow_stage, lambda sc: SlowSettings(), inputs=("surface",)))


def expected() -> np.ndarray:
    return np.repeat(np.arange(40, dtype=float), 1000)

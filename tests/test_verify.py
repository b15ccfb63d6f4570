"""verify_dataset lists every broken convention; the runner refuses to cache such an output."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.graph import REGISTRY, Stage, register, run_pipeline
from skyroute.pipeline.model import FrozenModel
from skyroute.pipeline.verify import DatasetError, verify_dataset
from skyroute.stages.grid import Grid


def _good() -> xr.Dataset:
    g = Grid.from_bounds("EPSG:32635", 0, 0, 10, 10, 1.0)
    return xr.Dataset({"surface": g.dataarray(np.zeros(g.shape), "surface", units="m", vertical_datum="EGM96")})


def test_a_good_dataset_has_no_problem():
    assert verify_dataset(_good()) == []


def test_every_problem_is_listed():
    ds = _good()
    ds["surface"].attrs.pop("vertical_datum")
    ds["count"] = (("y", "x"), np.ones((10, 10)))
    ds = ds.isel(x=slice(None, None, -1)).drop_vars("spatial_ref")
    probs = verify_dataset(ds)
    assert "surface: a height in metres without a 'vertical_datum' attribute" in probs
    assert "count: no 'units' attribute" in probs
    assert "x: coordinates must increase (west to east)" in probs
    assert any(p.startswith("no CRS") for p in probs)
    assert len(probs) == 4


class _S(FrozenModel):
    pass


def _bad_stage(surface: xr.Dataset, *, settings: _S) -> xr.Dataset:
    return xr.Dataset({"v": (("y", "x"), surface["surface"].values)}, coords={"y": surface.y, "x": surface.x})


def test_runner_never_caches_a_malformed_output(helsinki, cache):
    register(Stage("bad", _bad_stage, lambda sc: _S(), inputs=("surface",)))
    try:
        with pytest.raises(DatasetError, match=r"output of stage 'bad': 1 problem\(s\): v: no 'units' attribute"):
            run_pipeline(helsinki, cache=cache, targets=["bad"])
    finally:
        REGISTRY.pop("bad", None)
    assert [e.stage for e in cache.entries()] == ["surface"]

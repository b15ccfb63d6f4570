"""The cache writes stage outputs whose overlapped dask blocks came out uneven (issue 23).

``skyroute coverage`` of a 6 x 6 km AOI crashed in ``Cache.write`` with "Zarr requires uniform
chunk sizes except for final chunk ... ((3,), (1024, 526, 498, 1024, 28), ...)": the overlapped
block runner (:mod:`skyroute.stages.overlap`) merges blocks narrower than the halo into their
neighbours, which zarr cannot store.  The cache rechunks such arrays in one place."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest
import xarray as xr

from skyroute.pipeline.cache import Cache, zarr_uniform_chunks
from skyroute.stages.overlap import overlap_map

CASES = [  # (input blocks, halo [cells], blocks of the output along y)
    # blocks of 8 with a 2-cell last block: the runner merges it into its neighbour, the last
    # block comes out larger than the others ("Final chunk ... must be ... smaller than the first")
    (((8, 8, 8, 8, 2), (8, 8, 8, 2)), 5, (8, 8, 8, 10)),
    # uneven inner blocks, as in the issue ((1024, 526, 498, 1024, 28)): "uniform chunk sizes"
    (((8, 5, 3, 8, 10), (8, 4, 4, 10)), 2, (8, 5, 3, 8, 10)),
]


def _overlapped_dataset(chunks, depth) -> xr.Dataset:
    """(threshold, y, x) like the coverage stage: a 3-cell box max computed by the overlapped
    runner with a halo of ``depth`` cells on blocks ``chunks``."""
    rng = np.random.default_rng(3)
    a = rng.random((34, 26))
    arr = da.from_array(a, chunks=chunks)

    def fn(block, origin, core):
        from scipy.ndimage import maximum_filter
        out = maximum_filter(block, size=3, mode="nearest")[core]
        return np.stack([out, 2 * out, 3 * out])

    res = overlap_map(arr, depth, fn, ((3,),), np.float64)
    ds = xr.Dataset({"unflyable": (("threshold", "y", "x"), res > 0.5), "floor": (("threshold", "y", "x"), res)},
                    coords={"threshold": [2.0, 3.0, 4.0], "y": np.arange(34.0), "x": np.arange(26.0)})
    return ds, a


def test_uniform_chunks_rule():
    assert zarr_uniform_chunks(((3,), (1024, 1024, 28))) is None
    assert zarr_uniform_chunks(((3,), (1024, 526, 498, 1024, 28), (1024, 521, 503, 1024, 18))) == (
        (3,), (1024, 1024, 1024, 28), (1024, 1024, 1024, 18))
    assert zarr_uniform_chunks(((8, 8, 8, 10),)) == ((10, 10, 10, 4),)
    assert zarr_uniform_chunks(((5, 7),)) == ((7, 5),)


@pytest.mark.parametrize(("chunks", "depth", "out_y"), CASES)
def test_cache_writes_uneven_overlapped_chunks(tmp_path, chunks, depth, out_y):
    ds, a = _overlapped_dataset(chunks, depth)
    assert ds["floor"].chunks[1] == out_y                  # the runner's uneven blocks
    with pytest.raises(ValueError, match="(uniform chunk sizes|Final chunk of Zarr)"):   # what the stage write hit
        ds.to_zarr(tmp_path / "plain.zarr", mode="w", consolidated=False)
    cache = Cache(tmp_path / "cache")
    entry = cache.write("coverage", "k1", ds, {})
    back = cache.open(entry).load()
    from scipy.ndimage import maximum_filter
    ref = maximum_filter(a, size=3, mode="nearest")             # the unchunked computation
    np.testing.assert_array_equal(back["floor"].values[0], ref)
    np.testing.assert_array_equal(back["floor"].values[2], 3 * ref)
    np.testing.assert_array_equal(back["unflyable"].values, ds["unflyable"].values)
    assert cache.get("coverage", "k1") is not None

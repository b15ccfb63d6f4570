"""Overlapped blocks: run a function on every block of a 2D dask array extended by a halo.

A block's result may depend on cells up to ``depth`` cells away (e.g. a building's shadow,
:func:`skyroute.stages.occlusion.shadow_halo_cells`), so each block is computed on itself plus
``depth`` cells of its neighbours, and only the block's own cells (its *core*) are kept.
Outside the map there is nothing (``boundary="none"``: edge blocks get no padding), as in the
unchunked computation; with the block's ``origin`` in the whole map a function can give
bit-identical results for any block layout.

* :func:`ensure_min_chunks`: rechunk so that every block is at least the halo wide (dask's
  overlap needs it), merging too-small blocks into their neighbours
  (``dask.array.overlap.ensure_minimum_chunksize``); an axis with one block needs no halo.
* :func:`overlap_maps` / :func:`overlap_map`: the runner (``map_blocks`` on
  ``dask.array.overlap.overlap``).  The function gets ``(block, origin, core)``
  (:data:`BlockFn`) and returns ``(..., core_y, core_x)``.

Users: :mod:`skyroute.stages.occlusion` (visibility heights) and :mod:`skyroute.stages.coverage`
(coverage floors, DOP sections).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import dask.array as da
import numpy as np

BlockFn = Callable[[np.ndarray, tuple[int, int], tuple[slice, slice]], np.ndarray]
"""``fn(block, origin, core) -> (..., core_y, core_x)``: a 2D block with its halo, the (row, col)
of ``block[0, 0]`` in the map and the window of the block's own cells in it."""


def ensure_min_chunks(arr: da.Array, depth: int) -> tuple[da.Array, int, int]:
    """(``arr`` rechunked so that every block is at least ``depth`` cells wide, halo rows, halo
    columns) for a 2D dask array; the halo along an axis is ``min(depth, size)``, and 0 where
    the axis has one block."""
    dy = int(min(depth, arr.shape[0]))
    dx = int(min(depth, arr.shape[1]))
    new = tuple(c if len(c) == 1 or d <= 0 else da.overlap.ensure_minimum_chunksize(d, c)
                for c, d in zip(arr.chunks, (dy, dx), strict=True))
    if new != arr.chunks:
        arr = arr.rechunk(new)
    dy = dy if len(arr.chunks[0]) > 1 else 0
    dx = dx if len(arr.chunks[1]) > 1 else 0
    return arr, dy, dx


def overlap_maps(arr: da.Array, depth: int, fns: Sequence[BlockFn],
                 lead_chunks: tuple[tuple[int, ...], ...], dtype: Any) -> list[da.Array]:
    """Apply each ``fn(block, origin, core)`` (see :data:`BlockFn`) on every block of the 2D
    dask array ``arr`` extended by ``depth`` cells of its neighbours (none beyond the map
    edge); one dask array ``(*lead, y, x)`` per ``fn`` (``lead_chunks``: the chunks of the
    leading dims ``fn`` adds), all sharing the overlapped blocks.  ``arr`` is first passed
    through :func:`ensure_min_chunks`."""
    arr, dy, dx = ensure_min_chunks(arr, depth)
    ext = (da.overlap.overlap(arr, depth={0: dy, 1: dx}, boundary="none")
           if dy or dx else arr)
    chunks_y, chunks_x = arr.chunks
    start_y = np.r_[0, np.cumsum(chunks_y)[:-1]]
    start_x = np.r_[0, np.cumsum(chunks_x)[:-1]]
    n_lead = len(lead_chunks)

    def make(fn: BlockFn) -> da.Array:
        def block(b: np.ndarray, block_info: dict | None = None) -> np.ndarray:
            iy, ix = block_info[None]["chunk-location"][-2:]
            top = dy if iy > 0 else 0
            left = dx if ix > 0 else 0
            core = (slice(top, top + chunks_y[iy]), slice(left, left + chunks_x[ix]))
            return fn(np.asarray(b), (int(start_y[iy]) - top, int(start_x[ix]) - left), core)

        return da.map_blocks(block, ext, chunks=lead_chunks + (chunks_y, chunks_x),
                             new_axis=list(range(n_lead)) if n_lead else None,
                             dtype=dtype, meta=np.empty((0,) * (n_lead + 2), dtype))

    return [make(fn) for fn in fns]


def overlap_map(arr: da.Array, depth: int, fn: BlockFn,
                lead_chunks: tuple[tuple[int, ...], ...], dtype: Any) -> da.Array:
    """:func:`overlap_maps` with one function."""
    return overlap_maps(arr, depth, [fn], lead_chunks, dtype)[0]


__all__ = ["BlockFn", "ensure_min_chunks", "overlap_map", "overlap_maps"]

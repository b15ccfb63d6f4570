"""Clearance over a conservative surface (issue 8, part 3): thin spires (0.3 m wide, 60 m tall,
off the grid, rotated) at 0.5, 1 and 2 m cells.  The oracle is an exact point-to-rotated-box
distance, brute force over every spire, at random points inside every cell of the grid."""

from __future__ import annotations

import numpy as np
import pytest

from skyroute.stages.clearance import clearance_floor, is_clear
from skyroute.stages.grid import Grid, ring_cells
from skyroute.stages.surface import polygon_max

SPIRE_WIDTH_M = 0.3
SPIRE_HEIGHT_M = 60.0
EXTENT_M = 40.0


def _spires(rng, n=7):
    """(centre x, y [m], rotation [rad]) of ``n`` spires, off the grid lines of every tested
    resolution, plus one exactly on a grid node and one on a grid line."""
    c = rng.uniform(6.0, EXTENT_M - 6.0, (n, 2))
    c[0] = (20.0, 20.0)        # on a node of every grid
    c[1] = (12.0, 27.137)      # on a vertical grid line
    ang = rng.uniform(0, np.pi / 2, n)
    ang[0] = np.pi / 4
    return c, ang


def _corners(c, ang):
    h = SPIRE_WIDTH_M / 2
    loc = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    return loc @ R.T + c


def _dist_to_spires(x, y, z, centres, angles) -> np.ndarray:
    """Exact distance [m] from points to the nearest obstacle: every spire (a rotated box
    0.3 x 0.3 x [0, 60] m) and the ground half-space z <= 0; brute force over the spires."""
    d = np.maximum(z, 0.0)  # the ground
    h = SPIRE_WIDTH_M / 2
    for c, a in zip(centres, angles, strict=True):
        px, py = x - c[0], y - c[1]
        lx = np.cos(a) * px + np.sin(a) * py  # into the spire's frame
        ly = -np.sin(a) * px + np.cos(a) * py
        dx = np.maximum(np.abs(lx) - h, 0.0)
        dy = np.maximum(np.abs(ly) - h, 0.0)
        dz = np.maximum(np.maximum(z - SPIRE_HEIGHT_M, -z), 0.0)
        d = np.minimum(d, np.sqrt(dx * dx + dy * dy + dz * dz))
    return d


def _spire_surface(grid, centres, angles) -> np.ndarray:
    polys = [[np.column_stack([_corners(c, a), np.full(4, SPIRE_HEIGHT_M)])] for c, a in zip(centres, angles, strict=True)]
    top, _ = polygon_max(polys, grid)
    return np.where(np.isfinite(top), top, 0.0)


def _centre_sampled_surface(grid, centres, angles) -> np.ndarray:
    """What a cell-centre rasteriser makes of the spires (for the test's own power check)."""
    rings = [_corners(c, a) for c, a in zip(centres, angles, strict=True)]
    P = np.vstack(rings)
    off = np.arange(0, 4 * len(rings) + 1, 4)
    _, rr, cc = ring_cells(P[:, 0], P[:, 1], off, grid)
    s = np.zeros(grid.shape)
    s[rr, cc] = SPIRE_HEIGHT_M
    return s


def _worst_clearance(grid, floor, centres, angles, rng, per_cell=12) -> float:
    """Smallest exact obstacle distance over random points inside every cell at the cell's floor
    and above it (up to 70 m higher), and at the cell's corners and edge midpoints."""
    ny, nx = grid.shape
    rows, cols = np.mgrid[0:ny, 0:nx]
    rows, cols = rows.ravel(), cols.ravel()
    u = np.concatenate([rng.uniform(0, 1, (per_cell, rows.size)), np.array([0, 0.5, 0.999999999, 0])[:, None]
                        * np.ones(rows.size)])
    v = np.concatenate([rng.uniform(0, 1, (per_cell, rows.size)), np.array([0, 0.999999999, 0.5, 0.5])[:, None]
                        * np.ones(rows.size)])
    r = grid.resolution_m
    x = grid.x0 + (cols + u) * r
    y = grid.y1 - (rows + v) * r
    f = floor[rows, cols] * np.ones_like(x)
    worst = float(_dist_to_spires(x, y, f, centres, angles).min())
    z_above = f + rng.uniform(0, 70.0, f.shape)
    worst = min(worst, float(_dist_to_spires(x, y, z_above, centres, angles).min()))
    # the same points are inside the cell the O(1) lookup uses
    assert is_clear(grid.dataarray(floor, "clearance_floor"), x, y, f).all()
    return worst


@pytest.mark.parametrize("res", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("radius_m", [1.0, 5.0])
def test_spires_are_cleared_at_every_point_of_every_cell(res, radius_m):
    rng = np.random.default_rng(int(100 * res + radius_m))
    centres, angles = _spires(rng)
    grid = Grid.from_bounds("EPSG:32633", 0.0, 0.0, EXTENT_M, EXTENT_M, res)
    surface = _spire_surface(grid, centres, angles)
    # every spire is in the surface at its full height, in every cell its footprint touches
    assert (surface == SPIRE_HEIGHT_M).sum() >= len(centres)
    floor = clearance_floor(grid.dataarray(surface, "surface", units="m"), radius_m).values
    worst = _worst_clearance(grid, floor, centres, angles, rng)
    assert worst >= radius_m - 1e-9, (res, radius_m, worst)


@pytest.mark.parametrize("res", [1.0, 2.0])
def test_centre_sampling_would_fail_this_oracle(res):
    """Power check: with the spires rasterised at cell centres (the old rule) the same oracle
    finds points closer than r_p -- so the test above can fail."""
    rng = np.random.default_rng(9)
    centres, angles = _spires(rng)
    grid = Grid.from_bounds("EPSG:32633", 0.0, 0.0, EXTENT_M, EXTENT_M, res)
    surface = _centre_sampled_surface(grid, centres, angles)
    floor = clearance_floor(grid.dataarray(surface, "surface", units="m"), 5.0).values
    assert _worst_clearance(grid, floor, centres, angles, rng) < 5.0 - 0.5

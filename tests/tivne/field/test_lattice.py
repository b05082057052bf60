"""The brick lattice predicate (tivne/field/lattice.py) against the grid's own point queries."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tivne.field.lattice import brick_inside, bricks_for_voxels, lattice_for_voxels, observed_space
from tivne.field.voxels import CORNER_OFFSETS, SparseVoxelGrid


def random_grid(seed: int) -> SparseVoxelGrid:
    """Static hits in two calls (so hit counts differ), a dilation shell, and moving-object voxels
    seen at two times."""
    g = torch.Generator().manual_seed(seed)
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=64)
    grid.allocate(torch.rand(300, 3, generator=g) * 0.8 - 0.4, dilation=1)
    grid.allocate(torch.rand(100, 3, generator=g) * 0.3)
    moving = torch.rand(50, 3, generator=g) * 0.2 + 0.3
    for tau in (0.0, 1.0):
        grid.allocate(moving + tau * 0.1, dynamic=torch.ones(50, dtype=torch.bool), tau=tau)
    return grid


def reference_inside(grid, points, margin, min_hits, tau, window) -> torch.Tensor:
    """What meshing computed point by point before the lattice tables: contains(p) and, with a
    margin, observed(p ± margin) for any of the 8 sign patterns."""
    inside = grid.contains(points)
    if margin is None:
        return inside
    near = torch.zeros_like(inside)
    for offset in CORNER_OFFSETS.to(points.dtype):
        near |= grid.observed(points + (2 * offset - 1) * margin, min_hits, tau, window)
    return inside & near


def all_points(lattice) -> torch.Tensor:
    axes = [lattice.axis(a, torch.device("cpu")) for a in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)


@pytest.mark.parametrize(
    "resolution, margin, min_hits, tau, window",
    [(0.02, None, 0, None, 0.0), (0.02, 0.02, 1, None, 0.0), (0.03, 0.03, 2, 0.0, 0.2), (0.025, 0.025, 0, 1.0, 0.5)],
)
def test_brick_predicate_matches_point_queries(resolution, margin, min_hits, tau, window):
    grid = random_grid(0)
    lattice = lattice_for_voxels(grid.voxel_coords(), grid.voxel_size, resolution)
    space = observed_space(grid, lattice, margin, min_hits, tau, window)
    pts = all_points(lattice)
    expected = reference_inside(grid, pts.reshape(-1, 3), margin, min_hits, tau, window).reshape(pts.shape[:3])
    assert expected.any() and not expected.all()
    brick = 7
    bricks = bricks_for_voxels(grid.voxel_coords(), grid.voxel_size, lattice, brick)
    found = torch.zeros_like(expected)
    ar = torch.arange(brick + 1)
    index = tuple(bricks[:, a, None] * brick + ar for a in range(3))
    inside = brick_inside(space, index, lattice.dims)
    dims = lattice.dims
    for b in range(len(bricks)):  # paste each brick back where it lies in the lattice
        sl = [slice(int(index[a][b, 0]), min(int(index[a][b, -1]) + 1, int(dims[a]))) for a in range(3)]
        n = [s.stop - s.start for s in sl]
        part = inside[b, : n[0], : n[1], : n[2]]
        assert not inside[b, n[0] :].any() and not inside[b, :, n[1] :].any() and not inside[b, :, :, n[2] :].any()
        found[sl[0], sl[1], sl[2]] |= part
    assert torch.equal(found, expected)  # every inside point lies in a listed brick, and none else is inside


def test_bricks_cover_only_the_voxels_neighbourhood():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=64)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05], [1.05, 1.05, 1.05]]))  # two voxels far apart
    lattice = lattice_for_voxels(grid.voxel_coords(), grid.voxel_size, 0.02)
    assert list(lattice.dims) == [56, 56, 56]
    bricks = bricks_for_voxels(grid.voxel_coords(), grid.voxel_size, lattice, 4)
    # each voxel spans 5 cells (+1 margin each side) -> at most 3 bricks per axis around it, not the 14^3 of the box
    assert len(bricks) <= 2 * 27 and len(torch.unique(bricks, dim=0)) == len(bricks)
    assert np.array_equal(lattice.origin, [0.0, 0.0, 0.0])

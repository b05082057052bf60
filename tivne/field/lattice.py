"""Which points of a regular lattice lie in a sparse voxel grid's (observed) voxels, in bricks.

A lattice point's world coordinate on one axis depends on its index on that axis only, so the voxel
index of every lattice point (and of the point moved by ± a margin) is computed once per axis; the
hash keys of a brick of points are then integer ORs of three per-axis tables, with no float work
per point. The results are bit for bit those of :meth:`SparseVoxelGrid.contains` and
``observed`` on the same float32 points (the same float32 operations run, once per axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tivne.field.voxels import _BITS, _OFFSET, SparseVoxelGrid, bracketing_observations, sorted_lookup


@dataclass(frozen=True)
class Lattice:
    """Points origin + step · (i, j, k), 0 <= index < dims.

    origin: (3,) float64 world position of index (0, 0, 0); step: metres; dims: (3,) int64.
    """

    origin: np.ndarray
    step: float
    dims: np.ndarray

    def axis(self, a: int, device: torch.device) -> torch.Tensor:
        """(dims[a],) float32 world coordinates along axis ``a`` (float64 sum, then rounded, as meshing always did)."""
        return torch.from_numpy(self.origin[a] + self.step * np.arange(int(self.dims[a]))).to(device=device, dtype=torch.float32)


def lattice_for_voxels(voxel_coords: torch.Tensor, voxel_size: float, resolution: float) -> Lattice:
    """The lattice of step ``resolution`` covering the voxels' bounding box (V > 0 voxels); the
    last point per axis does not pass the box."""
    coords = voxel_coords.detach().cpu().double().numpy()
    lo = coords.min(0) * voxel_size
    hi = (coords.max(0) + 1) * voxel_size
    dims = np.floor((hi - lo) / resolution + 1e-9).astype(np.int64) + 1
    return Lattice(lo, float(resolution), dims)


def axis_keys(x: torch.Tensor, voxel_size: float, axis: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis part of the packed voxel key of coordinates ``x`` (n,) float32, and in_range (n,) bool
    (the same floor and range test as ``SparseVoxelGrid.point_keys``)."""
    base = torch.floor(x / voxel_size)
    in_range = base.abs() < _OFFSET - 1
    cell = torch.where(in_range, base, torch.zeros_like(base)).long() + _OFFSET
    return cell << ((2 - axis) * _BITS), in_range


@dataclass(frozen=True)
class ObservedSpace:
    """The lattice predicate of meshing: a point lies in an allocated voxel and, when ``margin`` is
    set, within ``margin`` per axis (the 8 points p ± margin) of an observed voxel: one with
    >= min_hits static hits, or one where a moving object was seen at the observations that bracket
    τ within the window (``SparseVoxelGrid.observed``).

    tables: per axis and shift (-margin, 0, +margin) the (dims[a],) key parts and in_range flags.
    voxel_keys: (V,) sorted allocated keys; observed_keys: (O,) sorted keys passing the observed
    test, or None for no culling.
    """

    keys: tuple[tuple[torch.Tensor, ...], ...]
    in_range: tuple[tuple[torch.Tensor, ...], ...]
    voxel_keys: torch.Tensor
    observed_keys: torch.Tensor | None


def observed_space(
    grid: SparseVoxelGrid, lattice: Lattice, margin: float | None, min_hits: int = 1, tau: float | None = None, window: float = 0.0
) -> ObservedSpace:
    """Build the predicate's tables (margin None: every allocated voxel counts, no observation test)."""
    device = grid.voxel_keys.device
    keys, ranges = [], []
    shifts = torch.tensor([-1.0, 0.0, 1.0], device=device) * (margin or 0.0)  # float32, as p + (2o - 1)·margin
    for a in range(3):
        x = lattice.axis(a, device)
        parts = [axis_keys(x if s == 1 else x + shifts[s], grid.voxel_size, a) for s in range(3)]
        keys.append(tuple(p[0] for p in parts))
        ranges.append(tuple(p[1] for p in parts))
    observed = None
    if margin is not None:
        observed = grid.voxel_keys if min_hits <= 0 else grid.voxel_keys[grid.voxel_hits >= min_hits]
        if tau is not None and grid.dynamic_keys.numel():
            recent = grid.dynamic_keys[bracketing_observations(grid.dynamic_tau, float(tau), window)]
            observed = torch.unique(torch.cat([observed, recent]))  # sorted
    return ObservedSpace(tuple(keys), tuple(ranges), grid.voxel_keys, observed)


def member(sorted_keys: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """(...) bool: queries found in the (K,) ascending keys."""
    return sorted_lookup(sorted_keys, queries)[1] if sorted_keys.numel() else torch.zeros_like(queries, dtype=torch.bool)


def brick_inside(space: ObservedSpace, index: tuple[torch.Tensor, torch.Tensor, torch.Tensor], dims: np.ndarray) -> torch.Tensor:
    """The predicate on bricks of lattice points.

    Args:
        index: per axis (nb, n) int64 lattice indices of each brick's points along that axis.
        dims: (3,) lattice size; indices outside [0, dims) are never inside.
    Returns:
        (nb, n, n, n) bool.
    """
    ix, iy, iz = (i.clamp(0, int(d) - 1) for i, d in zip(index, dims))
    ok = [(i >= 0) & (i < int(d)) for i, d in zip(index, dims)]

    def combine(parts: tuple[torch.Tensor, torch.Tensor, torch.Tensor], op) -> torch.Tensor:
        return op(op(parts[0][:, :, None, None], parts[1][:, None, :, None]), parts[2][:, None, None, :])

    key = combine((space.keys[0][1][ix], space.keys[1][1][iy], space.keys[2][1][iz]), torch.bitwise_or)
    valid = combine(tuple(o & r[1][i] for o, r, i in zip(ok, space.in_range, (ix, iy, iz))), torch.logical_and)
    inside = valid & member(space.voxel_keys, key)
    if space.observed_keys is None:
        return inside
    # only the points already inside need the 8 shifted tests
    b, i, j, k = inside.nonzero(as_tuple=True)
    pi, pj, pk = ix[b, i], iy[b, j], iz[b, k]
    near = torch.zeros_like(b, dtype=torch.bool)
    for sx in (0, 2):
        for sy in (0, 2):
            for sz in (0, 2):
                q = space.keys[0][sx][pi] | space.keys[1][sy][pj] | space.keys[2][sz][pk]
                r = space.in_range[0][sx][pi] & space.in_range[1][sy][pj] & space.in_range[2][sz][pk]
                near |= r & member(space.observed_keys, q)
    inside[b, i, j, k] = near
    return inside


def bricks_for_voxels(voxel_coords: torch.Tensor, voxel_size: float, lattice: Lattice, brick: int) -> torch.Tensor:
    """(B, 3) int64 brick indices (brick b holds lattice cells b·brick … b·brick + brick - 1 per
    axis) that may hold a cell with a corner inside one of the voxels, sorted, unique.

    Args:
        voxel_coords: (V, 3) integer voxel coordinates.
    """
    coords = voxel_coords.detach().cpu().double()
    origin = torch.from_numpy(lattice.origin)
    dims = torch.from_numpy(lattice.dims)
    lo = (torch.floor((coords * voxel_size - origin) / lattice.step).long() - 1).clamp(min=0)
    hi = torch.minimum(torch.floor(((coords + 1) * voxel_size - origin) / lattice.step).long() + 1, dims - 1)
    blo, bhi = lo // brick, hi // brick
    span = int((bhi - blo).max()) + 1
    r = torch.arange(span)
    offs = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    cand = torch.minimum(blo[:, None, :] + offs, bhi[:, None, :]).reshape(-1, 3)
    return torch.unique(cand, dim=0)

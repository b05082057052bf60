"""Sparse voxel grid with corner-shared embeddings, indexed by a tensor hash of integer coordinates.

Voxel (i, j, k) spans [i, i+1) x [j, j+1) x [k, k+1) in units of ``voxel_size``; its 8 corners are the
integer lattice points (i+dx, j+dy, k+dz). Each lattice point allocated as some voxel's corner owns one
row of the embedding table E, so neighbouring voxels share embeddings. Keys are packed int64s kept
sorted, so membership and lookup are ``torch.searchsorted`` (no preset scene bounds, no dense box).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

_BITS = 21
_OFFSET = 1 << (_BITS - 1)  # coordinates in [-2^20, 2^20) voxels: +-100 km at 10 cm
_MASK = (1 << _BITS) - 1

# Corner order i = 4*dx + 2*dy + dz (as Vox-Fusion).
CORNER_OFFSETS = torch.tensor([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=torch.long)


class GridCapacityError(RuntimeError):
    """Raised when allocation would exceed the grid's hard cap on embedding rows."""


def pack_coords(coords: torch.Tensor, checked: bool = True) -> torch.Tensor:
    """(..., 3) int64 voxel coordinates -> (...) int64 keys (order-preserving per axis, x major).

    ``checked=False`` skips the range check, for callers that already masked out-of-range points
    (the check costs a device sync per call, and lookups run every optimiser step).
    """
    c = coords + _OFFSET
    if checked and ((c < 0).any() or (c > _MASK).any()):
        raise ValueError(f"voxel coordinate out of the hashable range +-{_OFFSET}")
    return (c[..., 0] << (2 * _BITS)) | (c[..., 1] << _BITS) | c[..., 2]


def unpack_keys(keys: torch.Tensor) -> torch.Tensor:
    """(...) int64 keys -> (..., 3) int64 voxel coordinates."""
    return torch.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], dim=-1) - _OFFSET


def sorted_lookup(sorted_keys: torch.Tensor, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions of ``queries`` in ``sorted_keys``.

    Args:
        sorted_keys: (K,) ascending int64.
        queries: (...) int64.
    Returns:
        pos (...) clamped into [0, K-1] and found (...) bool.
    """
    if sorted_keys.numel() == 0:
        return torch.zeros_like(queries), torch.zeros_like(queries, dtype=torch.bool)
    pos = torch.searchsorted(sorted_keys, queries).clamp_(max=sorted_keys.numel() - 1)
    return pos, sorted_keys[pos] == queries


def merge_order(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The permutation that sorts ``torch.cat([a, b])``, for (n,) and (m,) ascending int64 keys with
    none in both: O(n + m) where a sort of the whole is O((n + m) log(n + m)) (a map grows by a few
    keys per frame; re-sorting all of them every frame was most of its allocation's cost).

    Returns:
        (n + m,) int64 order, ``torch.cat([a, b])[order]`` ascending.
    """
    n, m = a.numel(), b.numel()
    order = torch.empty(n + m, dtype=torch.long, device=a.device)
    order[torch.arange(n, device=a.device) + torch.searchsorted(b, a)] = torch.arange(n, device=a.device)
    order[torch.arange(m, device=a.device) + torch.searchsorted(a, b)] = torch.arange(n, n + m, device=a.device)
    return order


def trilinear_weights(frac: torch.Tensor) -> torch.Tensor:
    """Trilinear weights of the 8 corners.

    Args:
        frac: (P, 3) position inside the voxel in [0, 1)^3.
    Returns:
        (P, 8) weights in corner order 4*dx + 2*dy + dz; they sum to 1.
    """
    offs = CORNER_OFFSETS.to(frac.device, frac.dtype)  # (8, 3)
    w = frac[:, None, :] * offs + (1 - frac[:, None, :]) * (1 - offs)  # (P, 8, 3)
    return w.prod(dim=-1)


def bracketing_observations(times: torch.Tensor, tau: float, window: float) -> torch.Tensor:
    """(N,) observation times -> (N,) bool: the rows of the latest time <= ``tau`` and of the
    earliest time >= ``tau``, each only if within ``window`` seconds of ``tau``.

    A moving object at ``tau`` lies between where it was seen just before and just after; the union
    of every observation within the window would also show the path it swept in between (a trail
    of ghost surface as long as speed x 2 x window).
    """
    near = (times - tau).abs() <= window
    before, after = near & (times <= tau), near & (times >= tau)
    keep = torch.zeros_like(near)
    if before.any():
        keep |= before & (times == times[before].max())
    if after.any():
        keep |= after & (times == times[after].min())
    return keep


class SparseVoxelGrid(nn.Module):
    """Corner-shared embeddings E on sparsely allocated voxels.

    Args:
        voxel_size: edge length in metres.
        embed_dim: Q, embedding width.
        capacity: initial number of embedding rows; doubled on demand.
        max_capacity: hard cap on rows; exceeding it raises :class:`GridCapacityError`.
        init_std: embeddings are initialised N(0, init_std^2).
    """

    def __init__(
        self,
        voxel_size: float = 0.1,
        embed_dim: int = 16,
        capacity: int = 20000,
        max_capacity: int = 2_000_000,
        init_std: float = 0.01,
        surface_cell: float = 0.0,
    ) -> None:
        super().__init__()
        if voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.embed_dim = int(embed_dim)
        self.max_capacity = int(max_capacity)
        self.init_std = float(init_std)
        self.embeddings = nn.Parameter(torch.randn(int(capacity), self.embed_dim) * self.init_std)
        self.register_buffer("voxel_keys", torch.zeros(0, dtype=torch.long))  # (V,) sorted
        self.register_buffer("voxel_corner_rows", torch.zeros(0, 8, dtype=torch.long))  # (V, 8)
        # (V,) how many allocation calls had a static depth point inside the voxel (0: allocated only
        # by dilation or only ever held moving objects); meshing can stay inside observed space with it.
        self.register_buffer("voxel_hits", torch.zeros(0, dtype=torch.int32))
        # (D,) one row per (voxel, time) a moving object's depth point fell inside the voxel, so a
        # mesh at time τ can show moving objects only where they were seen around τ.
        self.register_buffer("dynamic_keys", torch.zeros(0, dtype=torch.long))
        self.register_buffer("dynamic_tau", torch.zeros(0, dtype=torch.float32))
        # (S,) sorted keys of the cells of size ``surface_cell`` that held a static depth point: a
        # record of the observed surface much finer than the voxels, so meshing can drop surfaces the
        # field made up where nothing was seen (behind the supervised band, inside a hit voxel).
        self.surface_cell = float(surface_cell)
        self.register_buffer("surface_keys", torch.zeros(0, dtype=torch.long))
        self.register_buffer("corner_keys", torch.zeros(0, dtype=torch.long))  # (C,) sorted
        self.register_buffer("corner_rows", torch.zeros(0, dtype=torch.long))  # (C,)
        self.grow_callbacks: list = []  # called with (old_rows, new_rows) after E grows

    @property
    def num_voxels(self) -> int:
        return int(self.voxel_keys.numel())

    @property
    def num_corners(self) -> int:
        return int(self.corner_keys.numel())

    @property
    def capacity(self) -> int:
        return int(self.embeddings.shape[0])

    def voxel_coords(self) -> torch.Tensor:
        """(V, 3) integer coordinates of the allocated voxels."""
        return unpack_keys(self.voxel_keys)

    def _ensure_capacity(self, rows_needed: int) -> None:
        if rows_needed <= self.capacity:
            return
        if rows_needed > self.max_capacity:
            raise GridCapacityError(
                f"voxel grid needs {rows_needed} embedding rows but field.max_capacity is {self.max_capacity}; "
                "raise field.max_capacity or field.voxel_size"
            )
        new_cap = min(max(rows_needed, 2 * self.capacity), self.max_capacity)
        old = self.capacity
        extra = torch.randn(new_cap - old, self.embed_dim, device=self.embeddings.device) * self.init_std
        # Replace the data in place so optimisers keep referring to the same Parameter.
        self.embeddings.data = torch.cat([self.embeddings.data, extra.to(self.embeddings.dtype)])
        for callback in self.grow_callbacks:
            callback(old, new_cap)

    @torch.no_grad()
    def allocate(
        self, points: torch.Tensor, dilation: int = 0, dynamic: torch.Tensor | None = None, tau: float = 0.0
    ) -> int:
        """Allocate the voxels containing ``points`` (and their ``dilation``-neighbourhood) and count
        the observation: static points add a hit to their voxels, points flagged ``dynamic`` record
        (voxel, ``tau``) rows instead.

        Args:
            points: (N, 3) world points in metres.
            dilation: also allocate voxels within this many voxels (Chebyshev) of each hit voxel.
            dynamic: (N,) bool, the point lies on a moving object (None: all static).
            tau: the observation's time.
        Returns:
            number of newly allocated voxels.
        """
        if points.numel() == 0:
            return 0
        device = self.voxel_keys.device
        coords = torch.floor(points.to(device) / self.voxel_size)
        # A diverged pose must not take the run down: only allocate where a key exists.
        ok = torch.isfinite(coords).all(-1) & (coords.abs() < _OFFSET - 2).all(-1)
        is_dynamic = torch.zeros_like(ok) if dynamic is None else dynamic.to(device).bool() & ok
        coords = coords[ok].long()
        if coords.numel() == 0:
            return 0
        all_keys = pack_coords(coords)
        keys = torch.unique(all_keys)
        dyn_keys = torch.unique(all_keys[is_dynamic[ok]])
        hit_keys = torch.unique(all_keys[~is_dynamic[ok]])
        if dilation > 0:
            r = torch.arange(-dilation, dilation + 1, device=device)
            offs = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
            keys = torch.unique(pack_coords(unpack_keys(keys)[:, None, :] + offs).reshape(-1))
        _, found = sorted_lookup(self.voxel_keys, keys)
        new_keys = keys[~found]
        if new_keys.numel() > 0:
            self._insert_voxels(new_keys)
        pos, _ = sorted_lookup(self.voxel_keys, hit_keys)  # every hit voxel exists now
        self.voxel_hits[pos] += 1
        if self.surface_cell > 0:
            self._record_surface(points.to(device)[ok & ~is_dynamic])
        if dyn_keys.numel():
            self.dynamic_keys = torch.cat([self.dynamic_keys, dyn_keys])
            self.dynamic_tau = torch.cat([self.dynamic_tau, torch.full(dyn_keys.shape, float(tau), device=device)])
        return int(new_keys.numel())

    def _insert_voxels(self, new_keys: torch.Tensor) -> None:
        """Add voxels (keys not yet present, (Vn,) ascending) and fresh embedding rows for their new corners."""
        device = self.voxel_keys.device
        # Corners of the new voxels; those not yet present get fresh embedding rows.
        corner_keys = pack_coords(unpack_keys(new_keys)[:, None, :] + CORNER_OFFSETS.to(device))  # (Vn, 8)
        uniq = torch.unique(corner_keys)
        _, cfound = sorted_lookup(self.corner_keys, uniq)
        fresh = uniq[~cfound]
        first_row = self.num_corners
        self._ensure_capacity(first_row + fresh.numel())
        all_ckeys = torch.cat([self.corner_keys, fresh])
        all_crows = torch.cat([self.corner_rows, torch.arange(first_row, first_row + fresh.numel(), device=device)])
        order = merge_order(self.corner_keys, fresh)
        self.corner_keys = all_ckeys[order]
        self.corner_rows = all_crows[order]
        pos, _ = sorted_lookup(self.corner_keys, corner_keys)
        new_rows = self.corner_rows[pos]  # (Vn, 8)
        all_vkeys = torch.cat([self.voxel_keys, new_keys])
        all_vrows = torch.cat([self.voxel_corner_rows, new_rows])
        all_hits = torch.cat([self.voxel_hits, torch.zeros_like(new_keys, dtype=torch.int32)])
        order = merge_order(self.voxel_keys, new_keys)
        self.voxel_keys = all_vkeys[order]
        self.voxel_corner_rows = all_vrows[order]
        self.voxel_hits = all_hits[order]

    def point_keys(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) world points -> voxel keys (...) and in_range (...) bool; points outside the
        hashable range (or non-finite) get key 0 and in_range False -- they are simply not in the map."""
        base = torch.floor(points / self.voxel_size)
        in_range = (base.abs() < _OFFSET - 1).all(-1)  # False for NaN and inf too
        return pack_coords(torch.where(in_range[..., None], base, torch.zeros_like(base)).long(), checked=False), in_range

    def contains(self, points: torch.Tensor, min_hits: int = 0) -> torch.Tensor:
        """(..., 3) world points -> (...) bool, True inside an allocated voxel (False for NaN/inf/huge).

        ``min_hits`` > 0 keeps only voxels that held static depth points in at least that many
        allocation calls (observed space, not the dilation shell around it).
        """
        keys, in_range = self.point_keys(points)
        pos, found = sorted_lookup(self.voxel_keys, keys)
        found &= in_range
        if min_hits > 0 and self.num_voxels > 0:
            found &= self.voxel_hits[pos] >= min_hits
        return found

    def _record_surface(self, points: torch.Tensor) -> None:
        """Add the cells of (N, 3) static depth points to ``surface_keys`` (kept sorted, unique)."""
        cells = torch.floor(points / self.surface_cell)
        cells = cells[(cells.abs() < _OFFSET - 2).all(-1)].long()
        if cells.numel() == 0:
            return
        keys = torch.unique(pack_coords(cells, checked=False))
        fresh = keys[~sorted_lookup(self.surface_keys, keys)[1]]
        if fresh.numel():
            self.surface_keys = torch.cat([self.surface_keys, fresh])[merge_order(self.surface_keys, fresh)]

    def near_surface(self, points: torch.Tensor) -> torch.Tensor:
        """(P, 3) world points -> (P,) bool: within one cell (per axis) of a cell that held a static
        depth point. All True when nothing was recorded (``surface_cell`` 0, or an older map)."""
        if self.surface_keys.numel() == 0:
            return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
        cells = torch.floor(points.to(self.surface_keys.device) / self.surface_cell)
        in_range = (cells.abs() < _OFFSET - 2).all(-1)
        cells = torch.where(in_range[:, None], cells, torch.zeros_like(cells)).long()
        near = torch.zeros(points.shape[0], dtype=torch.bool, device=self.surface_keys.device)
        r = torch.arange(-1, 2, device=cells.device)
        for off in torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3):
            near |= sorted_lookup(self.surface_keys, pack_coords(cells + off, checked=False))[1]
        return (near & in_range).to(points.device)

    def dynamic_observed(self, points: torch.Tensor, tau: float, window: float) -> torch.Tensor:
        """(..., 3) world points -> (...) bool: inside a voxel where a moving object was seen at the
        observations that bracket ``tau`` within ``window`` (:func:`bracketing_observations`)."""
        keys, in_range = self.point_keys(points)
        if self.dynamic_keys.numel() == 0:
            return torch.zeros_like(in_range)
        recent = torch.unique(self.dynamic_keys[bracketing_observations(self.dynamic_tau, float(tau), window)])
        return sorted_lookup(recent, keys)[1] & in_range

    def observed(self, points: torch.Tensor, min_hits: int = 1, tau: float | None = None, window: float = 0.0) -> torch.Tensor:
        """(..., 3) world points -> (...) bool: inside a voxel with >= ``min_hits`` static hits, or
        (``tau`` given) one where a moving object was seen around ``tau`` (:meth:`dynamic_observed`)."""
        out = self.contains(points, min_hits)
        return out if tau is None else out | self.dynamic_observed(points, tau, window)

    def lookup(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinearly interpolated embeddings at points inside allocated voxels.

        Differentiable w.r.t. E and (through the trilinear weights) the points.

        Args:
            points: (P, 3) world points in metres.
        Returns:
            features (P_valid, Q) for the valid points, and valid (P,) bool mask.
        """
        g = points / self.voxel_size
        base = torch.floor(g.detach())
        # Points outside the hashable range (or non-finite) are simply not in the map.
        in_range = (base.abs() < _OFFSET - 1).all(-1)  # False for NaN and inf too
        keys = pack_coords(torch.where(in_range[:, None], base, torch.zeros_like(base)).long(), checked=False)
        pos, valid = sorted_lookup(self.voxel_keys, keys)
        valid &= in_range
        rows = self.voxel_corner_rows[pos[valid]]  # (Pv, 8)
        frac = g[valid] - base[valid]
        w = trilinear_weights(frac)  # (Pv, 8)
        # One kernel for gather, weights and sum, and a backward that adds rows into E's gradient:
        # 2-3x faster on CPU than E[rows] (whose backward is an accumulating index_put).
        return F.embedding_bag(rows, self.embeddings, mode="sum", per_sample_weights=w.to(self.embeddings.dtype)), valid

    def load_sparse_state(self, state: dict[str, torch.Tensor]) -> None:
        """Load a state dict whose tensors may be larger than this (fresh) grid's."""
        self.embeddings.data = state["embeddings"].clone()
        for name in ("voxel_keys", "voxel_corner_rows", "corner_keys", "corner_rows"):
            setattr(self, name, state[name].clone())
        # Checkpoints from before hit counting: treat every voxel as observed.
        self.voxel_hits = state.get("voxel_hits", torch.ones_like(self.voxel_keys, dtype=torch.int32)).clone()
        self.dynamic_keys = state.get("dynamic_keys", torch.zeros(0, dtype=torch.long)).clone()
        self.dynamic_tau = state.get("dynamic_tau", torch.zeros(0, dtype=torch.float32)).clone()
        self.surface_keys = state.get("surface_keys", torch.zeros(0, dtype=torch.long)).clone()  # older maps: none

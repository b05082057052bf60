"""Where the map grows: voxels are allocated where a frame's depth lands (static depth adds hits and
marks surface cells, moving depth adds (voxel, τ) rows; :meth:`SparseVoxelGrid.allocate`)."""

from __future__ import annotations

import torch

from tivne.config import AllocationConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import backproject
from tivne.render.rays import View


class VoxelAllocator:
    """Back-projects every ``allocation.stride``-th pixel (both axes) of a view with depth and
    allocates the voxels it lands in, ``allocation.dilation`` voxels around them too."""

    def __init__(self, cfg: AllocationConfig = AllocationConfig()) -> None:
        self.cfg = cfg

    @torch.no_grad()
    def allocate(self, field: TimeVaryingField, view: View, K: torch.Tensor) -> None:
        """Through the field's own ``allocate`` (an object field routes moving depth into the
        objects' grids, in their coordinates)."""
        s = self.cfg.stride
        depth = view.depth[::s, ::s]
        h, w = depth.shape
        v, u = torch.meshgrid(torch.arange(h, device=depth.device) * s, torch.arange(w, device=depth.device) * s, indexing="ij")
        valid = depth > 0
        cam = backproject(torch.stack([u[valid], v[valid]], dim=-1).float(), depth[valid], K)
        world = (view.pose[:3, :3] @ cam.T).T + view.pose[:3, 3]
        dynamic = None if view.dynamic is None else view.dynamic[::s, ::s][valid]
        field.allocate(world, dynamic, view.tau, dilation=self.cfg.dilation)

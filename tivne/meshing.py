"""Mesh extraction at any time τ: marching cubes restricted to allocated voxels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage import measure

from tivne.field.networks import TimeVaryingField


@torch.no_grad()
def query_field(field: TimeVaryingField, points: torch.Tensor, tau: float, chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
    """SDF (P,) and colour (P, 3) of the field at (P, 3) world points at time τ, in chunks."""
    sdf, rgb = [], []
    for start in range(0, points.shape[0], chunk):
        p = points[start : start + chunk]
        out = field(p, torch.full((p.shape[0],), float(tau), device=p.device, dtype=p.dtype))
        sdf.append(out.sdf)
        rgb.append(out.rgb)
    if not sdf:
        return points.new_zeros(0), points.new_zeros(0, 3)
    return torch.cat(sdf), torch.cat(rgb)


@torch.no_grad()
def extract_mesh(field: TimeVaryingField, tau: float, resolution: float = 0.02, chunk: int = 65536) -> trimesh.Trimesh:
    """Zero level set of the field at τ as one welded, vertex-coloured mesh in world metres.

    A lattice of step ``resolution`` spans the allocated voxels' bounding box; the field is evaluated
    only at lattice points inside allocated voxels, and marching cubes runs only on cells whose
    corners are all evaluated, so no surface appears where the map knows nothing.
    """
    grid = field.grid
    device = grid.voxel_keys.device
    if grid.num_voxels == 0:
        return trimesh.Trimesh()
    coords = grid.voxel_coords().double()
    lo = coords.min(0).values * grid.voxel_size
    hi = (coords.max(0).values + 1) * grid.voxel_size
    dims = torch.ceil((hi - lo) / resolution).long() + 1
    axes = [lo[i] + resolution * torch.arange(int(dims[i]), dtype=torch.float64) for i in range(3)]
    lattice = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).float().to(device)
    inside = grid.contains(lattice)
    volume = torch.ones(lattice.shape[0], device=device)
    sdf, _ = query_field(field, lattice[inside], tau, chunk)
    volume[inside] = sdf
    volume_np = volume.reshape(*dims.tolist()).cpu().numpy()
    mask_np = inside.reshape(*dims.tolist()).cpu().numpy()
    if not ((volume_np[mask_np] < 0).any() and (volume_np[mask_np] > 0).any()):
        return trimesh.Trimesh()
    verts, faces, _, _ = measure.marching_cubes(volume_np, level=0.0, spacing=(resolution,) * 3, mask=mask_np)
    verts = verts + lo.numpy()[None]
    _, rgb = query_field(field, torch.as_tensor(verts, dtype=torch.float32, device=device), tau, chunk)
    colors = np.concatenate([(rgb.clamp(0, 1).cpu().numpy() * 255).astype(np.uint8), np.full((len(verts), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False)


def save_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write a PLY atomically (tmp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.ply")
    mesh.export(tmp)
    tmp.replace(path)
    return path

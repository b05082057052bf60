"""Seeds of the model-free motion mask: pixels whose observation contradicts what was seen before.

A static world predicts each pixel's depth from an earlier frame (:func:`free_space_seeds`) or from
the map (:func:`march_map_depth` + :func:`residual_seeds`). Only the sign "observed in front of what
was seen" seeds: something now occupies space that was free, i.e. the moving object's current
pixels, not the background it uncovered. Thresholds follow the sensor's depth noise
(:func:`data_modules.sensor.kinect_depth_sigma`).
"""

from __future__ import annotations

import numpy as np
import torch

from data_modules.sensor import kinect_depth_sigma
from tivne.geometry import backproject, depth_lookup, pixel_grid, transform_points
from tivne.render.rays import rays_from_pixels


def residual_seeds(
    observed: torch.Tensor,
    rendered: torch.Tensor,
    known: torch.Tensor,
    abs_threshold: float = 0.08,
    k_sigma: float = 6.0,
    color_residual: torch.Tensor | None = None,
    color_threshold: float | None = None,
) -> torch.Tensor:
    """Pixels where the observation is *in front of* the map: something now occupies space the map
    saw as free. That sign marks the moving object's current pixels; the opposite sign (observed
    behind the map) is disoccluded background where the object was and is left out.

    Args:
        observed, rendered: (H, W) depth in metres (0 = invalid observation).
        known: (H, W) bool, the map has a surface along the ray (not newly observed space).
        color_residual: optional (H, W) colour L1 (mean over channels); flags pixels whose depth
            agrees with the map (|r| < threshold) but whose colour does not.
    Returns:
        (H, W) bool.
    """
    thr = torch.clamp(k_sigma * kinect_depth_sigma(observed), min=abs_threshold)
    valid = known & (observed > 0)
    seeds = valid & (rendered - observed > thr)
    if color_residual is not None and color_threshold is not None and color_threshold > 0:
        seeds = seeds | (valid & ((observed - rendered).abs() <= thr) & (color_residual > color_threshold))
    return seeds


@torch.no_grad()
def free_space_seeds(
    depth: torch.Tensor,
    pose: torch.Tensor,
    ref_depth: torch.Tensor,
    ref_pose: torch.Tensor,
    K: torch.Tensor,
    abs_threshold: float = 0.08,
    k_sigma: float = 6.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixels whose observed point lies in space an earlier frame saw as free (static-world test).

    Each valid pixel is back-projected with ``depth`` and ``pose``, moved into the reference camera
    and compared with the reference depth there (the minimum over a 3x3 neighbourhood, so static
    silhouettes do not fire): ``z_ref(X) < d_ref - thr`` means the point was empty space then, so
    something moved *into* it -- the moving object's current pixels. Disoccluded background
    (``z_ref(X) > d_ref``) is not flagged.

    Args:
        depth, ref_depth: (H, W) metres, 0 = invalid. pose, ref_pose: (4, 4) c2w. K: (3, 3) for (H, W).
    Returns:
        seeds (H, W) bool, known (H, W) bool (the reference saw the point's pixel), and residual
        (H, W) float: (z_ref(X) - d_ref) / σ(d_ref) at the nearest reference pixel (no 3x3 minimum;
        NaN where not known), the signed static-world residual in noise units.
    """
    h, w = depth.shape
    # The grid in K's dtype: the points come out in the dtype K and depth promote to.
    cam = backproject(pixel_grid(h, w, depth.device, K.dtype), depth, K).reshape(-1, 3)
    rel = torch.linalg.solve(ref_pose.to(cam.dtype), pose.to(cam.dtype))  # current camera -> reference camera
    z, inb, d_ref, d_centre = depth_lookup(transform_points(rel, cam), ref_depth.to(cam.dtype), K)
    known = inb & torch.isfinite(d_ref) & (depth.reshape(-1) > 0)
    thr = torch.clamp(k_sigma * kinect_depth_sigma(d_ref.clamp(max=20.0)), min=abs_threshold)
    seeds = known & (z < d_ref - thr)
    scored = known & (d_centre > 0)
    residual = torch.full_like(z, float("nan"))
    residual[scored] = (z[scored] - d_centre[scored]) / kinect_depth_sigma(d_centre[scored])
    return seeds.view(h, w), known.view(h, w), residual.view(h, w)


@torch.no_grad()
def march_map_depth(
    field: torch.nn.Module,
    pose: torch.Tensor,
    K: torch.Tensor,
    uv: torch.Tensor,
    tau: float,
    near: float,
    far: float,
    step: float,
    chunk: int = 4096,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where the map's first surface lies along pixel rays (sphere-free SDF marching).

    Samples every ``step`` metres in [near, far], finds the first + to - sign change of the SDF among
    allocated samples (unallocated space counts as free) and interpolates linearly.

    Args:
        uv: (N, 2) pixel coordinates. pose: (4, 4) c2w.
    Returns:
        depth (N,) z-depth of the surface (0 where none), known (N,) bool, rgb (N, 3) at the surface.
    """
    n_s = max(int(np.ceil((far - near) / step)) + 1, 2)
    z = torch.linspace(near, far, n_s, device=uv.device, dtype=K.dtype)
    out_d, out_k, out_c = [], [], []
    per = max(chunk // n_s, 64)  # rays per forward pass
    for start in range(0, uv.shape[0], per):
        o, d = rays_from_pixels(uv[start : start + per].to(K.dtype), K, pose)
        pts = o[:, None, :] + d[:, None, :] * z[None, :, None]
        m = pts.shape[0]
        f = field(pts.reshape(-1, 3), torch.full((m * n_s,), float(tau), device=uv.device, dtype=K.dtype))
        sdf = torch.where(f.valid, f.sdf, torch.ones_like(f.sdf)).view(m, n_s)
        crossing = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0) & f.valid.view(m, n_s)[:, 1:]
        has = crossing.any(dim=1)
        i = crossing.float().argmax(dim=1)
        s0 = sdf.gather(1, i[:, None])[:, 0]
        s1 = sdf.gather(1, (i + 1)[:, None])[:, 0]
        frac = (s0 / (s0 - s1).clamp_min(1e-6)).clamp(0, 1)
        depth = torch.where(has, z[i] + frac * (z[1] - z[0]), torch.zeros_like(s0))
        rgb = f.rgb.view(m, n_s, 3)
        c = rgb.gather(1, (i + 1)[:, None, None].expand(-1, 1, 3))[:, 0]
        out_d.append(depth)
        out_k.append(has)
        out_c.append(c)
    return torch.cat(out_d), torch.cat(out_k), torch.cat(out_c)

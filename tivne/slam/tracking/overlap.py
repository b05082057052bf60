"""Reprojection overlap between views (paper Eq. 11): how much of one frame another camera sees,
and which stored cameras see a view. Used by the keyframe policy, the tracker's stored references
and the pose graph's loop candidates."""

from __future__ import annotations

import torch

from tivne.geometry import backproject, invert_pose, pose_difference, project, transform_points
from tivne.render.rays import View


def overlap_ratios(
    uv: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, kf_c2w: torch.Tensor, width: int, height: int
) -> torch.Tensor:
    """Share of the current frame's sampled pixels that reproject inside each keyframe (paper Eq. 11).

    u_kf = K · T_w2c(kf) · T_c2w(cur) · K⁻¹ · u, counted when it lands inside the image with positive depth.

    Args:
        uv: (N, 2) sampled pixels of the current frame; depth: (N,) their depths (> 0).
        K: (3, 3); c2w: (4, 4) current pose; kf_c2w: (F, 4, 4) keyframe poses.
    Returns:
        (F,) ratios in [0, 1].
    """
    world = transform_points(c2w, backproject(uv, depth, K))  # (N, 3)
    cam = transform_points(invert_pose(kf_c2w)[:, None], world[None])  # (F, N, 3)
    uv_kf, z = project(cam, K)
    inside = (z > 0) & (uv_kf[..., 0] >= 0) & (uv_kf[..., 0] <= width - 1) & (uv_kf[..., 1] >= 0) & (uv_kf[..., 1] <= height - 1)
    return inside.float().mean(dim=1)


def view_overlaps(new: View, poses: list[torch.Tensor], K: torch.Tensor, pixels: int = 256) -> torch.Tensor:
    """(F,) share of ``new``'s static pixels with depth (a regular subset of about ``pixels``) that
    reproject inside the image of a camera at each of ``poses`` ((4, 4) c2w) (:func:`overlap_ratios`)."""
    usable = new.depth > 0
    if new.dynamic is not None:
        usable = usable & ~new.dynamic
    idx = usable.reshape(-1).nonzero()[:, 0]
    if idx.numel() == 0 or not poses:
        return torch.zeros(len(poses))
    idx = idx[:: max(1, idx.numel() // pixels)]
    h, w = new.depth.shape
    dtype = new.depth.dtype
    uv = torch.stack([idx % w, idx // w], dim=-1).to(dtype)
    stacked = torch.stack([p.to(dtype) for p in poses])
    return overlap_ratios(uv, new.depth.reshape(-1)[idx], K.to(dtype), new.pose.to(dtype), stacked, w, h).cpu()


def views_seeing(
    view: View, stored: list[torch.Tensor], K: torch.Tensor, max_m: float, max_deg: float, min_overlap: float
) -> list[tuple[int, float]]:
    """(index, overlap), in their order, of the ``stored`` c2w poses ((4, 4), e.g. oldest first)
    whose camera was within ``max_m`` / ``max_deg`` of ``view.pose`` and whose image holds at least
    ``min_overlap`` of the view's static pixels with depth (reprojected at the current poses)."""
    near = [i for i, pose in enumerate(stored) if (d := pose_difference(pose, view.pose))[0] <= max_m and d[1] <= max_deg]
    ratios = view_overlaps(view, [stored[i] for i in near], K).tolist() if near else []
    return [(i, r) for i, r in zip(near, ratios) if r >= min_overlap]

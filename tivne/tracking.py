"""Camera tracking: optimise only the current pose against the frozen map."""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from tivne.field.networks import TimeVaryingField
from tivne.geometry import invert_pose, orthonormalize_pose, se3_exp
from tivne.keyframes import View
from tivne.losses import LossWeights, robust_ray_mask, slam_loss
from tivne.rendering import RenderConfig, gather_rays, render_rays
from tivne.sampling import PixelPool, depth_guided_depths, draw


@dataclass(frozen=True)
class TrackingConfig:
    """iters: optimiser steps per frame. rays: pixels (one fixed set per frame, so the best-loss
    iterate is comparable). motion_model: 'zero' (paper) or 'constant_velocity' initialisation.
    outlier_factor: rays with depth residual > factor x median are dropped (<= 0 disables).
    exclude_dynamic: draw no tracking rays from masked pixels.
    query_time: 'last_mapped' renders the map at the latest time it was trained on (the best
    prediction of a not-yet-mapped frame; moving pixels become outliers), 'frame' at the frame's own
    τ (extrapolating the deformation field).
    stratified: jitter samples each iteration; off, the loss is a deterministic function of the pose,
    so the best-iterate choice is not decided by sampling noise. lr_final_factor: the learning rate
    decays exponentially to this fraction over the iterations (fine steps near convergence)."""

    iters: int = 30
    rays: int = 512
    lr_rot: float = 2e-3
    lr_trans: float = 2e-3
    motion_model: str = "constant_velocity"
    outlier_factor: float = 10.0
    keep_best: bool = True
    exclude_dynamic: bool = True
    query_time: str = "last_mapped"
    stratified: bool = False
    lr_final_factor: float = 0.1

    def __post_init__(self) -> None:
        if self.query_time not in ("last_mapped", "frame"):
            raise ValueError(f"tracking.query_time must be 'last_mapped' or 'frame', got {self.query_time!r}")
        if self.motion_model not in ("zero", "constant_velocity"):
            raise ValueError(f"tracking.motion_model must be 'zero' or 'constant_velocity', got {self.motion_model!r}")


def predict_pose(previous: list[torch.Tensor], motion_model: str) -> torch.Tensor:
    """Initial pose from the last tracked poses (c2w): zero motion, or T_{k-1} T_{k-2}⁻¹ T_{k-1}."""
    if motion_model == "constant_velocity" and len(previous) >= 2:
        return orthonormalize_pose(previous[-1] @ invert_pose(previous[-2]) @ previous[-1])
    return previous[-1].clone()


@contextmanager
def frozen(module: torch.nn.Module):
    """Disable gradients of a module's parameters (the map) for the duration of the block."""
    flags = [p.requires_grad for p in module.parameters()]
    module.requires_grad_(False)
    try:
        yield
    finally:
        for p, f in zip(module.parameters(), flags):
            p.requires_grad_(f)


def track_frame(
    field: TimeVaryingField,
    view: View,
    K: torch.Tensor,
    render: RenderConfig,
    weights: LossWeights,
    cfg: TrackingConfig,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Optimise T = T_init · exp(ξ) (a camera-frame delta ξ) with the map frozen.

    ``view.pose`` is the initial pose. Returns the tracked c2w pose and statistics.
    """
    pool = PixelPool.from_masks(view.depth > 0, view.dynamic if cfg.exclude_dynamic else None)
    pixels = draw(pool.static, cfg.rays, generator)
    images = [(view.rgb, view.depth, view.dynamic, view.tau)]
    init = view.pose.detach()
    rot = torch.zeros(1, 3, device=init.device, dtype=init.dtype, requires_grad=True)
    trans = torch.zeros(1, 3, device=init.device, dtype=init.dtype, requires_grad=True)
    opt = torch.optim.Adam([{"params": [rot], "lr": cfg.lr_rot}, {"params": [trans], "lr": cfg.lr_trans}])
    gamma = cfg.lr_final_factor ** (1.0 / max(cfg.iters - 1, 1))
    schedule = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    no_offset = LossWeights(weights.color, weights.depth, weights.free_space, weights.sdf, offset=0.0)
    best_loss, best_pose, last_loss, kept, nonfinite = float("inf"), init, float("nan"), 0.0, 0
    with frozen(field):
        for _ in range(cfg.iters):
            pose = init @ se3_exp(torch.cat([trans, rot], dim=-1))[0]
            rays = gather_rays([pixels], images, pose[None], K)
            z = depth_guided_depths(rays.depth, render.truncation, render.n_band, render.n_free, render.band, render.near, cfg.stratified, generator)
            rendered, outputs = render_rays(field, rays, z, render.truncation)
            mask = robust_ray_mask(rendered, rays.depth, cfg.outlier_factor)
            loss, _ = slam_loss(rays, z, rendered, outputs, render.truncation, no_offset, mask)
            last_loss = float(loss.detach())
            if not math.isfinite(last_loss) or not loss.requires_grad:  # diverged or off the map: keep the best pose so far
                nonfinite += 1
                break
            if last_loss < best_loss:
                best_loss, best_pose, kept = last_loss, pose.detach(), float(mask.float().mean())
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if not (torch.isfinite(rot.grad).all() and torch.isfinite(trans.grad).all()):
                nonfinite += 1
                break
            opt.step()
            schedule.step()
    final = best_pose if cfg.keep_best or nonfinite else (init @ se3_exp(torch.cat([trans, rot], dim=-1))[0]).detach()
    return orthonormalize_pose(final), {"loss": best_loss, "last_loss": last_loss, "inlier_ratio": kept, "nonfinite": float(nonfinite)}

"""The paper's field tracker: optimise only the current pose against the frozen map; the motion model."""

from __future__ import annotations

import math
from contextlib import contextmanager

import torch

from tivne.config import FieldTrackingConfig, LossWeights, RenderConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import invert_pose, orthonormalize_pose, se3_exp, se3_log
from tivne.render.losses import robust_ray_mask, slam_loss
from tivne.render.rays import View
from tivne.render.renderer import render_pixels
from tivne.render.samplers import PixelPool, draw
from tivne.slam.tracking.result import FieldTrackStats


def predict_pose(previous: list[torch.Tensor], motion_model: str, steps: float = 1.0) -> torch.Tensor:
    """Initial pose from the last poses (c2w, (4, 4) each, oldest first): zero motion, or constant
    velocity, the last step D = T_{k-1} T_{k-2}⁻¹ carried on for ``steps`` of its own duration,
    exp(steps · log D) T_{k-1} (D T_{k-1} at steps = 1): the time to this frame over the time
    between the last two, so frames a recorder dropped neither stretch nor shrink the velocity."""
    if motion_model == "constant_velocity" and len(previous) >= 2:
        step = previous[-1] @ invert_pose(previous[-2])
        if abs(steps - 1.0) > 1e-6:  # else the one-step product as it is, not through log and exp
            step = se3_exp(steps * se3_log(step.double())).to(step.dtype)
        return orthonormalize_pose(step @ previous[-1])
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
    cfg: FieldTrackingConfig,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, FieldTrackStats]:
    """Optimise T = T_init · exp(ξ) (a camera-frame delta ξ) with the map frozen.

    ``view.pose`` is the initial pose. Returns the tracked c2w pose and its statistics.
    """
    pool = PixelPool.from_masks(view.depth > 0, view.dynamic if cfg.exclude_dynamic else None)
    pixels = [draw(pool.static, cfg.rays, generator)]
    init = view.pose.detach()
    rot = torch.zeros(1, 3, device=init.device, dtype=init.dtype, requires_grad=True)
    trans = torch.zeros(1, 3, device=init.device, dtype=init.dtype, requires_grad=True)
    opt = torch.optim.Adam([{"params": [rot], "lr": cfg.lr_rot}, {"params": [trans], "lr": cfg.lr_trans}])
    gamma = cfg.lr_final_factor ** (1.0 / max(cfg.iters - 1, 1))
    schedule = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    no_offset = weights.without_offset()
    best_loss, best_pose, last_loss, kept, nonfinite = float("inf"), init, float("nan"), 0.0, 0
    with frozen(field):
        for _ in range(cfg.iters):
            pose = init @ se3_exp(torch.cat([trans, rot], dim=-1))[0]
            batch = render_pixels(field, [view], pixels, pose[None], K, render, cfg.stratified, generator)
            mask = robust_ray_mask(batch.rendered, batch.rays.depth, cfg.outlier_factor)
            loss, _ = slam_loss(batch, render.truncation, no_offset, mask)
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
    return orthonormalize_pose(final), FieldTrackStats(best_loss, last_loss, kept, nonfinite)

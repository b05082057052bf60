"""Stages 3-4 of the render path: query the field at the samples and composite (paper Eq. 3-5).

The one render path of the system: tracking, mapping and image rendering all call
:func:`render_pixels` (pixels of views -> :class:`RenderBatch`); :func:`render_image` renders every
pixel of a view with it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from tivne.config import RenderConfig
from tivne.field.networks import FieldOutputs, TimeVaryingField
from tivne.render.rays import RayBundle, View, bundle_rays
from tivne.render.samplers import PixelPool, place_samples


@dataclass
class RenderedRays:
    """rgb (N, 3), depth (N,), depth_var (N,) = Σ w (z - D)², weight_sum (N,) before normalisation."""

    rgb: torch.Tensor
    depth: torch.Tensor
    depth_var: torch.Tensor
    weight_sum: torch.Tensor


def bell_weights(sdf: torch.Tensor, sharpness: float) -> torch.Tensor:
    """w = σ(s·k) σ(-s·k) with k = 1/tr (paper Eq. 4); sdf (N, M) in truncation units -> (N, M)."""
    x = sdf * sharpness
    return torch.sigmoid(x) * torch.sigmoid(-x)


def first_surface_mask(
    sdf: torch.Tensor, z: torch.Tensor, truncation: float, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Keep samples up to one truncation behind the first + to - zero crossing (Vox-Fusion).

    Args:
        sdf: (N, M), z: (N, M) ascending.
        valid: (N, M) bool, sample inside the map; a crossing counts only between two valid
            samples, so the fill value of unmapped samples never fakes a surface (a ray entering a
            negative region from unmapped space would otherwise render nothing and never be corrected).
    Returns:
        (N, M) bool. Rays without a crossing keep every sample.
    """
    sign_change = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0)
    if valid is not None:
        sign_change &= valid[:, :-1] & valid[:, 1:]
    has = sign_change.any(dim=1)
    first = sign_change.float().argmax(dim=1)
    z_first = torch.gather(z, 1, first[:, None])
    keep = z <= z_first + truncation
    return keep | ~has[:, None]


def composite(weights: torch.Tensor, rgb: torch.Tensor, z: torch.Tensor, eps: float = 1e-8) -> RenderedRays:
    """Normalised compositing (paper Eq. 5).

    Args:
        weights: (N, M) unnormalised, rgb: (N, M, 3), z: (N, M).
    """
    wsum = weights.sum(dim=1)
    w = weights / (wsum[:, None] + eps)
    depth = (w * z).sum(dim=1)
    color = (w[..., None] * rgb).sum(dim=1)
    var = (w * (z - depth[:, None]).pow(2)).sum(dim=1)
    return RenderedRays(rgb=color, depth=depth, depth_var=var, weight_sum=wsum)


def render_samples(
    field: TimeVaryingField, rays: RayBundle, z: torch.Tensor, truncation: float
) -> tuple[RenderedRays, FieldOutputs]:
    """Query the field at samples ``z`` (N, M) along ``rays`` and composite.

    Returns the rendered rays and the field outputs reshaped to (N, M[, C]).
    """
    n, m = z.shape
    points = rays.origins[:, None, :] + rays.directions[:, None, :] * z[..., None]  # (N, M, 3)
    tau = rays.tau[:, None].expand(n, m)
    out = field(points.reshape(-1, 3), tau.reshape(-1))
    sdf = out.sdf.view(n, m)
    rgb = out.rgb.view(n, m, 3)
    valid = out.valid.view(n, m)
    weights = bell_weights(sdf, 1.0 / truncation) * valid
    weights = weights * first_surface_mask(sdf, z, truncation, valid)
    rendered = composite(weights, rgb, z)
    parts = None if out.parts is None else out.parts.view(n, m, 2)
    return rendered, FieldOutputs(sdf=sdf, rgb=rgb, valid=valid, offset_sq=out.offset_sq.view(n, m), parts=parts)




@dataclass
class RenderBatch:
    """Everything one render of a pixel batch produced: the rays, their sample depths z (N, M), the
    field at the samples (shaped (N, M[, C])) and the composited rays. The losses read all four."""

    rays: RayBundle
    z: torch.Tensor
    outputs: FieldOutputs
    rendered: RenderedRays


def render_pixels(
    field: TimeVaryingField,
    views: Sequence[View],
    pixels: Sequence[torch.Tensor],
    poses: torch.Tensor,
    K: torch.Tensor,
    cfg: RenderConfig,
    stratified: bool,
    generator: torch.Generator | None = None,
) -> RenderBatch:
    """Render the given pixels of ``views`` from camera ``poses``.

    Args:
        views: V views; pixels: per view, (n_v,) flat pixel indices with valid depth.
        poses: (V, 4, 4) c2w (may carry gradients: tracking and pose refinement differentiate them).
        K: (3, 3). cfg: sample placement and truncation. stratified: jitter the samples.
    """
    rays = bundle_rays(views, pixels, poses, K)
    z = place_samples(rays.depth, cfg, stratified, generator)
    rendered, outputs = render_samples(field, rays, z, cfg.truncation)
    return RenderBatch(rays, z, outputs, rendered)


@torch.no_grad()
def render_image(
    field: TimeVaryingField, view: View, K: torch.Tensor, cfg: RenderConfig, stride: int = 1
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render colour and depth at ``view.pose`` for every ``stride``-th pixel with observed depth.

    Samples are placed around the observed depth, so pixels without it stay 0.

    Returns:
        rgb (H', W', 3) and depth (H', W') at the strided resolution.
    """
    small = View(view.frame_id, view.tau, view.rgb[::stride, ::stride], view.depth[::stride, ::stride], None, view.pose)
    Ks = K.clone()
    Ks[:2] /= stride  # pixel (i*s) of the frame is pixel i here
    h, w = small.depth.shape
    pool = PixelPool.from_masks(small.depth > 0, None)
    rgb = small.depth.new_zeros(h * w, 3)
    depth = small.depth.new_zeros(h * w)
    for start in range(0, pool.valid.numel(), cfg.chunk):
        idx = pool.valid[start : start + cfg.chunk]
        batch = render_pixels(field, [small], [idx], view.pose[None], Ks, cfg, stratified=False)
        rgb[idx] = batch.rendered.rgb
        depth[idx] = batch.rendered.depth
    return rgb.view(h, w, 3), depth.view(h, w)

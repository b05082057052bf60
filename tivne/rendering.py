"""SDF volume rendering along z = 1 rays (paper Eq. 3-5): stage objects and pure functions."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tivne.field.networks import FieldOutputs, TimeVaryingField
from tivne.geometry import pixel_to_ray


@dataclass(frozen=True)
class RenderConfig:
    """Where samples go along a ray and how sharp the surface is.

    truncation: tr in metres (SDF band and bell width). band: samples span D ± band·tr.
    n_band / n_free: samples in the band / in free space in front of it. near: closest depth.
    chunk: rays per forward pass when rendering whole images.
    """

    truncation: float = 0.05
    band: float = 2.0
    n_band: int = 12
    n_free: int = 4
    near: float = 0.05
    chunk: int = 8192


@dataclass
class RayBundle:
    """N rays with their observations.

    origins: (N, 3) world camera centres. directions: (N, 3) world directions whose camera-frame z
    is 1, so the ray parameter is z-depth. tau: (N,) normalised time. rgb: (N, 3) observed colour.
    depth: (N,) observed z-depth (> 0). dynamic: (N,) bool, pixel on a moving object (False without
    masks). has_mask: whether ``dynamic`` comes from a motion mask.
    """

    origins: torch.Tensor
    directions: torch.Tensor
    tau: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor
    dynamic: torch.Tensor
    has_mask: bool = False

    def __len__(self) -> int:
        return int(self.origins.shape[0])


@dataclass
class RenderedRays:
    """rgb (N, 3), depth (N,), depth_var (N,) = Σ w (z - D)², weight_sum (N,) before normalisation."""

    rgb: torch.Tensor
    depth: torch.Tensor
    depth_var: torch.Tensor
    weight_sum: torch.Tensor


def rays_from_pixels(uv: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through pixels.

    Args:
        uv: (N, 2) pixel coordinates.
        K: (3, 3).
        c2w: (4, 4) or (N, 4, 4) camera-to-world.
    Returns:
        origins (N, 3), directions (N, 3) with camera-frame z = 1.
    """
    d_cam = pixel_to_ray(uv, K)
    R = c2w[..., :3, :3]
    directions = (R @ d_cam[..., None])[..., 0]
    origins = c2w[..., :3, 3].expand_as(directions)
    return origins, directions


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


def render_rays(
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
    return rendered, FieldOutputs(sdf=sdf, rgb=rgb, valid=valid, offset_sq=out.offset_sq.view(n, m))


def gather_rays(
    pixels: list[torch.Tensor],
    images: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, float]],
    poses: torch.Tensor,
    K: torch.Tensor,
) -> RayBundle:
    """Rays of several views in one bundle (one forward pass for the whole mapping window).

    Args:
        pixels: per view, (n_v,) flat pixel indices.
        images: per view, (rgb (H, W, 3), depth (H, W), dynamic (H, W) bool or None, tau).
        poses: (V, 4, 4) c2w, may carry gradients.
        K: (3, 3).
    """
    uv, rgb, depth, dyn, tau, view = [], [], [], [], [], []
    has_mask = False
    for v, (idx, (img, dep, dmask, t)) in enumerate(zip(pixels, images)):
        w = dep.shape[1]
        uv.append(torch.stack([idx % w, idx // w], dim=-1))
        rgb.append(img.reshape(-1, 3)[idx])
        depth.append(dep.reshape(-1)[idx])
        if dmask is not None:
            has_mask = True
            dyn.append(dmask.reshape(-1)[idx])
        else:
            dyn.append(torch.zeros_like(idx, dtype=torch.bool))
        tau.append(torch.full_like(depth[-1], t))
        view.append(torch.full_like(idx, v))
    view_idx = torch.cat(view)
    origins, directions = rays_from_pixels(torch.cat(uv).to(K.dtype), K, poses[view_idx])
    return RayBundle(
        origins=origins,
        directions=directions,
        tau=torch.cat(tau),
        rgb=torch.cat(rgb),
        depth=torch.cat(depth),
        dynamic=torch.cat(dyn),
        has_mask=has_mask,
    )

"""Stage 1 of the render path: a frame as the map sees it (:class:`View`) and its rays (:class:`RayBundle`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from tivne.geometry import pixel_to_ray


def float_colour(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) colour as float in [0, 1]: uint8 scaled, float as it is."""
    return rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb


@dataclass(frozen=True)
class View:
    """A frame at the field's time ``tau`` with a camera-to-world pose: what tracking, mapping and
    image rendering need of it (frozen: a changed pose or mask is a new View).

    rgb (H, W, 3) float in [0, 1], or uint8 (stored keyframes); depth (H, W) metres, 0 = invalid; dynamic (H, W) bool (True = moving
    object) or None without a motion mask; pose (4, 4) c2w.
    """

    frame_id: int
    tau: float
    rgb: torch.Tensor
    depth: torch.Tensor
    dynamic: torch.Tensor | None
    pose: torch.Tensor

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    def colour(self) -> torch.Tensor:
        """(H, W, 3) float colour in [0, 1] (whichever way it is stored)."""
        return float_colour(self.rgb)


@dataclass
class RayBundle:
    """N rays with their observations.

    origins: (N, 3) world camera centres. directions: (N, 3) world directions whose camera-frame z
    is 1, so the ray parameter is z-depth. tau: (N,) field time. rgb: (N, 3) observed colour.
    depth: (N,) observed z-depth. dynamic: (N,) bool, pixel on a moving object (False without
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


def pixel_uv(pixels: torch.Tensor, width: int) -> torch.Tensor:
    """(N,) flat pixel indices of an image ``width`` wide -> (N, 2) (u, v) coordinates."""
    return torch.stack([pixels % width, pixels // width], dim=-1)


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


def bundle_rays(views: Sequence[View], pixels: Sequence[torch.Tensor], poses: torch.Tensor, K: torch.Tensor) -> RayBundle:
    """Rays of several views in one bundle (one forward pass for a whole mapping window).

    Args:
        views: V views; pixels: per view, (n_v,) flat pixel indices.
        poses: (V, 4, 4) c2w used for the rays (may carry gradients, may differ from ``view.pose``).
        K: (3, 3).
    """
    uv, rgb, depth, dyn, tau, owner = [], [], [], [], [], []
    for v, (view, idx) in enumerate(zip(views, pixels)):
        uv.append(pixel_uv(idx, view.width))
        colour = view.rgb.reshape(-1, 3)[idx]
        rgb.append(float_colour(colour))
        depth.append(view.depth.reshape(-1)[idx])
        dyn.append(view.dynamic.reshape(-1)[idx] if view.dynamic is not None else torch.zeros_like(idx, dtype=torch.bool))
        tau.append(torch.full_like(depth[-1], view.tau))
        owner.append(torch.full_like(idx, v))
    origins, directions = rays_from_pixels(torch.cat(uv).to(K.dtype), K, poses[torch.cat(owner)])
    return RayBundle(
        origins=origins,
        directions=directions,
        tau=torch.cat(tau),
        rgb=torch.cat(rgb),
        depth=torch.cat(depth),
        dynamic=torch.cat(dyn),
        has_mask=any(view.dynamic is not None for view in views),
    )

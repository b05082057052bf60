"""Exact noise-free rendering of a posed scene: depth, colour, per-object labels, incidence cosines.

Speed comes from two exact shortcuts: a primitive is ray-cast only over the pixel rectangle its
projected bounding box covers (a ray outside it cannot hit it), and planar faces look their texture
noise up in per-face tables (:class:`~data_modules.synthetic.textures.PlaneNoise`) built once per
sequence, since a face's local frame does not change when its object moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from data_modules.synthetic.scene import Hit, Placed, Rect, Room, raycast
from data_modules.synthetic.shapes import CURVED, Sphere, bound_half
from data_modules.synthetic.textures import PlaneNoise, Texture, fbm, shade

__all__ = ["TextureBank", "View", "pixel_flow", "pixel_rays", "render_view", "screen_rects"]


def pixel_rays(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> torch.Tensor:
    """(3, H, W) float64 camera-frame ray directions with z = 1 through every pixel centre,
    coordinate-major."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    return torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)])


_CORNER_SIGNS = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)


def screen_rects(placed: list[Placed], c2w: torch.Tensor, K: tuple[float, float, float, float], width: int,
                 height: int) -> list[Rect | None]:
    """Pixel rectangle that can see each primitive (None: entirely behind the camera or off-screen).

    The 8 corners of the primitive's bounding box are projected; if all lie in front of the camera,
    the hull of their projections contains the primitive's whole projection, so pixels outside the
    rounded-out rectangle cannot hit it. A box straddling the image plane gets the full image.
    """
    fx, fy, cx, cy = K
    R, o = c2w[:3, :3], c2w[:3, 3]
    out: list[Rect | None] = []
    for pr in placed:
        corners = pr.c + (_CORNER_SIGNS * torch.from_numpy(bound_half(pr.obj.shape))) @ pr.R.T
        cam = (corners - o) @ R
        z = cam[:, 2]
        if bool((z <= 0).all()):
            out.append(None)
            continue
        if bool((z <= 1e-6).any()):
            out.append((0, height, 0, width))
            continue
        u, v = fx * cam[:, 0] / z + cx, fy * cam[:, 1] / z + cy
        u0, u1 = max(0, math.floor(float(u.min()))), min(width, math.ceil(float(u.max())) + 1)
        v0, v1 = max(0, math.floor(float(v.min()))), min(height, math.ceil(float(v.max())) + 1)
        out.append((v0, v1, u0, u1) if u0 < u1 and v0 < v1 else None)
    return out


class TextureBank:
    """Texture and noise evaluator of every surface of a scene (tables built lazily, then reused).

    Surfaces are keyed ``(primitive id, face id)``; primitive 0 is the room.
    """

    def __init__(self, room: Room, placed: list[Placed]) -> None:
        self.room = room
        self.objects = {p.index: p.obj for p in placed}
        self._planes: dict[tuple[int, int], PlaneNoise] = {}

    def texture(self, prim: int, face: int) -> Texture:
        return self.room.textures[face] if prim == 0 else self.objects[prim].texture

    def noise(self, prim: int, face: int, local: torch.Tensor) -> torch.Tensor:
        """(N,) fbm value of (3, N) coordinate-major local points on surface ``(prim, face)``."""
        tex = self.texture(prim, face)
        if face == CURVED:
            return fbm(local.T, tex.salt, tex.scale)
        key = (prim, face)
        if key not in self._planes:
            axis = face // 2
            if prim == 0:
                lo, hi = np.asarray(self.room.lo), np.asarray(self.room.hi)
                offset = lo[axis] if face % 2 else hi[axis]  # the inward normal points away from its wall
            else:
                hi = bound_half(self.objects[prim].shape)
                lo, offset = -hi, (hi[axis] if face % 2 else -hi[axis])
            self._planes[key] = PlaneNoise(axis, float(offset), lo, hi, tex.salt, tex.scale)
        return self._planes[key](local)

    def normals(self, prim: int, face: int, local: torch.Tensor) -> torch.Tensor:
        """Local unit normals of (3, N) points on surface ``(prim, face)``: (3, 1) on a planar face
        (constant), (3, N) on a curved one (towards the outside of the object)."""
        if face != CURVED:
            n = torch.zeros(3, 1, dtype=torch.float64)
            n[face // 2, 0] = 1.0 if face % 2 else -1.0
            return n
        shape = self.objects[prim].shape
        if isinstance(shape, Sphere):
            return local / shape.radius
        return torch.cat([local[:2] / shape.radius, torch.zeros_like(local[2:])])  # cylinder side

    def colour(self, prim: torch.Tensor, face: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
        """Noise-free colour (N, 3) float32 of hits: primitive and face ids (N,), local points (3, N)."""
        group = prim * 8 + face
        counts = torch.bincount(group).tolist()
        # Few distinct small ids: numpy's stable (radix) sort of int16 is several times torch's argsort.
        order = torch.from_numpy(np.argsort(group.numpy().astype(np.int16), kind="stable"))
        rgb = torch.empty(prim.shape[0], 3, dtype=torch.float32)
        start = 0
        for g, count in enumerate(counts):
            if count == 0:
                continue
            idx = order[start : start + count]
            start += count
            p = local.index_select(1, idx)
            noise = self.noise(g // 8, g % 8, p)
            rgb.index_copy_(0, idx, shade(self.texture(g // 8, g % 8), noise, p, self.normals(g // 8, g % 8, p)))
        return rgb


@dataclass
class View:
    """A noise-free rendered view. depth (H, W) float64 z-depth; rgb (H, W, 3) float32 in [0, 1];
    prim (H, W) int64 primitive ids; cos (H, W) |cos| of the incidence angle."""

    depth: torch.Tensor
    rgb: torch.Tensor
    prim: torch.Tensor
    cos: torch.Tensor


def render_view(room: Room, placed: list[Placed], bank: TextureBank, c2w: torch.Tensor, rays_cam: torch.Tensor,
                K: tuple[float, float, float, float], colour: bool = True) -> View:
    """Ray-cast and shade one view.

    Args:
        c2w: (4, 4) camera-to-world pose.
        rays_cam: (3, H, W) camera-frame directions with z = 1 through the pixel centres of ``K``
            (:func:`pixel_rays`): the culling rectangles assume exactly this grid. For other rays use
            :func:`~data_modules.synthetic.scene.raycast` and :meth:`TextureBank.colour`.
        K: (fx, fy, cx, cy) of that pixel grid.
        colour: False skips shading (``rgb`` is then empty).
    """
    _, H, W = rays_cam.shape
    c2w = torch.as_tensor(c2w, dtype=torch.float64)
    dirs = (c2w[:3, :3] @ rays_cam.reshape(3, -1)).view(3, H, W)
    hit: Hit = raycast(room, placed, c2w[:3, 3], dirs, screen_rects(placed, c2w, K, W, H))
    rgb = torch.empty(0)
    if colour:
        rgb = bank.colour(hit.prim.reshape(-1), hit.face.reshape(-1), hit.local.reshape(3, -1)).reshape(H, W, 3)
    return View(hit.depth, rgb, hit.prim, hit.cos)


def pixel_flow(depth: torch.Tensor, labels: torch.Tensor, rays_cam: torch.Tensor, c2w_a: torch.Tensor,
               c2w_b: torch.Tensor, moves: list[torch.Tensor], K: tuple[float, float, float, float]) -> torch.Tensor:
    """Where each pixel's surface point of view a appears in view b: exact scene flow, projected.

    Args:
        depth: (H, W) z-depth of view a (finite). labels: (H, W) int object ids (0 = static).
        rays_cam: (3, H, W) the pixel grid's camera rays (:func:`pixel_rays`). c2w_a, c2w_b: (4, 4).
        moves: (4, 4) world motion of object k from a to b (``T_k(b) T_k(a)^-1``) at index k - 1.
        K: (fx, fy, cx, cy).
    Returns:
        (H, W, 2) float32 displacement (du, dv) in pixels; 0 where the point is behind camera b.
    """
    _, H, W = rays_cam.shape
    fx, fy, cx, cy = K
    p = c2w_a[:3, :3] @ (rays_cam * depth).reshape(3, -1) + c2w_a[:3, 3:]
    flat = labels.reshape(-1)
    for k, M in enumerate(moves, start=1):
        sel = flat == k
        p[:, sel] = M[:3, :3] @ p[:, sel] + M[:3, 3:]
    q = c2w_b[:3, :3].T @ (p - c2w_b[:3, 3:])
    z = q[2].clamp_min(1e-6)
    u = (fx * q[0] / z + cx).view(H, W) - rays_cam[0] * fx - cx
    v = (fy * q[1] / z + cy).view(H, W) - rays_cam[1] * fy - cy
    flow = torch.stack([u, v], dim=-1)
    return torch.where((q[2] > 1e-6).view(H, W, 1), flow, 0.0).to(torch.float32)

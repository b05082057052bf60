"""Solid primitives in their local frame: exact SDF, exact ray intersection, uniform surface samples.

Shapes are centred at the local origin: :class:`Box` (half extents), :class:`Sphere` (radius) and
:class:`Cylinder` (axis = local z, capped). Everything is float64. A face id is
``2 * axis + (normal > 0)`` for the planar faces (box faces, cylinder caps, room walls) and
:data:`CURVED` for curved surface (sphere, cylinder side).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "CURVED",
    "Box",
    "Cylinder",
    "Shape",
    "Sphere",
    "bound_half",
    "box_sdf",
    "planar_faces",
    "scaled",
    "shape_area",
    "shape_raycast",
    "shape_sample",
    "shape_sdf",
]

CURVED = 6
_EPS_T = 1e-9  # hits nearer than this along the ray are ignored


@dataclass(frozen=True)
class Box:
    half: tuple[float, float, float]


@dataclass(frozen=True)
class Sphere:
    radius: float


@dataclass(frozen=True)
class Cylinder:
    radius: float
    half_height: float


Shape = Box | Sphere | Cylinder


def scaled(shape: Shape, k: float) -> Shape:
    """The shape scaled by ``k`` > 0 about its centre."""
    if isinstance(shape, Box):
        return Box(tuple(float(h) * k for h in shape.half))
    if isinstance(shape, Sphere):
        return Sphere(shape.radius * k)
    return Cylinder(shape.radius * k, shape.half_height * k)


def bound_half(shape: Shape) -> np.ndarray:
    """(3,) half extents of the shape's local axis-aligned bounding box (tight)."""
    if isinstance(shape, Box):
        return np.asarray(shape.half, dtype=np.float64)
    if isinstance(shape, Sphere):
        return np.full(3, shape.radius, dtype=np.float64)
    return np.array([shape.radius, shape.radius, shape.half_height], dtype=np.float64)


def box_sdf(p: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """Exact signed distance of (N, 3) local points to a box of ``half`` (3,) extents -> (N,)."""
    q = p.abs() - half
    return q.clamp_min(0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0)


def shape_sdf(shape: Shape, p: torch.Tensor) -> torch.Tensor:
    """Exact signed distance (N,) of (N, 3) local points to the solid (negative inside)."""
    if isinstance(shape, Box):
        return box_sdf(p, torch.tensor(shape.half, dtype=p.dtype))
    if isinstance(shape, Sphere):
        return p.norm(dim=-1) - shape.radius
    d = torch.stack([p[:, :2].norm(dim=-1) - shape.radius, p[:, 2].abs() - shape.half_height], dim=-1)
    return d.clamp_min(0).norm(dim=-1) + d.max(dim=-1).values.clamp_max(0)


def _safe(x: torch.Tensor) -> torch.Tensor:
    """Replace near-zero direction components so slab divisions stay finite."""
    return torch.where(x.abs() < 1e-12, 1e-12, x)


Ray = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def shape_raycast(shape: Shape, o: torch.Tensor, d: torch.Tensor) -> Ray:
    """First entry of rays into the solid, in its local frame.

    Ray tests are coordinate-major, (3, N), so every per-axis operation runs on contiguous rows.

    Args:
        o: (3,) ray origin (outside the solid).
        d: (3, N) ray directions (any length; the ray parameter scales with it).
    Returns:
        t (N,) ray parameter of the hit (inf = miss), face (N,) int64 face id of the hit, and
        incidence (N,) ``|n . d|`` with the unit surface normal n (both arbitrary where missed).
    """
    if isinstance(shape, Box):
        return _box_raycast(torch.tensor(shape.half, dtype=d.dtype)[:, None], o[:, None], d)
    if isinstance(shape, Sphere):
        return _sphere_raycast(shape.radius, o, d)
    return _cylinder_raycast(shape.radius, shape.half_height, o, d)


def _box_raycast(h: torch.Tensor, o: torch.Tensor, d: torch.Tensor) -> Ray:
    """Slab test (h, o: (3, 1)); see :func:`shape_raycast`."""
    d = _safe(d)
    t1 = (-h - o) / d
    t2 = (h - o) / d
    tmin, tmax = torch.minimum(t1, t2), torch.maximum(t1, t2)
    tnear = torch.maximum(torch.maximum(tmin[0], tmin[1]), tmin[2])
    tfar = torch.minimum(torch.minimum(tmax[0], tmax[1]), tmax[2])
    axis = torch.where((tmin[0] >= tmin[1]) & (tmin[0] >= tmin[2]), 0, torch.where(tmin[1] >= tmin[2], 1, 2))
    hit = (tnear <= tfar) & (tnear > _EPS_T)
    d_axis = d.gather(0, axis[None])[0]  # the face's normal points against the ray
    return torch.where(hit, tnear, math.inf), 2 * axis + (d_axis < 0), d_axis.abs()


def _sphere_raycast(r: float, o: torch.Tensor, d: torch.Tensor) -> Ray:
    """Closed-form ray/sphere; see :func:`shape_raycast`."""
    a = (d * d).sum(0)
    b = o @ d
    disc = b * b - a * (o @ o - r * r)
    t = (-b - disc.clamp_min(0).sqrt()) / a
    hit = (disc >= 0) & (t > _EPS_T)
    t = torch.where(hit, t, math.inf)
    # n . d at the hit = (o + t d) . d / r = (b + t a) / r
    return t, torch.full_like(t, CURVED, dtype=torch.int64), ((b + torch.where(hit, t, 0.0) * a) / r).abs()


def _cylinder_raycast(r: float, hh: float, o: torch.Tensor, d: torch.Tensor) -> Ray:
    """Side (quadratic in x, y) and the two caps (planes z = +-hh); see :func:`shape_raycast`."""
    a = d[0] ** 2 + d[1] ** 2
    b = o[:2] @ d[:2]
    disc = b * b - a * (o[:2] @ o[:2] - r * r)
    t_side = (-b - disc.clamp_min(0).sqrt()) / a.clamp_min(1e-300)
    z_side = o[2] + t_side * d[2]
    side = (disc >= 0) & (a > 1e-24) & (t_side > _EPS_T) & (z_side.abs() <= hh)
    dz = _safe(d[2])
    cap_z = -torch.sign(dz) * hh  # the cap facing the ray
    t_cap = (cap_z - o[2]) / dz
    x, y = o[0] + t_cap * d[0], o[1] + t_cap * d[1]
    cap = (t_cap > _EPS_T) & (x * x + y * y <= r * r)
    t = torch.where(side, t_side, math.inf)
    use_cap = cap & (t_cap < t)
    t = torch.where(use_cap, t_cap, t)
    # Side: n . d = (o_xy + t d_xy) . d_xy / r = (b + t a) / r; caps: n . d = +-d_z.
    side_dot = (b + torch.where(torch.isfinite(t), t, 0.0) * a) / r
    face = torch.where(use_cap, 4 + (cap_z > 0).long(), CURVED)
    return t, face, torch.where(use_cap, d[2], side_dot).abs()


def shape_area(shape: Shape) -> float:
    """Surface area in square metres."""
    if isinstance(shape, Box):
        x, y, z = (2 * h for h in shape.half)
        return 2 * (x * y + y * z + z * x)
    if isinstance(shape, Sphere):
        return 4 * math.pi * shape.radius**2
    return 2 * math.pi * shape.radius * 2 * shape.half_height + 2 * math.pi * shape.radius**2


def planar_faces(shape: Shape) -> list[tuple[int, float, float]]:
    """(face id, offset along its axis, area) of every planar face of the shape."""
    if isinstance(shape, Box):
        h = shape.half
        out = []
        for axis in range(3):
            area = 4 * h[(axis + 1) % 3] * h[(axis + 2) % 3]
            out += [(2 * axis, -h[axis], area), (2 * axis + 1, h[axis], area)]
        return out
    if isinstance(shape, Cylinder):
        area = math.pi * shape.radius**2
        return [(4, -shape.half_height, area), (5, shape.half_height, area)]
    return []


def shape_sample(shape: Shape, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points uniform by area on the surface, local frame: points (n, 3), outward normals (n, 3)."""
    f64 = torch.float64
    if isinstance(shape, Sphere):
        g = torch.randn(n, 3, generator=gen, dtype=f64)
        g = g / g.norm(dim=-1, keepdim=True)
        return shape.radius * g, g
    half = torch.tensor(bound_half(shape))
    faces = planar_faces(shape)
    weights = [area for _, _, area in faces]
    if isinstance(shape, Cylinder):
        weights.append(2 * math.pi * shape.radius * 2 * shape.half_height)  # the side, last
    pick = torch.multinomial(torch.tensor(weights, dtype=f64), n, replacement=True, generator=gen)
    uv = torch.rand(n, 2, generator=gen, dtype=f64)
    pts = torch.zeros(n, 3, dtype=f64)
    nrm = torch.zeros(n, 3, dtype=f64)
    for k, (face, offset, _) in enumerate(faces):
        sel = pick == k
        axis = face // 2
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        if isinstance(shape, Box):
            pts[sel, a1] = (2 * uv[sel, 0] - 1) * half[a1]
            pts[sel, a2] = (2 * uv[sel, 1] - 1) * half[a2]
        else:  # uniform on a disc of the cap
            rad, ang = shape.radius * uv[sel, 0].sqrt(), 2 * math.pi * uv[sel, 1]
            pts[sel, 0], pts[sel, 1] = rad * torch.cos(ang), rad * torch.sin(ang)
        pts[sel, axis] = offset
        nrm[sel, axis] = math.copysign(1.0, offset)
    if isinstance(shape, Cylinder):
        sel = pick == len(faces)
        ang = 2 * math.pi * uv[sel, 0]
        nrm[sel, 0], nrm[sel, 1] = torch.cos(ang), torch.sin(ang)
        pts[sel, :2] = shape.radius * nrm[sel, :2]
        pts[sel, 2] = (2 * uv[sel, 1] - 1) * shape.half_height
    return pts, nrm

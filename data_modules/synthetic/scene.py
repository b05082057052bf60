"""A scene: a box-shaped room, static furniture and moving rigid objects, with exact geometry.

World frame ("room frame"): metres, z up, the room is the axis-aligned box ``[lo, hi]`` and its floor
is ``z = lo_z`` (0 in every preset). Everything here is float64 and exact: the signed distance field,
the first ray hit (vectorised slab / quadric tests), and area-uniform surface samples. Time enters
only through :func:`place`, which poses every primitive at one instant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from data_modules.synthetic.motion import LookAtCamera, Motion
from data_modules.synthetic.shapes import Shape, box_sdf, scaled, shape_area, shape_raycast, shape_sample, shape_sdf
from data_modules.synthetic.textures import Texture

__all__ = ["PARTS", "Hit", "Placed", "Room", "Scene", "SceneObject", "place", "raycast", "sample_surface", "scene_sdf"]

Vec3 = tuple[float, float, float]
PARTS = ("all", "static", "dynamic")


@dataclass(frozen=True)
class SceneObject:
    """One rigid primitive: its shape (local frame), texture and object-to-world motion."""

    name: str
    shape: Shape
    texture: Texture
    motion: Motion


@dataclass(frozen=True)
class Room:
    """The room's interior box and the textures of its six faces, indexed by face id
    ``2 * axis + (inward normal > 0)`` (so 5 = floor, 4 = ceiling)."""

    lo: Vec3
    hi: Vec3
    textures: tuple[Texture, ...]


@dataclass(frozen=True)
class Scene:
    """Everything that defines the noise-free frames besides image size and frame rate."""

    room: Room
    statics: tuple[SceneObject, ...]
    movers: tuple[SceneObject, ...]
    camera: LookAtCamera
    description: str = ""


@dataclass(frozen=True)
class Placed:
    """A primitive posed at one instant: ``world = R @ local + c``.

    ``index``: primitive id in ray-cast results (0 is the room; statics 1..S, then movers).
    """

    index: int
    obj: SceneObject
    R: torch.Tensor
    c: torch.Tensor
    dynamic: bool


@dataclass
class Hit:
    """First hits of a grid of rays (H, W).

    depth: (H, W) ray parameter of the hit (the z-depth for camera rays with z = 1; inf = no hit).
    prim: (H, W) primitive id (0 = room). face: (H, W) face id on it (``shapes.CURVED`` on curved
    surface). local: (3, H, W) hit point in the primitive's frame, coordinate-major (so per-axis
    work stays contiguous). cos: (H, W) |cos| of the angle between the ray and the surface normal.
    """

    depth: torch.Tensor
    prim: torch.Tensor
    face: torch.Tensor
    local: torch.Tensor
    cos: torch.Tensor


def place(scene: Scene, t_object: float) -> list[Placed]:
    """Every static and moving primitive posed at object time ``t_object`` seconds."""
    out = []
    for k, obj in enumerate(scene.statics + scene.movers):
        T = torch.from_numpy(obj.motion.pose(t_object))
        scale = getattr(obj.motion, "scale", None)  # a non-rigid (breathing) object: its shape at this time
        if scale is not None:
            obj = replace(obj, shape=scaled(obj.shape, scale(t_object)))
        out.append(Placed(k + 1, obj, T[:3, :3].contiguous(), T[:3, 3].clone(), k >= len(scene.statics)))
    return out


def _check_part(part: str) -> None:
    if part not in PARTS:
        raise ValueError(f"part must be 'all', 'static' or 'dynamic', got {part!r}")


def _keep(p: Placed, part: str, names: tuple[str, ...] | None) -> bool:
    if names is not None:
        return p.obj.name in names
    return part == "all" or (part == "dynamic") == p.dynamic


def scene_sdf(room: Room, placed: list[Placed], points: torch.Tensor, part: str = "all") -> torch.Tensor:
    """Exact signed distance (metres) of the posed scene.

    Args:
        points: (N, 3) world points.
        part: "all", "static" (room + static objects) or "dynamic" (moving objects only).
    Returns:
        (N,) float64: positive in free space, negative inside solids (objects and beyond the walls);
        +inf where the part is empty (no moving objects).
    """
    _check_part(part)
    p = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
    d = torch.full((p.shape[0],), math.inf, dtype=torch.float64)
    if part != "dynamic":
        lo, hi = torch.tensor(room.lo, dtype=torch.float64), torch.tensor(room.hi, dtype=torch.float64)
        d = torch.minimum(d, -box_sdf(p - (lo + hi) / 2, (hi - lo) / 2))
    for pr in placed:
        if _keep(pr, part, None):
            d = torch.minimum(d, shape_sdf(pr.obj.shape, (p - pr.c) @ pr.R))
    return d


def _room_exit(room: Room, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Where rays from ``o`` (3,) inside the room leave it; ``d`` (3, N) coordinate-major directions.

    Returns t (N,), world point (3, N), face id (N,) and |inward normal . d| (N,).
    """
    ts, ds = [], []
    lo, hi = torch.tensor(room.lo, dtype=torch.float64) - o, torch.tensor(room.hi, dtype=torch.float64) - o
    for a in range(3):
        da = torch.where(d[a].abs() < 1e-12, 1e-12, d[a])
        ds.append(da)
        # The exit wall along this axis is the one the ray heads to.
        ts.append(torch.where(da > 0, hi[a], lo[a]) / da)
    t = torch.minimum(torch.minimum(ts[0], ts[1]), ts[2])
    axis = torch.where((ts[0] <= ts[1]) & (ts[0] <= ts[2]), 0, torch.where(ts[1] <= ts[2], 1, 2))
    d_axis = torch.where(axis == 0, ds[0], torch.where(axis == 1, ds[1], ds[2]))
    face = 2 * axis + (d_axis < 0)  # the inward normal is -sign(d) along the axis
    return t, o[:, None] + t * d, face, d_axis.abs()


Rect = tuple[int, int, int, int]  # v0, v1, u0, u1: rows v0:v1, columns u0:u1 of the ray grid


def raycast(room: Room, placed: list[Placed], origin: torch.Tensor, dirs: torch.Tensor,
            rects: list[Rect | None] | None = None) -> Hit:
    """First hit of every ray of a grid through the posed scene.

    Args:
        origin: (3,) world ray origin inside the room.
        dirs: (3, H, W) world ray directions, coordinate-major (the ray parameter scales with their
            length).
        rects: per primitive of ``placed``, the sub-grid of rays that can hit it (None = skip it),
            e.g. from its projected bounding box; default: every ray tests every primitive.
    Returns:
        :class:`Hit` of the (H, W) grid.
    """
    _, H, W = dirs.shape
    o = torch.as_tensor(origin, dtype=torch.float64)
    d_cm = dirs.contiguous()
    best, local, face, dot = _room_exit(room, o, d_cm.view(3, -1))
    best, face, dot, local = best.view(H, W), face.view(H, W), dot.view(H, W), local.view(3, H, W)
    prim = torch.zeros(H, W, dtype=torch.int64)
    for k, pr in enumerate(placed):
        rect = (0, H, 0, W) if rects is None else rects[k]
        if rect is None:
            continue
        v0, v1, u0, u1 = rect
        ol, dl = (o - pr.c) @ pr.R, pr.R.T @ d_cm[:, v0:v1, u0:u1].reshape(3, -1)
        tk, fk, incidence = shape_raycast(pr.obj.shape, ol, dl)
        hit = tk < best[v0:v1, u0:u1].reshape(-1)
        if not bool(hit.any()):
            continue
        # Write the new nearest hits into the rectangle (views of the full-grid tensors).
        hw = (v1 - v0, u1 - u0)
        h2 = hit.view(hw)
        sub = (slice(v0, v1), slice(u0, u1))
        best[sub] = torch.where(h2, tk.view(hw), best[sub])
        prim[sub] = torch.where(h2, pr.index, prim[sub])
        face[sub] = torch.where(h2, fk.view(hw), face[sub])
        dot[sub] = torch.where(h2, incidence.view(hw), dot[sub])
        pl = ol[:, None] + torch.where(hit, tk, 0.0) * dl
        local[(slice(None), *sub)] = torch.where(h2, pl.view(3, *hw), local[(slice(None), *sub)])
    norm = (d_cm * d_cm).sum(0).sqrt()
    return Hit(best, prim, face, local, dot / norm)


def _room_faces(room: Room) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """(corner, edge u, edge v, inward normal) of the six room faces."""
    lo, hi = torch.tensor(room.lo, dtype=torch.float64), torch.tensor(room.hi, dtype=torch.float64)
    out = []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for side, sign in ((lo, 1.0), (hi, -1.0)):
            o = lo.clone()
            o[axis] = side[axis]
            eu, ev, n = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
            eu[a1], ev[a2], n[axis] = hi[a1] - lo[a1], hi[a2] - lo[a2], sign
            out.append((o, eu, ev, n))
    return out


def _draw(room: Room, parts: list[Placed], with_room: bool, m: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``m`` raw area-uniform samples (points, normals) on the room (optional) and ``parts``."""
    faces = _room_faces(room) if with_room else []
    areas = [float(torch.linalg.cross(eu, ev).norm()) for _, eu, ev, _ in faces] + [shape_area(p.obj.shape) for p in parts]
    counts = torch.bincount(torch.multinomial(torch.tensor(areas, dtype=torch.float64), m, replacement=True, generator=gen),
                            minlength=len(areas))
    pts, nrm = [], []
    for k, (o, eu, ev, n) in enumerate(faces):
        uv = torch.rand(int(counts[k]), 2, generator=gen, dtype=torch.float64)
        pts.append(o + uv[:, :1] * eu + uv[:, 1:] * ev)
        nrm.append(n.expand(len(uv), 3))
    for k, pr in enumerate(parts):
        pl, nl = shape_sample(pr.obj.shape, int(counts[len(faces) + k]), gen)
        pts.append(pl @ pr.R.T + pr.c)
        nrm.append(nl @ pr.R.T)
    order = torch.randperm(m, generator=gen)  # mix the components (callers keep a prefix)
    return torch.cat(pts)[order], torch.cat(nrm)[order]


def sample_surface(room: Room, placed: list[Placed], n: int, gen: torch.Generator, part: str = "all",
                   names: tuple[str, ...] | None = None) -> torch.Tensor:
    """Points sampled uniformly by area on the posed scene's surfaces.

    Args:
        n: number of points.
        part: "all", "static" (room + static objects) or "dynamic"; ignored when ``names`` is given.
        names: sample only these objects (no room).
    Returns:
        (n, 3) float64 world points (fewer only if the selection has no visible surface). Surface that
        touches another solid (a box bottom on the floor, the floor under it) is excluded: a point is
        kept only where 1 mm off the surface along its normal is free space.
    """
    _check_part(part)
    parts = [p for p in placed if _keep(p, part, names)]
    with_room = names is None and part != "dynamic"
    if n <= 0 or not (parts or with_room):
        return torch.zeros(0, 3, dtype=torch.float64)
    chunks, have = [], 0
    for _ in range(50):
        if have >= n:
            break
        pts, nrm = _draw(room, parts, with_room, max(64, int(1.3 * (n - have)) + 16), gen)
        free = scene_sdf(room, placed, pts + 1e-3 * nrm) > 5e-4
        chunks.append(pts[free])
        have += int(free.sum())
    return torch.cat(chunks)[:n]

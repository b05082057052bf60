"""Seeded procedural layout: a random room, random rigid shapes and furniture that keeps clear of the
camera path and of the moving objects' swept paths (checked in the floor plane)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from data_modules.synthetic.motion import Fixed
from data_modules.synthetic.scene import Room, SceneObject
from data_modules.synthetic.shapes import Box, Cylinder, Shape, Sphere, bound_half
from data_modules.synthetic.textures import random_texture

__all__ = ["KeepOut", "footprint_radius", "random_furniture", "random_room", "random_shape", "swept_xy"]

# (xy points (M, 2), clearance radius): furniture footprints stay this far from every point.
KeepOut = tuple[np.ndarray, float]


def random_room(rng: np.random.Generator, half_x: tuple[float, float] = (2.3, 3.0), half_y: tuple[float, float] = (1.9, 2.6),
                height: tuple[float, float] = (2.5, 3.0)) -> Room:
    """A room centred on the origin in x, y with its floor at z = 0, random size and wall textures."""
    hx, hy, hz = rng.uniform(*half_x), rng.uniform(*half_y), rng.uniform(*height)
    textures = tuple(random_texture(rng, "wall") for _ in range(6))
    return Room((-round(hx, 3), -round(hy, 3), 0.0), (round(hx, 3), round(hy, 3), round(hz, 3)), textures)


def random_shape(rng: np.random.Generator, size: float, kinds: tuple[str, ...] = ("box", "cylinder", "sphere")) -> Shape:
    """A box, cylinder or sphere of characteristic half size ``size`` metres (+-40 %)."""
    kind = str(rng.choice(list(kinds)))
    if kind == "box":
        return Box(tuple(round(float(x), 4) for x in size * rng.uniform(0.6, 1.0, 3)))
    if kind == "cylinder":
        return Cylinder(round(float(size * rng.uniform(0.6, 0.9)), 4), round(float(size * rng.uniform(0.7, 1.2)), 4))
    if kind == "sphere":
        return Sphere(round(float(size * rng.uniform(0.8, 1.0)), 4))
    raise ValueError(f"unknown shape kind {kind!r}")


def footprint_radius(shape: Shape) -> float:
    """Radius of a vertical cylinder containing the shape under any rotation about z."""
    h = bound_half(shape)
    return float(math.hypot(h[0], h[1]))


def swept_xy(pose: Callable[[float], np.ndarray], duration: float, step: float = 0.05) -> np.ndarray:
    """(M, 2) floor-plane positions of a trajectory sampled every ``step`` s over ``duration`` s."""
    ts = np.arange(0.0, duration + step, step)
    return np.array([pose(float(t))[:2, 3] for t in ts])


def _clear(xy: np.ndarray, radius: float, keep_out: list[KeepOut]) -> bool:
    return all(float(np.min(np.linalg.norm(pts - xy, axis=1))) > radius + clearance for pts, clearance in keep_out)


def _furniture_piece(rng: np.random.Generator) -> tuple[Shape, float]:
    """A random piece standing on the floor: its shape and the height of its centre."""
    kind = str(rng.choice(["cabinet", "cabinet", "column", "ball", "low"]))
    if kind == "cabinet":
        shape = Box((round(rng.uniform(0.15, 0.45), 3), round(rng.uniform(0.15, 0.35), 3), round(rng.uniform(0.25, 0.6), 3)))
    elif kind == "low":
        shape = Box((round(rng.uniform(0.3, 0.6), 3), round(rng.uniform(0.25, 0.45), 3), round(rng.uniform(0.12, 0.25), 3)))
    elif kind == "column":
        shape = Cylinder(round(rng.uniform(0.1, 0.25), 3), round(rng.uniform(0.2, 0.7), 3))
    else:
        shape = Sphere(round(rng.uniform(0.12, 0.3), 3))
    return shape, float(bound_half(shape)[2])


def random_furniture(rng: np.random.Generator, room: Room, count: int, keep_out: list[KeepOut],
                     prefix: str = "static", tries: int = 400) -> tuple[SceneObject, ...]:
    """Up to ``count`` pieces standing on the floor, rotated about z, not overlapping each other, the
    walls or the keep-out zones (fewer if the room is too full after ``tries`` attempts)."""
    placed: list[SceneObject] = []
    zones = list(keep_out)
    for _ in range(tries):
        if len(placed) >= count:
            break
        shape, z = _furniture_piece(rng)
        r = footprint_radius(shape)
        lo, hi = np.array(room.lo[:2]) + r + 0.02, np.array(room.hi[:2]) - r - 0.02
        if (lo >= hi).any():
            continue
        xy = rng.uniform(lo, hi)
        if not _clear(xy, r, zones):
            continue
        yaw = float(rng.uniform(-math.pi, math.pi))
        obj = SceneObject(f"{prefix}_{len(placed)}", shape, random_texture(rng, "object"),
                          Fixed((round(float(xy[0]), 4), round(float(xy[1]), 4), z), round(yaw, 4)))
        placed.append(obj)
        zones.append((xy[None], r + 0.05))
    return tuple(placed)

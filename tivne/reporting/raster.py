"""A small CPU z-buffer rasteriser for mesh snapshots: numpy only, no display and no OpenGL.

Cameras follow the project's convention (OpenCV axes: x right, y down, z forward; ``w2c`` maps
world points into the camera). Triangles are filled by testing, for each face, the pixel centres
of its screen bounding box (all faces at once, in chunks), then the nearest face wins each pixel.
Faces turned away from the camera are skipped (culled), so a room seen from outside shows its inside.
"""

from __future__ import annotations

import math

import numpy as np

BACKGROUND = np.array([1.0, 1.0, 1.0])
CANDIDATES_PER_CHUNK = 4_000_000  # pixel tests per batch: bounds the memory (~200 MB at most)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera for a camera at ``eye`` looking at ``target``, with ``up`` (world)
    shown upwards in the image (OpenCV axes: the camera's -y). ``eye`` != ``target``; ``up`` not
    parallel to the viewing direction."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: any sideways axis will do
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ np.asarray(eye, float)
    return w2c


def pinhole(width: int, height: int, fov_x_deg: float = 60.0) -> np.ndarray:
    """(3, 3) intrinsics with a horizontal field of view, principal point at the centre."""
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def project(vertices: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) world points -> pixel coordinates (V, 2) and camera depth z (V,)."""
    cam = vertices @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam[:, :2] / z[:, None]) * np.diag(K)[:2] + K[:2, 2]
    return uv, z


def candidate_pixels(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pixel of each face's bounding box: (face index, x, y), each (sum of box areas,).

    Args:
        lo, hi: (F, 2) inclusive integer box corners (x, y).
    """
    size = hi - lo + 1
    count = size[:, 0] * size[:, 1]
    face = np.repeat(np.arange(len(lo)), count)
    local = np.arange(len(face)) - np.repeat(np.cumsum(count) - count, count)
    return face, lo[face, 0] + local % size[face, 0], lo[face, 1] + local // size[face, 0]


def fill_chunk(
    tri_uv: np.ndarray, tri_z: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels covered by triangles (screen space, either winding).

    Args:
        tri_uv: (F, 3, 2) corners in pixels; tri_z: (F, 3) depths; lo, hi: (F, 2) pixel boxes.
    Returns:
        face (P,), x (P,), y (P,), depth (P,) and barycentric weights (P, 3) of the covered pixels.
    """
    face, x, y = candidate_pixels(lo, hi)
    a, b, c = tri_uv[face, 0], tri_uv[face, 1], tri_uv[face, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])

    def edge(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # signed area of (p, q, pixel)
        return (q[:, 0] - p[:, 0]) * (y - p[:, 1]) - (q[:, 1] - p[:, 1]) * (x - p[:, 0])

    weights = np.stack([edge(b, c), edge(c, a), edge(a, b)], axis=1) / area[:, None]
    inside = (weights >= -1e-9).all(axis=1)
    weights = weights[inside]
    depth = (weights * tri_z[face[inside]]).sum(axis=1)
    return face[inside], x[inside], y[inside], depth, weights


def rasterize(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    near: float = 1e-3,
) -> np.ndarray:
    """Render a mesh with a headlight.

    Args:
        vertices: (V, 3) world; faces: (F, 3) int, counter-clockwise seen from outside (trimesh's
        winding: the face normal points to the side that is shown); colors: (V, 3) in [0, 1].
        K: (3, 3); w2c: (4, 4); width, height: image size.
    Returns:
        (height, width, 3) float image in [0, 1], white where no face is.
    """
    image = np.tile(BACKGROUND, (height, width, 1))
    if len(faces) == 0:
        return image
    uv, z = project(np.asarray(vertices, float), K, w2c)
    tri = np.asarray(faces)
    tri = tri[(z[tri] > near).all(axis=1)]  # faces crossing the near plane are dropped, not clipped
    cam = np.asarray(vertices, float) @ w2c[:3, :3].T + w2c[:3, 3]
    normals = np.cross(cam[tri[:, 1]] - cam[tri[:, 0]], cam[tri[:, 2]] - cam[tri[:, 0]])
    facing = -(normals * cam[tri].mean(axis=1)).sum(axis=1)  # > 0: the normal points at the camera
    tri, normals, facing = tri[facing > 0], normals[facing > 0], facing[facing > 0]
    shade = facing / (np.linalg.norm(normals, axis=1) * np.linalg.norm(cam[tri].mean(axis=1), axis=1) + 1e-12)
    lo = np.floor(uv[tri].min(axis=1)).astype(np.int64).clip(0, [width - 1, height - 1])
    hi = np.ceil(uv[tri].max(axis=1)).astype(np.int64).clip(0, [width - 1, height - 1])
    on_screen = (uv[tri].max(axis=1) >= 0).all(axis=1) & (uv[tri].min(axis=1) <= [width - 1, height - 1]).all(axis=1)
    keep = np.flatnonzero(on_screen)
    zbuf = np.full(height * width, np.inf)
    best_face = np.full(height * width, -1)
    best_weights = np.zeros((height * width, 3))
    count = ((hi - lo + 1)[keep]).prod(axis=1)
    bounds = np.searchsorted(np.cumsum(count), np.arange(1, count.sum() // CANDIDATES_PER_CHUNK + 2) * CANDIDATES_PER_CHUNK)
    for chunk in np.split(keep, np.unique(np.clip(bounds + 1, 1, len(keep)))):
        if len(chunk) == 0:
            continue
        face, x, y, depth, weights = fill_chunk(uv[tri[chunk]], z[tri[chunk]], lo[chunk], hi[chunk])
        pixel = y * width + x
        order = np.lexsort((depth, pixel))  # per pixel, nearest first
        first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]]
        nearer = depth[first] < zbuf[pixel[first]]
        win = first[nearer]
        zbuf[pixel[win]] = depth[win]
        best_face[pixel[win]] = chunk[face[win]]
        best_weights[pixel[win]] = weights[win]
    covered = np.flatnonzero(best_face >= 0)
    corner_colors = np.asarray(colors, float)[tri[best_face[covered]]]  # (P, 3 corners, 3)
    rgb = (best_weights[covered, :, None] * corner_colors).sum(axis=1)
    light = 0.35 + 0.65 * shade[best_face[covered]]
    image.reshape(-1, 3)[covered] = np.clip(rgb * light[:, None], 0, 1)
    return image

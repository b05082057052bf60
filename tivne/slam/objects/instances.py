"""Object instances of one frame and their association with tracks (pure functions).

Two sources: the dataset's instance ids (``Frame.instances``: ids are identities, every frame the
same), or the connected, depth-continuous segments of a dynamic mask (ids only for this frame: the
tracker associates them with its tracks by overlap under the predicted motion, and re-identifies a
lost track by its predicted position and size).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from tivne.geometry import backproject_depth, project, transform_points
from tivne.masks.segments import depth_segments
from tivne.morphology import dilate


def dataset_instances(ids: torch.Tensor, depth: torch.Tensor, min_pixels: int) -> dict[int, torch.Tensor]:
    """{dataset id: (H, W) bool} of every object id > 0 with at least ``min_pixels`` pixels with depth.

    Args:
        ids: (H, W) int64 instance ids (0 = static). depth: (H, W) metres, 0 = invalid.
    """
    found = torch.unique(ids[(ids > 0) & (depth > 0)])
    out = {}
    for k in found.tolist():
        m = (ids == k) & (depth > 0)
        if int(m.sum()) >= min_pixels:
            out[int(k)] = m
    return out


def mask_segments(dynamic: torch.Tensor, depth: torch.Tensor, min_pixels: int) -> list[torch.Tensor]:
    """The connected, depth-continuous parts (H, W) bool of a dynamic mask with at least
    ``min_pixels`` pixels, largest first (two objects touching in the image but at different depths
    are two segments; :func:`tivne.masks.segments.depth_segments` edges belong to none)."""
    from scipy import ndimage

    d = depth.detach().cpu().numpy()
    dyn = dynamic.detach().cpu().numpy() & (d > 0)
    labels, n = depth_segments(d, hole_edges=True)  # at full resolution a hole costs one pixel of rim
    if n == 0 or not dyn.any():
        return []
    parts, m = ndimage.label(dyn & (labels > 0))
    key = parts.astype(np.int64) * (n + 1) + labels
    keys, counts = np.unique(key[parts > 0], return_counts=True)
    order = np.argsort(-counts)
    return [torch.from_numpy(key == keys[i]).to(dynamic.device) for i in order if counts[i] >= min_pixels]


def world_points(mask: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, T_wc: torch.Tensor, max_points: int = 2000) -> torch.Tensor:
    """(N, 3) float64 world points of the masked pixels with depth (every k-th, at most about
    ``max_points``)."""
    cam = backproject_depth(depth, K)[mask & (depth > 0)]
    step = max(1, len(cam) // max_points)
    return transform_points(T_wc.double(), cam[::step].double())


def projected_mask(points_world: torch.Tensor, T_wc: torch.Tensor, K: torch.Tensor, shape: tuple[int, int], radius: int = 2) -> torch.Tensor:
    """(H, W) bool footprint of world points (N, 3) in a camera T_wc (4, 4): each projected point
    marks its pixel, dilated by ``radius`` (the points are a sparse sample of the surface)."""
    h, w = shape
    cam = transform_points(torch.linalg.inv(T_wc.double()), points_world.double())
    uv, z = project(cam, K.double())
    u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
    keep = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = torch.zeros(h, w, dtype=torch.bool, device=points_world.device)
    out[v[keep], u[keep]] = True
    return dilate(out, radius)


def touches_border(mask: torch.Tensor, margin: int = 2) -> bool:
    """Whether an (H, W) bool mask reaches within ``margin`` pixels of the image border (the object
    is cut off by the view: only a sliver of it may be seen)."""
    m = int(margin)
    return bool(mask[:m].any() or mask[-m:].any() or mask[:, :m].any() or mask[:, -m:].any())


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    """Intersection over union of two (H, W) bool masks (0 when both are empty)."""
    union = int((a | b).sum())
    return int((a & b).sum()) / union if union else 0.0


def greedy_match(scores: np.ndarray, threshold: float) -> list[tuple[int, int]]:
    """Pairs (row, column) of a score matrix (R, C), best first, each row and column at most once,
    every pair's score >= ``threshold``."""
    pairs, used_r, used_c = [], set(), set()
    flat = np.argsort(-scores, axis=None) if scores.size else []
    for idx in flat:
        r, c = np.unravel_index(int(idx), scores.shape)
        if scores[r, c] < threshold:
            break
        if r not in used_r and c not in used_c:
            pairs.append((int(r), int(c)))
            used_r.add(r)
            used_c.add(c)
    return pairs


def extent(points: torch.Tensor) -> float:
    """A robust size (m) of a point set (N, 3): the diagonal of its 5–95 % box."""
    if len(points) < 2:
        return 0.0
    lo, hi = torch.quantile(points, 0.05, dim=0), torch.quantile(points, 0.95, dim=0)
    return float((hi - lo).norm())


def smooth_depth(depth: torch.Tensor, mask: torch.Tensor, radius: int) -> torch.Tensor:
    """(H, W) depth with each masked pixel replaced by the mean of the masked pixels with depth in
    its (2·radius + 1)² window (others unchanged): the object's axial noise, averaged down before the
    odometry warps with it (noisy depths shrink the estimated rotation, the errors-in-variables bias)."""
    if radius <= 0:
        return depth
    valid = (mask & (depth > 0)).float()[None, None]
    k = 2 * radius + 1
    total = F.avg_pool2d(depth[None, None] * valid, k, stride=1, padding=radius)
    count = F.avg_pool2d(valid, k, stride=1, padding=radius)
    smooth = (total / count.clamp_min(1e-9))[0, 0]
    return torch.where(valid[0, 0] > 0, smooth, depth)

"""Surface metrics as pure functions (numpy float64, metres): mesh sampling, points in oriented boxes,
and the one implementation of accuracy, completion, Chamfer distance and ghost fraction.

A reference surface is given either as points sampled on it, (M, 3), or as a distance function
``(N, 3) -> (N,)`` (:data:`DistanceFn`, e.g. ``|sdf|`` of an exact scene), so the same metric serves
an exact ground truth and a sampled one.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from tivne.metrics.trajectory import ArrayLike, _as_np64

DistanceFn = Callable[[np.ndarray], np.ndarray]
"""Distance (N,) metres from (N, 3) points to a surface."""
Surface = ArrayLike | DistanceFn


def _as_points(x: ArrayLike, name: str) -> np.ndarray:
    p = _as_np64(x)
    if p.size == 0:
        return p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    return p


def sample_mesh_surface(mesh, n: int, seed: int = 0) -> np.ndarray:
    """Area-weighted uniform samples on a triangle mesh (``trimesh.sample.sample_surface``).

    Args:
        mesh: ``trimesh.Trimesh``.
        n: number of samples.
        seed: RNG seed (same seed, same mesh -> same points).
    Returns:
        (n, 3) float64 points; (0, 3) when the mesh has no faces or zero area.
    """
    import trimesh

    if len(mesh.faces) == 0 or not mesh.area > 0 or n <= 0:
        return np.zeros((0, 3))
    points, _ = trimesh.sample.sample_surface(mesh, int(n), seed=seed)
    return np.asarray(points, dtype=np.float64)


def voxel_subsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """(M, 3) -> (K, 3): the first point in every occupied ``voxel``-sized cube (each input point is
    within ``voxel * sqrt(3)`` of one that is kept)."""
    if len(points) == 0:
        return points
    _, first = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def distance_to_points(points: ArrayLike, exact_within: float = 0.5, coarse_voxel: float = 0.02) -> DistanceFn:
    """Distance to the nearest of ``points`` (M, 3) (cKDTrees built once, queried per call); ``inf`` when M = 0.

    Distances up to ``exact_within`` metres are exact. Beyond, they are distances to one point per
    ``coarse_voxel`` cube (:func:`voxel_subsample`), at most ``coarse_voxel * sqrt(3)`` (3.5 cm, 7 %
    at 0.5 m) longer than the true one: an exact search from a query far from a compact cloud (a GT
    object far from every reconstructed surface) visits nearly every point, seconds per thousand queries.
    """
    p = _as_points(points, "points")
    tree = cKDTree(p) if len(p) else None
    coarse: list[cKDTree] = []  # built on the first far query

    def distance(query: np.ndarray) -> np.ndarray:
        q = _as_points(query, "query")
        if len(q) == 0:
            return np.zeros(0)
        if tree is None:
            return np.full(len(q), np.inf)
        d = np.asarray(tree.query(q, k=1, distance_upper_bound=exact_within)[0], dtype=np.float64)
        far = ~np.isfinite(d)
        if far.any():
            if not coarse:
                coarse.append(cKDTree(voxel_subsample(p, coarse_voxel)))
            d[far] = coarse[0].query(q[far], k=1)[0]
        return d

    return distance


def _distance_fn(surface: Surface) -> DistanceFn:
    return surface if callable(surface) else distance_to_points(surface)


@dataclass(frozen=True)
class OrientedBox:
    """A box in the world: a point ``p`` is inside iff ``all(|R^T (p - center)| <= half_extents)``.

    center (3,), half_extents (3,) metres, rotation R (3, 3) box-to-world.
    """

    center: np.ndarray
    half_extents: np.ndarray
    rotation: np.ndarray


def in_boxes(points: ArrayLike, boxes: Sequence[OrientedBox], margin: float = 0.0) -> np.ndarray:
    """(N, 3) points -> (N,) bool: inside any of ``boxes`` dilated by ``margin`` metres."""
    p = _as_points(points, "points")
    inside = np.zeros(len(p), dtype=bool)
    for box in boxes:
        local = (p - box.center) @ box.rotation  # R^T (p - c), row by row
        inside |= (np.abs(local) <= box.half_extents + margin).all(1)
    return inside


def faces_near(mesh, boxes: Sequence[OrientedBox], margin: float):
    """The faces of ``mesh`` with a vertex inside a dilated box, as a new ``trimesh.Trimesh`` (same vertices)."""
    import trimesh

    if len(mesh.faces) == 0:
        return mesh
    near = in_boxes(np.asarray(mesh.vertices), boxes, margin)
    return trimesh.Trimesh(mesh.vertices, mesh.faces[near[mesh.faces].any(1)], process=False)


def accuracy(pred_points: ArrayLike, truth: Surface) -> float:
    """Mean distance (m) from reconstructed surface samples to the true surface.

    Args:
        pred_points: (N, 3) samples of the reconstruction.
        truth: the true surface, (M, 3) samples or a :data:`DistanceFn`.
    Returns:
        metres; NaN when there are no predicted points (nothing to measure).
    """
    pred = _as_points(pred_points, "pred_points")
    if len(pred) == 0:
        return math.nan
    return float(_distance_fn(truth)(pred).mean())


def completion(truth_points: ArrayLike, pred: Surface, threshold: float) -> tuple[float, float]:
    """How much of the true surface the reconstruction covers.

    Args:
        truth_points: (M, 3) samples of the (part of the) true surface that should be reconstructed.
        pred: the reconstruction, (N, 3) samples or a :data:`DistanceFn`.
        threshold: metres under which a true point counts as covered.
    Returns:
        (completion: mean distance (m) from the true points to the reconstruction, completion ratio:
        share of true points within ``threshold``). (NaN, NaN) without true points; (inf, 0) without
        a reconstruction.
    """
    truth = _as_points(truth_points, "truth_points")
    if len(truth) == 0:
        return math.nan, math.nan
    d = _distance_fn(pred)(truth)
    return float(d.mean()), float((d < threshold).mean())


def chamfer(accuracy_m: float, completion_m: float) -> float:
    """Chamfer-L1 distance (m): the mean of accuracy and completion."""
    return 0.5 * (accuracy_m + completion_m)


def ghost_fraction(pred_points: ArrayLike, truth: Surface, threshold: float) -> float:
    """Share of reconstructed surface samples farther than ``threshold`` from the true surface.

    Measures "ghost" geometry at a time t (e.g. a moving object left where it used to be), when
    ``truth`` is the whole true surface at t.

    Args:
        pred_points: (N, 3) samples of the reconstruction at t.
        truth: (M, 3) samples or a :data:`DistanceFn` of the true surface at t.
    Returns:
        fraction in [0, 1]; NaN without predicted points; 1 for an empty ``truth``.
    """
    pred = _as_points(pred_points, "pred_points")
    if len(pred) == 0:
        return math.nan
    return float((_distance_fn(truth)(pred) > threshold).mean())

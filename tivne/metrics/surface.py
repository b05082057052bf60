"""Surface metrics as pure functions: mesh sampling, nearest distances, accuracy, completion,
Chamfer-L1, completion ratio and ghost fraction (numpy float64; metres)."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from tivne.metrics.trajectory import ArrayLike, _as_np64


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


def nearest_distances(query: ArrayLike, points: ArrayLike) -> np.ndarray:
    """Distance from every query point to its nearest neighbour in ``points`` (cKDTree).

    Args:
        query: (N, 3); points: (M, 3).
    Returns:
        (N,) metres; all ``inf`` when ``points`` is empty.
    """
    q = _as_points(query, "query")
    p = _as_points(points, "points")
    if len(p) == 0:
        return np.full(len(q), np.inf)
    if len(q) == 0:
        return np.zeros(0)
    d, _ = cKDTree(p).query(q, k=1)
    return np.asarray(d, dtype=np.float64)


def mesh_metrics(pred_points: ArrayLike, gt_points: ArrayLike, threshold: float = 0.05) -> dict[str, float]:
    """Surface accuracy / completion between reconstructed and ground-truth surface samples.

    Args:
        pred_points: (N, 3) samples of the reconstructed surface (see :func:`sample_mesh_surface`).
        gt_points: (M, 3) samples of the ground-truth surface, M > 0.
        threshold: distance in metres under which a GT point counts as completed.
    Returns:
        ``accuracy_m``: mean distance pred -> nearest gt; ``completion_m``: mean distance gt -> nearest
        pred; ``chamfer_l1_m``: their mean; ``completion_ratio``: share of gt points within
        ``threshold`` of pred. With no predicted points: accuracy NaN (nothing to measure),
        completion and Chamfer inf, completion ratio 0.
    Raises:
        ValueError: empty ground truth.
    """
    pred = _as_points(pred_points, "pred_points")
    gt = _as_points(gt_points, "gt_points")
    if len(gt) == 0:
        raise ValueError("mesh_metrics: ground-truth point set is empty")
    if len(pred) == 0:
        return {"accuracy_m": math.nan, "completion_m": math.inf, "chamfer_l1_m": math.inf, "completion_ratio": 0.0}
    acc = float(nearest_distances(pred, gt).mean())
    d_gt = nearest_distances(gt, pred)
    comp = float(d_gt.mean())
    return {
        "accuracy_m": acc,
        "completion_m": comp,
        "chamfer_l1_m": 0.5 * (acc + comp),
        "completion_ratio": float((d_gt < threshold).mean()),
    }


def ghost_fraction(pred_points: ArrayLike, gt_points_at_t: ArrayLike, threshold: float = 0.05) -> float:
    """Share of reconstructed surface points at time t farther than ``threshold`` from every GT point at t.

    Measures "ghost" geometry (e.g. a dynamic object left behind where it used to be).

    Args:
        pred_points: (N, 3) samples of the surface reconstructed for time t.
        gt_points_at_t: (M, 3) samples of the true surface at time t.
        threshold: metres.
    Returns:
        Fraction in [0, 1]; NaN when there are no predicted points; 1 when the GT is empty and the
        prediction is not.
    """
    pred = _as_points(pred_points, "pred_points")
    if len(pred) == 0:
        return math.nan
    d = nearest_distances(pred, gt_points_at_t)
    return float((d > threshold).mean())

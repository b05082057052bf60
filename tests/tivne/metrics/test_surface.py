"""Tests of tivne.metrics.surface: mesh sampling, oriented boxes, accuracy / completion / Chamfer, ghost fraction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from tivne.metrics import surface as M


def sphere_points(n: int, radius: float = 1.0, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def unit_sphere_distance(points: np.ndarray) -> np.ndarray:
    """Exact distance to the unit sphere at the origin."""
    return np.abs(np.linalg.norm(points, axis=1) - 1.0)


class TestSurfaceMetrics:
    def test_concentric_spheres(self):
        gt = sphere_points(4000, 1.0, seed=0)
        pred = 1.01 * gt  # same directions: every nearest neighbour is exactly the radial gap away
        acc = M.accuracy(pred, gt)
        comp, ratio = M.completion(gt, pred, threshold=0.05)
        assert acc == pytest.approx(0.01, abs=1e-12) and comp == pytest.approx(0.01, abs=1e-12)
        assert M.chamfer(acc, comp) == pytest.approx(0.01, abs=1e-12) and ratio == 1.0
        assert M.completion(gt, pred, threshold=0.005)[1] == 0.0

    def test_exact_distance_function_equals_dense_samples(self):
        pred = sphere_points(2000, 1.01, seed=2)
        assert M.accuracy(pred, unit_sphere_distance) == pytest.approx(0.01, abs=1e-12)
        mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
        assert M.accuracy(pred, M.sample_mesh_surface(mesh, 200_000, seed=0)) == pytest.approx(0.01, abs=2e-3)

    def test_half_sphere_completion_ratio(self):
        gt = sphere_points(6000, seed=3)
        pred = gt[gt[:, 2] > 0]
        comp, ratio = M.completion(gt, pred, threshold=0.05)
        assert M.accuracy(pred, gt) == 0.0
        assert ratio == pytest.approx(0.5 + 0.05 / 2, abs=0.03)  # band of width 0.05 past the equator
        assert comp > 0.1
        # Over the half that should be there, the same reconstruction is complete.
        assert M.completion(gt[gt[:, 2] > 0], pred, threshold=0.05) == (0.0, 1.0)

    def test_ghost_fraction_of_shifted_copy(self):
        gt_t = sphere_points(3000, seed=4)  # e.g. a moving object at time t
        stale = gt_t + np.array([0.5, 0.0, 0.0])  # reconstruction still shows it where it was
        pred = np.concatenate([gt_t, stale])
        assert M.ghost_fraction(gt_t, gt_t, threshold=0.05) == 0.0
        frac = M.ghost_fraction(pred, unit_sphere_distance, threshold=0.05)
        # The stale copy overlaps the true sphere only near the intersection circle.
        assert 0.4 < frac < 0.5
        assert frac == pytest.approx(M.ghost_fraction(pred, gt_t, threshold=0.05), abs=0.02)
        assert M.ghost_fraction(stale + np.array([5.0, 0, 0]), gt_t, threshold=0.05) == 1.0

    def test_empty_inputs(self):
        gt = sphere_points(100)
        none = np.zeros((0, 3))
        assert math.isnan(M.accuracy(none, gt)) and math.isnan(M.ghost_fraction(none, gt, 0.05))
        assert M.completion(gt, none, 0.05) == (math.inf, 0.0)
        assert all(math.isnan(v) for v in M.completion(none, gt, 0.05))
        assert M.ghost_fraction(gt, none, 0.05) == 1.0
        with pytest.raises(ValueError, match=r"\(N, 3\)"):
            M.accuracy(np.zeros((4, 2)), gt)

    def test_distance_to_points_exact_near_bounded_far(self):
        cloud = sphere_points(20_000, radius=0.3, seed=6)
        rng = np.random.default_rng(7)
        query = np.concatenate([sphere_points(500, radius=0.5, seed=8), rng.normal(size=(500, 3)) + [2.0, 1.0, 0.0]])
        brute = cKDTree(cloud).query(query, k=1)[0]  # exact search, however slow
        d = M.distance_to_points(cloud, exact_within=0.5, coarse_voxel=0.02)(query)
        near = brute <= 0.5
        assert near.sum() >= 500 and (~near).sum() > 100
        assert np.array_equal(d[near], brute[near])
        assert (d[~near] >= brute[~near]).all() and (d[~near] <= brute[~near] + 0.02 * np.sqrt(3)).all()
        assert M.voxel_subsample(cloud, 0.02).shape[0] < len(cloud)

    def test_torch_inputs(self):
        gt = torch.from_numpy(sphere_points(500, seed=5)).float()
        assert M.accuracy(gt, gt) == 0.0 and M.completion(gt, gt, 0.01) == (0.0, 1.0)

    def test_sample_mesh_surface(self):
        box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
        a = M.sample_mesh_surface(box, 5000, seed=3)
        b = M.sample_mesh_surface(box, 5000, seed=3)
        assert a.shape == (5000, 3) and a.dtype == np.float64 and np.array_equal(a, b)
        assert not np.array_equal(a, M.sample_mesh_surface(box, 5000, seed=4))
        assert np.abs(a).max(0) == pytest.approx([1.0, 0.5, 0.25])
        # Area-weighted: the two 2 x 1 faces hold 4 of the 7 m^2 of 2*(2 + 1 + 0.5).
        on_z_faces = np.isclose(np.abs(a[:, 2]), 0.25)
        assert on_z_faces.mean() == pytest.approx(4.0 / 7.0, abs=0.03)
        assert M.sample_mesh_surface(trimesh.Trimesh(), 10, seed=0).shape == (0, 3)


class TestBoxes:
    def test_in_boxes_rotated_and_dilated(self):
        c = np.cos(np.pi / 4)
        R = np.array([[c, -c, 0.0], [c, c, 0.0], [0.0, 0.0, 1.0]])  # 45 degrees about z
        box = M.OrientedBox(np.array([1.0, 0.0, 0.0]), np.array([0.1, 0.1, 0.1]), R)
        pts = np.array([[1.0, 0.0, 0.0], [1.13, 0.0, 0.0], [1.2, 0.0, 0.0], [1.0, 0.0, 0.12]])
        # Along the world x axis the rotated box reaches 0.1 * sqrt(2) = 0.141.
        assert M.in_boxes(pts, [box]).tolist() == [True, True, False, False]
        assert M.in_boxes(pts, [box], margin=0.05).tolist() == [True, True, True, True]
        assert M.in_boxes(pts, []).tolist() == [False] * 4

    def test_faces_near(self):
        a = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
        b = a.copy()
        b.apply_translation([2.0, 0.0, 0.0])
        both = trimesh.util.concatenate([a, b])
        box = M.OrientedBox(np.zeros(3), np.full(3, 0.1), np.eye(3))
        near = M.faces_near(both, [box], margin=0.01)
        assert len(near.faces) == len(a.faces) and np.abs(near.vertices[near.faces]).max() <= 0.1 + 1e-12

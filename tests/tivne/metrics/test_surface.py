"""Tests of tivne.metrics.surface: mesh sampling, accuracy / completion / Chamfer, ghost fraction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from tivne.metrics import surface as M


def sphere_points(n: int, radius: float = 1.0, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


class TestSurfaceMetrics:
    def test_concentric_spheres(self):
        gt = sphere_points(4000, 1.0, seed=0)
        pred = 1.01 * gt  # same directions: every nearest neighbour is exactly the radial gap away
        out = M.mesh_metrics(pred, gt, threshold=0.05)
        assert set(out) == {"accuracy_m", "completion_m", "chamfer_l1_m", "completion_ratio"}
        assert out["accuracy_m"] == pytest.approx(0.01, abs=1e-12)
        assert out["completion_m"] == pytest.approx(0.01, abs=1e-12)
        assert out["chamfer_l1_m"] == pytest.approx(0.01, abs=1e-12)
        assert out["completion_ratio"] == 1.0
        assert M.mesh_metrics(pred, gt, threshold=0.005)["completion_ratio"] == 0.0

    def test_dense_sphere_accuracy_is_radial_gap(self):
        mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
        gt = M.sample_mesh_surface(mesh, 200_000, seed=0)
        pred = sphere_points(2000, 1.01, seed=2)
        assert M.mesh_metrics(pred, gt)["accuracy_m"] == pytest.approx(0.01, abs=2e-3)

    def test_half_sphere_completion_ratio(self):
        gt = sphere_points(6000, seed=3)
        pred = gt[gt[:, 2] > 0]
        out = M.mesh_metrics(pred, gt, threshold=0.05)
        assert out["accuracy_m"] == 0.0
        assert out["completion_ratio"] == pytest.approx(0.5 + 0.05 / 2, abs=0.03)  # band of width 0.05 past the equator
        assert out["completion_m"] > 0.1

    def test_ghost_fraction_of_shifted_copy(self):
        gt_t = sphere_points(3000, seed=4)  # e.g. a moving object at time t
        stale = gt_t + np.array([0.5, 0.0, 0.0])  # reconstruction still shows it where it was
        pred = np.concatenate([gt_t, stale])
        assert M.ghost_fraction(gt_t, gt_t) == 0.0
        frac = M.ghost_fraction(pred, gt_t, threshold=0.05)
        # The stale copy overlaps the true sphere only near the intersection circle.
        assert 0.4 < frac < 0.5
        assert M.ghost_fraction(stale + np.array([5.0, 0, 0]), gt_t) == 1.0

    def test_empty_inputs(self):
        gt = sphere_points(100)
        out = M.mesh_metrics(np.zeros((0, 3)), gt)
        assert math.isnan(out["accuracy_m"]) and out["completion_m"] == math.inf
        assert out["chamfer_l1_m"] == math.inf and out["completion_ratio"] == 0.0
        assert math.isnan(M.ghost_fraction(np.zeros((0, 3)), gt))
        assert M.ghost_fraction(gt, np.zeros((0, 3))) == 1.0
        with pytest.raises(ValueError, match="empty"):
            M.mesh_metrics(gt, np.zeros((0, 3)))

    def test_torch_inputs(self):
        gt = torch.from_numpy(sphere_points(500, seed=5)).float()
        assert M.mesh_metrics(gt, gt)["chamfer_l1_m"] == 0.0

    def test_sample_mesh_surface(self):
        box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
        a = M.sample_mesh_surface(box, 5000, seed=3)
        b = M.sample_mesh_surface(box, 5000, seed=3)
        assert a.shape == (5000, 3) and a.dtype == np.float64 and np.array_equal(a, b)
        assert not np.array_equal(a, M.sample_mesh_surface(box, 5000, seed=4))
        assert np.abs(a).max(0) == pytest.approx([1.0, 0.5, 0.25])
        # Area-weighted: the two 2 x 1 faces hold 2 / 7 of the area... of 2*(2 + 1 + 0.5) = 7.
        on_z_faces = np.isclose(np.abs(a[:, 2]), 0.25)
        assert on_z_faces.mean() == pytest.approx(4.0 / 7.0, abs=0.03)
        assert M.sample_mesh_surface(trimesh.Trimesh(), 10, seed=0).shape == (0, 3)

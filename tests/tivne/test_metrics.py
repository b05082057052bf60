"""Tests of tivne.metrics: association, Umeyama, ATE / RPE (cross-checked with evo), image and surface metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from tivne import geometry as G
from tivne import metrics as M

F64 = torch.float64


def random_walk_poses(n: int, seed: int) -> np.ndarray:
    """(n, 4, 4) float64 smooth random camera trajectory (a few metres, full 3-D rotation changes)."""
    gen = torch.Generator().manual_seed(seed)
    steps = torch.randn(n, 6, generator=gen, dtype=F64) * torch.tensor([0.05, 0.05, 0.05, 0.03, 0.03, 0.03], dtype=F64)
    T = torch.eye(4, dtype=F64)
    out = []
    for xi in G.se3_exp(steps):
        T = T @ xi
        out.append(T)
    return torch.stack(out).numpy()


def similarity(R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


def apply_sim3_to_poses(S: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Map c2w poses by a similarity: positions s R p + t, orientations R_S R (stays in SE(3))."""
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    out = poses.copy()
    out[:, :3, :3] = (S[:3, :3] / s) @ poses[:, :3, :3]
    out[:, :3, 3] = poses[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    return out


def rot(seed: int) -> np.ndarray:
    q = torch.randn(4, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return G.quat_to_matrix(q).numpy()


class TestAssociation:
    def test_by_timestamp_is_the_data_layer_function(self):
        from data_modules.timestamps import associate_by_timestamp

        assert M.associate_by_timestamp is associate_by_timestamp  # tested in tests/data_modules/test_timestamps.py

    def test_by_index(self):
        a, b = M.associate_by_index(5, 3)
        assert a.tolist() == b.tolist() == [0, 1, 2]


class TestUmeyama:
    @pytest.mark.parametrize("with_scale", [False, True])
    def test_recovers_transform(self, with_scale):
        rng = np.random.default_rng(1)
        src = rng.normal(size=(50, 3))
        R_true, t_true, s_true = rot(2), np.array([1.0, -2.0, 0.5]), (2.5 if with_scale else 1.0)
        dst = s_true * src @ R_true.T + t_true
        R, t, s = M.umeyama_alignment(src, dst, with_scale=with_scale)
        assert R.dtype == np.float64 and t.shape == (3,) and isinstance(s, float)
        assert np.allclose(R, R_true, atol=1e-10) and np.allclose(t, t_true) and math.isclose(s, s_true)

    def test_reflection_is_never_returned(self):
        rng = np.random.default_rng(3)
        src = rng.normal(size=(30, 3))
        dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: best fit would be a reflection
        R, _, _ = M.umeyama_alignment(src, dst)
        assert math.isclose(np.linalg.det(R), 1.0, abs_tol=1e-10)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-10)

    def test_torch_input_and_errors(self):
        src = torch.randn(10, 3, dtype=torch.float32)
        R, t, s = M.umeyama_alignment(src, src)
        assert np.allclose(R, np.eye(3), atol=1e-6) and np.allclose(t, 0, atol=1e-6)
        with pytest.raises(ValueError):
            M.umeyama_alignment(np.zeros((4, 3)), np.zeros((5, 3)))
        with pytest.raises(ValueError, match="scale"):
            M.umeyama_alignment(np.ones((4, 3)), np.zeros((4, 3)), with_scale=True)


class TestATE:
    def test_zero_error_after_alignment(self):
        ref = random_walk_poses(40, seed=0)
        est = apply_sim3_to_poses(similarity(rot(4), np.array([3.0, 1.0, -1.0]), 1.0), ref)
        res = M.absolute_trajectory_error(est, ref, align="se3")
        assert res.rmse < 1e-10 and res.max < 1e-10 and res.num_poses == 40
        assert M.absolute_trajectory_error(est, ref, align="none").rmse > 0.5
        scaled = apply_sim3_to_poses(similarity(rot(5), np.zeros(3), 0.3), ref)
        assert M.absolute_trajectory_error(scaled, ref, align="sim3").rmse < 1e-10
        assert M.absolute_trajectory_error(scaled, ref, align="se3").rmse > 1e-3

    def test_known_offset_without_alignment(self):
        ref = random_walk_poses(20, seed=1)
        est = ref.copy()
        est[:, 0, 3] += 0.1
        res = M.absolute_trajectory_error(torch.from_numpy(est), ref, align="none")
        assert np.allclose(res.errors, 0.1) and math.isclose(res.rmse, 0.1) and res.std < 1e-12
        assert res.as_metrics() == {
            "ate_rmse_m": res.rmse,
            "ate_mean_m": res.mean,
            "ate_median_m": res.median,
            "ate_std_m": res.std,
            "ate_max_m": res.max,
        }
        assert set(res.as_metrics("eval_ate")) >= {"eval_ate_rmse_m"}
        assert np.allclose(res.alignment_matrix, np.eye(4))

    def test_errors(self):
        ref = random_walk_poses(5, seed=2)
        with pytest.raises(ValueError):
            M.absolute_trajectory_error(ref[:4], ref)
        with pytest.raises(ValueError, match="align"):
            M.absolute_trajectory_error(ref, ref, align="sim2")
        with pytest.raises(ValueError, match="no timestamps"):
            M.ate_from_trajectories([0.0], ref[:1], [5.0], ref[:1])

    def test_from_trajectories_associates(self):
        ref = random_walk_poses(30, seed=3)
        ts_ref = np.arange(30) * 0.033
        est = ref[5:25:2]
        ts_est = ts_ref[5:25:2] + 0.003
        res = M.ate_from_trajectories(ts_est, est, ts_ref, ref)
        assert res.rmse < 1e-10
        assert res.idx_ref.tolist() == list(range(5, 25, 2)) and res.idx_est.tolist() == list(range(10))


def noisy_pair(seed: int, scale: float):
    """Reference and a noisy, Sim(3)-transformed, time-jittered, subsampled estimate."""
    rng = np.random.default_rng(seed)
    n = 120
    ref = random_walk_poses(n, seed=seed)
    ts_ref = 1000.0 + np.arange(n) / 30.0
    keep = np.sort(rng.choice(n, size=100, replace=False))
    est = apply_sim3_to_poses(similarity(rot(seed + 100), rng.normal(size=3), scale), ref[keep])
    est[:, :3, 3] += rng.normal(scale=0.03, size=(len(keep), 3))
    noise_rot = G.se3_exp(torch.from_numpy(np.concatenate([np.zeros((len(keep), 3)), rng.normal(scale=0.02, size=(len(keep), 3))], 1)))
    est[:, :3, :3] = est[:, :3, :3] @ noise_rot[:, :3, :3].numpy()
    ts_est = ts_ref[keep] + rng.uniform(-0.005, 0.005, size=len(keep))
    return ts_est, est, ts_ref, ref


class TestAgainstEvo:
    @pytest.mark.parametrize("align,scale", [("se3", 1.0), ("sim3", 0.4)])
    def test_ate_matches_evo(self, align, scale):
        pytest.importorskip("evo", reason="evo not installed (pip install 'tivne[eval]')")
        from evo.core import metrics as evo_metrics
        from evo.core import sync
        from evo.core.trajectory import PoseTrajectory3D

        ts_est, est, ts_ref, ref = noisy_pair(seed=7 if align == "se3" else 8, scale=scale)
        traj_est = PoseTrajectory3D(poses_se3=list(est), timestamps=ts_est)
        traj_ref = PoseTrajectory3D(poses_se3=list(ref), timestamps=ts_ref)
        traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.02)
        _, _, evo_scale = traj_est.align(traj_ref, correct_scale=align == "sim3")
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((traj_ref, traj_est))
        stats = ape.get_all_statistics()

        ours = M.ate_from_trajectories(ts_est, est, ts_ref, ref, max_diff=0.02, align=align)
        assert ours.num_poses == traj_est.num_poses == 100
        for key in ("rmse", "mean", "median", "std", "max"):
            assert abs(getattr(ours, key) - stats[key]) < 1e-6, (key, getattr(ours, key), stats[key])
        assert np.allclose(ours.aligned_positions, traj_est.positions_xyz, atol=1e-6)
        assert abs(ours.scale - evo_scale) < 1e-9
        if align == "sim3":
            assert 1.5 < ours.scale < 3.0  # ~1 / 0.4, biased low by the position noise

    def test_rpe_matches_evo(self):
        pytest.importorskip("evo", reason="evo not installed (pip install 'tivne[eval]')")
        from evo.core import metrics as evo_metrics
        from evo.core.trajectory import PosePath3D

        _, est, _, ref = noisy_pair(seed=9, scale=1.0)
        ref = ref[: len(est)]  # RPE needs associated poses; any pairing works for the comparison
        ours = M.relative_pose_error(est, ref, delta=3)
        for relation, ours_rmse in [
            (evo_metrics.PoseRelation.translation_part, ours.trans_rmse_m),
            (evo_metrics.PoseRelation.rotation_angle_deg, ours.rot_rmse_deg),
        ]:
            # all_pairs=True: every (i, i + delta), as TUM's evaluate_rpe and ours (evo's default
            # takes non-overlapping pairs 0-3, 3-6, ...).
            rpe = evo_metrics.RPE(relation, delta=3, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
            rpe.process_data((PosePath3D(poses_se3=list(ref)), PosePath3D(poses_se3=list(est))))
            assert abs(ours_rmse - rpe.get_statistic(evo_metrics.StatisticsType.rmse)) < 1e-6


class TestRPE:
    def test_zero_for_rigidly_moved_trajectory(self):
        ref = random_walk_poses(15, seed=4)
        est = apply_sim3_to_poses(similarity(rot(6), np.array([1.0, 2.0, 3.0]), 1.0), ref)
        res = M.relative_pose_error(est, ref)
        assert res.trans_rmse_m < 1e-10 and res.rot_rmse_deg < 1e-5 and len(res.trans_errors) == 14
        assert set(res.as_metrics()) == {"rpe_trans_rmse_m", "rpe_trans_mean_m", "rpe_rot_rmse_deg", "rpe_rot_mean_deg"}

    def test_known_drift(self):
        ref = np.repeat(np.eye(4)[None], 5, 0)
        est = ref.copy()
        est[:, 0, 3] = 0.01 * np.arange(5)  # 1 cm drift per frame
        est[:, :3, :3] = G.se3_exp(torch.tensor([[0, 0, 0, 0, 0, math.radians(2.0) * k] for k in range(5)], dtype=F64))[:, :3, :3].numpy()
        res = M.relative_pose_error(est, ref, delta=1)
        assert np.allclose(res.rot_errors, 2.0) and np.allclose(res.trans_errors, 0.01)
        with pytest.raises(ValueError):
            M.relative_pose_error(est, ref, delta=5)


class TestImageMetrics:
    def test_identical(self):
        img = torch.rand(16, 20, 3, generator=torch.Generator().manual_seed(0))
        assert M.mse(img, img) == 0.0
        assert M.psnr(img, img) == math.inf
        assert M.ssim(img, img) == pytest.approx(1.0, abs=1e-5)

    def test_known_noise_psnr(self):
        gt = torch.full((1, 3, 8, 8), 0.5)
        pred = gt + 0.1  # mse = 0.01 -> 20 dB
        assert M.mse(pred, gt) == pytest.approx(0.01)
        assert M.psnr(pred, gt) == pytest.approx(20.0, abs=1e-4)
        assert M.psnr(pred * 255, gt * 255, max_val=255.0) == pytest.approx(20.0, abs=1e-4)
        rng = np.random.default_rng(0)
        gt = rng.uniform(0.2, 0.8, size=(32, 32, 3))
        pred = gt + rng.normal(scale=0.05, size=gt.shape)
        m = np.mean((pred - gt) ** 2)
        assert M.psnr(pred, gt) == pytest.approx(10 * math.log10(1 / m), abs=1e-9)
        assert M.ssim(torch.from_numpy(pred).float(), torch.from_numpy(gt).float()) < 0.99

    def test_layouts_agree(self):
        gen = torch.Generator().manual_seed(1)
        a, b = torch.rand(12, 14, 3, generator=gen), torch.rand(12, 14, 3, generator=gen)
        a4, b4 = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
        assert M.mse(a, b) == pytest.approx(M.mse(a4, b4))
        assert M.psnr(a, b) == pytest.approx(M.psnr(a4, b4))
        assert M.ssim(a, b) == pytest.approx(M.ssim(a4, b4))

    def test_batch_psnr_is_mean_of_images(self):
        gt = torch.zeros(2, 3, 4, 4)
        pred = torch.stack([torch.full((3, 4, 4), 0.1), torch.full((3, 4, 4), 0.01)])
        assert M.psnr(pred, gt) == pytest.approx(30.0, abs=1e-4)  # (20 + 40) / 2

    def test_mask(self):
        gt = torch.zeros(6, 8, 3)
        pred = gt.clone()
        pred[:3] = 0.1  # error only in the top half
        top = torch.zeros(6, 8, dtype=torch.bool)
        top[:3] = True
        assert M.mse(pred, gt, mask=top) == pytest.approx(0.01)
        assert M.mse(pred, gt, mask=~top) == 0.0
        assert M.mse(pred, gt) == pytest.approx(0.005)
        assert M.psnr(pred, gt, mask=top) == pytest.approx(20.0, abs=1e-4)
        assert M.psnr(pred, gt, mask=~top) == math.inf
        assert math.isnan(M.mse(pred, gt, mask=torch.zeros(6, 8, dtype=torch.bool)))
        assert M.ssim(pred, pred, mask=top) == pytest.approx(1.0, abs=1e-4)  # kornia's eps on flat images
        with pytest.raises(ValueError, match="mask"):
            M.mse(pred, gt, mask=torch.ones(5, 8, dtype=torch.bool))

    def test_bad_shapes(self):
        with pytest.raises(ValueError):
            M.mse(torch.zeros(4, 4), torch.zeros(4, 4))
        with pytest.raises(ValueError):
            M.psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))

    def test_lpips_reports_unavailability_without_download(self, monkeypatch, tmp_path):
        monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache: weights cannot be there
        ok, reason = M.lpips_available()
        assert ok is False and reason
        value, why = M.lpips(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))
        assert value is None and why == reason
        assert not any(tmp_path.rglob("*.pth"))


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

"""Tests of tivne.metrics.trajectory: association, Umeyama, ATE / RPE (cross-checked with evo)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tivne import geometry as G
from tivne.metrics import trajectory as M

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


def translating_poses(n: int, seed: int) -> np.ndarray:
    """(n, 4, 4) poses with identity rotation at random 3-D positions (camera frame = world frame)."""
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, 3] = np.random.default_rng(seed).normal(size=(n, 3)) * 0.3
    return out


def test_relative_motion_map_of_a_perfect_estimate_is_the_identity():
    gt = random_walk_poses(80, 3)
    r = M.relative_motion_map(gt, gt, delta=10)
    np.testing.assert_allclose(r.matrix, np.eye(3), atol=1e-9)
    assert r.trans_rmse_m < 1e-12 and r.fit_rmse_m < 1e-12 and r.rotation_deg < 1e-6 and r.pairs == 70


def test_relative_motion_map_recovers_a_shared_linear_distortion_and_separates_it_from_noise():
    gt = translating_poses(200, 4)
    A = np.diag([1.1, 0.95, 0.9])
    est = gt.copy()
    est[:, :3, 3] = gt[:, :3, 3] @ A.T
    exact = M.relative_motion_map(est, gt, delta=5)
    np.testing.assert_allclose(exact.singular_values, [1.1, 0.95, 0.9], atol=1e-9)
    assert exact.fit_rmse_m < 1e-12 < exact.trans_rmse_m
    # random per-pose error is no linear map: it stays in the fit's residual
    noisy = est.copy()
    noisy[:, :3, 3] += np.random.default_rng(5).normal(size=(200, 3)) * 0.01
    r = M.relative_motion_map(noisy, gt, delta=5)
    np.testing.assert_allclose(r.singular_values, [1.1, 0.95, 0.9], atol=0.02)
    assert r.fit_rmse_m == pytest.approx(0.01 * math.sqrt(2 * 3), rel=0.15)


def test_relative_motion_map_rejects_too_few_poses_and_degenerate_motion():
    gt = translating_poses(10, 6)
    with pytest.raises(ValueError, match="delta=10"):
        M.relative_motion_map(gt, gt, delta=10)
    line = np.tile(np.eye(4), (20, 1, 1))
    line[:, 0, 3] = np.arange(20) * 0.01
    with pytest.raises(ValueError, match="fewer than 3 dimensions"):
        M.relative_motion_map(line, line, delta=2)

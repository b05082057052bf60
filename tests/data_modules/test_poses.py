"""data_modules.poses: quaternions, poses from (t, q), projection onto SO(3), pose interpolation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from data_modules import poses as P
from data_modules.poses import (
    TIME_TOLERANCE_S,
    interpolate_poses,
    orthonormalize_pose,
    slerp_quat,
)

F64 = torch.float64


def random_rotations(n: int, seed: int) -> torch.Tensor:
    """(n, 3, 3) float64 random proper rotations."""
    return P.quat_to_matrix(torch.randn(n, 4, generator=torch.Generator().manual_seed(seed), dtype=F64))


def random_poses(n: int, seed: int) -> torch.Tensor:
    """(n, 4, 4) float64 random rigid transforms."""
    T = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    T[:, :3, :3] = random_rotations(n, seed)
    T[:, :3, 3] = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
    return T


class TestQuaternion:
    def test_identity(self):
        assert torch.allclose(P.quat_to_matrix(torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64)), torch.eye(3, dtype=F64))
        assert torch.allclose(P.matrix_to_quat(torch.eye(3, dtype=F64)), torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64))

    def test_round_trip_sign_canonicalised(self):
        gen = torch.Generator().manual_seed(10)
        q = torch.randn(200, 4, generator=gen, dtype=F64)
        q = q / q.norm(dim=-1, keepdim=True)
        assert (q[:, 3] < 0).any()
        R = P.quat_to_matrix(q)
        assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(200, 3, 3), atol=1e-12)
        assert torch.allclose(torch.linalg.det(R), torch.ones(200, dtype=F64))
        q2 = P.matrix_to_quat(R)
        assert torch.all(q2[:, 3] >= 0)
        canonical = torch.where(q[:, 3:4] < 0, -q, q)
        assert torch.allclose(q2, canonical, atol=1e-12)

    def test_non_unit_quaternion_is_normalised(self):
        q = torch.tensor([0.1, -0.2, 0.3, 0.9], dtype=F64)
        assert torch.allclose(P.quat_to_matrix(7.5 * q), P.quat_to_matrix(q))
        assert torch.allclose(P.matrix_to_quat(P.quat_to_matrix(7.5 * q)), q / q.norm(), atol=1e-12)

    @pytest.mark.parametrize("eps", [0.0, 1e-9, 1e-5])
    def test_near_180_degrees(self, eps):
        gen = torch.Generator().manual_seed(11)
        axis = torch.randn(50, 3, generator=gen, dtype=F64)
        axis = axis / axis.norm(dim=-1, keepdim=True)
        half = 0.5 * (math.pi - eps)
        q = torch.cat([axis * math.sin(half), torch.full((50, 1), math.cos(half), dtype=F64)], -1)
        q2 = P.matrix_to_quat(P.quat_to_matrix(q))
        assert torch.allclose(q2.norm(dim=-1), torch.ones(50, dtype=F64))
        # qw ~ 0: the sign is only defined up to +-; the rotation must round-trip exactly.
        same = torch.minimum((q2 - q).norm(dim=-1), (q2 + q).norm(dim=-1))
        assert same.max() < 1e-9
        assert torch.allclose(P.quat_to_matrix(q2), P.quat_to_matrix(q), atol=1e-12)

    def test_pose_from_tq(self):
        T = P.pose_from_tq(torch.tensor([1.0, 2.0, 3.0], dtype=F64), torch.tensor([0.0, 0.0, 0.0, 2.0], dtype=F64))
        expected = torch.eye(4, dtype=F64)
        expected[:3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
        assert torch.allclose(T, expected)


class TestOrthonormalizePose:
    def test_rotations_and_translation_are_kept(self):
        T = random_poses(20, 0)
        out = orthonormalize_pose(T)
        assert out.dtype == F64 and out.shape == (20, 4, 4)
        assert torch.allclose(out, T, atol=1e-12)

    def test_nearest_rotation_with_det_plus_one(self):
        # a scaled, sheared rotation (like Bonn's hand-measured T_M) and a reflection
        T = random_poses(2, 3)
        T[0, :3, :3] = 1.06 * T[0, :3, :3] + 0.01 * torch.randn(3, 3, generator=torch.Generator().manual_seed(4), dtype=F64)
        T[1, :3, :3] = T[1, :3, :3] @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=F64))
        out = orthonormalize_pose(T)
        R = out[:, :3, :3]
        assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(2, 3, 3), atol=1e-12)
        assert torch.allclose(torch.linalg.det(R), torch.ones(2, dtype=F64))
        assert torch.equal(out[:, :3, 3], T[:, :3, 3])
        U, _, Vt = np.linalg.svd(T[0, :3, :3].numpy())  # SVD projection, no reflection needed here
        np.testing.assert_allclose(R[0].numpy(), U @ Vt, atol=1e-12)

    def test_float32_in_float32_out_and_last_row(self):
        T = random_poses(3, 5).float()
        T[:, 3, :3] = 0.5
        out = orthonormalize_pose(T)
        assert out.dtype == torch.float32
        assert torch.equal(out[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(3, 4))

    def test_rank_deficient_input_gives_a_rotation(self):
        T = torch.eye(4, dtype=F64)
        T[2, 2] = 0.0  # det 0: the sign fix must not zero a column
        R = orthonormalize_pose(T)[:3, :3]
        assert torch.linalg.det(R) == pytest.approx(1.0)


class TestSlerp:
    def test_endpoints_midpoint_and_short_arc(self):
        qa = P.matrix_to_quat(torch.eye(3, dtype=F64))
        qb = torch.tensor([0.0, 0.0, math.sin(0.5), math.cos(0.5)], dtype=F64)  # 1 rad about z
        s = torch.tensor([0.0, 0.5, 1.0], dtype=F64)
        q = slerp_quat(qa.expand(3, 4), qb.expand(3, 4), s)
        assert torch.allclose(q[0], qa) and torch.allclose(q[2], qb)
        assert torch.allclose(q[1], torch.tensor([0.0, 0.0, math.sin(0.25), math.cos(0.25)], dtype=F64))
        # -qb is the same rotation: still the 0.5 rad midpoint, not the long way round
        assert torch.allclose(slerp_quat(qa, -qb, torch.tensor(0.5, dtype=F64)), q[1])

    def test_nearly_equal_quaternions_are_finite(self):
        qa = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64)
        qb = torch.tensor([0.0, 0.0, 1e-9, 1.0], dtype=F64)
        q = slerp_quat(qa, qb / qb.norm(), torch.tensor(0.3, dtype=F64))
        assert torch.isfinite(q).all() and q.norm() == pytest.approx(1.0)


def test_interpolate_poses_exact_hits_and_outside():
    P_ = random_poses(3, 8)
    out, valid = interpolate_poses([0.0, 1.0, 2.0], P_, [-0.5, 0.0, 2.0, 2.5], max_gap=0.1)
    assert valid.tolist() == [False, True, True, False]
    np.testing.assert_allclose(out[1].numpy(), P_[0].numpy())
    np.testing.assert_allclose(out[2].numpy(), P_[2].numpy())


def test_interpolate_poses_between_samples():
    A = random_poses(2, 7)
    B = A.clone()
    angle = 0.6
    Rz = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]], dtype=F64)
    B[1, :3, :3] = B[0, :3, :3] @ Rz
    B[1, :3, 3] = B[0, :3, 3] + torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    out, valid = interpolate_poses([10.0, 11.0], B, [10.25, 10.5], max_gap=None)
    assert valid.all() and out.dtype == F64
    for k, s in enumerate((0.25, 0.5)):
        Rs = torch.tensor([[math.cos(s * angle), -math.sin(s * angle), 0], [math.sin(s * angle), math.cos(s * angle), 0], [0, 0, 1]], dtype=F64)
        assert torch.allclose(out[k, :3, :3], B[0, :3, :3] @ Rs, atol=1e-12)
        assert torch.allclose(out[k, :3, 3], (1 - s) * B[0, :3, 3] + s * B[1, :3, 3], atol=1e-12)
    _, valid = interpolate_poses([10.0, 11.0], B, [10.5], max_gap=0.5)
    assert valid.tolist() == [False]  # a 1 s gap is longer than max_gap
    out, valid = interpolate_poses([], torch.zeros(0, 4, 4), [1.0])
    assert valid.tolist() == [False] and torch.equal(out[0], torch.eye(4, dtype=F64))


def test_interpolate_poses_snaps_within_tolerance():
    # Rounded file timestamps: a query a few microseconds outside the samples' span is the end pose.
    P_ = random_poses(3, 9)
    t = [1.0, 2.0, 3.0]
    eps = 0.5 * TIME_TOLERANCE_S
    out, valid = interpolate_poses(t, P_, [1.0 - eps, 2.0 + eps, 3.0 + eps, 3.0 + 2 * TIME_TOLERANCE_S], max_gap=0.1)
    assert valid.tolist() == [True, True, True, False]
    for k, j in enumerate((0, 1, 2)):
        assert torch.equal(out[k], P_[j])
    _, exact = interpolate_poses(t, P_, [3.0 + eps, 3.0], max_gap=0.1, tolerance=0.0)
    assert exact.tolist() == [False, True]


def _slide_and_spin(t: float) -> torch.Tensor:
    """A body sliding at (1.3, 0, 0.1) m/s while it spins at 2 rad/s about its own z axis."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = P.rotation_from_vector(torch.tensor([0.0, 0.0, 2.0 * t], dtype=torch.float64))
    T[:3, 3] = torch.tensor([1.3 * t, 0.2, 0.1 * t], dtype=torch.float64)
    return T


def test_rotation_vector_and_back():
    w = torch.tensor([[0.3, -0.2, 0.5], [1e-14, 0.0, 0.0], [3.0, 0.1, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(P.rotation_vector(P.rotation_from_vector(w)), w, atol=1e-12, rtol=0)


def test_pose_on_track_interpolates_inside_and_continues_the_end_velocity_outside():
    times = np.arange(0.4, 1.0, 1 / 30)
    poses = torch.stack([_slide_and_spin(float(t)) for t in times])
    for t in (0.1, 0.55, 1.3):  # before, inside, after: exact for a constant slide and spin
        torch.testing.assert_close(P.pose_on_track(times, poses, t), _slide_and_spin(t), atol=1e-6, rtol=0)
    # the speed comes from a baseline, not from the last step alone: a 1 mm jitter of the last pose
    # moves a pose 0.3 s ahead by ~1 mm + 1 mm·0.3/0.1, not by 1 mm·0.3/0.033
    noisy = poses.clone()
    noisy[-1, 0, 3] += 0.001
    off = (P.pose_on_track(times, noisy, times[-1] + 0.3)[:3, 3] - _slide_and_spin(times[-1] + 0.3)[:3, 3]).norm()
    assert float(off) < 0.0045
    with pytest.raises(ValueError):
        P.pose_on_track(np.zeros(0), torch.zeros(0, 4, 4), 0.0)


def test_pose_on_track_follows_a_body_that_turns_back_inside_a_gap():
    """A body sliding out at 1 m/s and braked at 2 m/s² (it stops at 0.5 s and comes back), unseen
    from 0.35 to 1.25 s: the cubic through both ends' positions and velocities stays within 3 cm of
    it; each end carried on at its own velocity and blended (exact only for a constant one) was up to
    27 cm off."""
    times = np.arange(0.0, 2.0, 1 / 30)
    times = times[(times < 0.35) | (times > 1.25)]
    slide = lambda t: 1.0 * t - 1.0 * t * t  # noqa: E731
    poses = torch.eye(4, dtype=torch.float64).repeat(len(times), 1, 1)
    poses[:, 0, 3] = torch.as_tensor(slide(times))
    for t in (0.5, 0.8, 1.1):
        assert abs(float(P.pose_on_track(times, poses, t)[0, 3]) - slide(t)) < 0.03, t
    assert torch.allclose(P.hermite(torch.zeros(3), torch.ones(3), torch.ones(3), torch.ones(3), 1.0, 0.5), torch.full((3,), 0.5))


def test_a_short_run_between_two_gaps_gives_its_own_velocity():
    """Seen for two frames (1.0 and 1.033 s) between two gaps, then unseen until 1.83 s while it turns
    back (at 1.4 s): the two frames' velocity shapes the cubic (within 1.5 cm; the straight line between
    the gap's ends, taken when no sample lay a baseline inside the run, was 11-16 cm off)."""
    times = np.arange(0.0, 2.4, 1 / 30)
    times = times[(times < 0.3) | ((times > 0.99) & (times < 1.05)) | (times > 1.8)]
    slide = lambda t: 2.8 * t - 1.0 * t * t  # noqa: E731
    poses = torch.eye(4, dtype=torch.float64).repeat(len(times), 1, 1)
    poses[:, 0, 3] = torch.as_tensor(slide(times))
    for t in (1.2, 1.4, 1.6):
        assert abs(float(P.pose_on_track(times, poses, t)[0, 3]) - slide(t)) < 0.015, t


def test_pose_on_track_turns_about_the_pivot_it_is_given_and_the_long_way_across_a_gap():
    # A box turning in place at 3 rad/s about its own axis, tracked with its origin 10 cm off that axis
    # (the centre of the points first seen), unseen for 1.5 s (4.5 rad, more than half a turn).
    off = torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)  # the axis in body coordinates

    def turning(t: float) -> torch.Tensor:
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = P.rotation_from_vector(torch.tensor([0.0, 0.0, 3.0 * t], dtype=torch.float64))
        T[:3, 3] = torch.tensor([0.5, 0.2, 1.0], dtype=torch.float64) - T[:3, :3] @ off
        return T

    times = np.concatenate([np.arange(0.0, 0.2, 1 / 30), np.arange(1.7, 1.9, 1 / 30)])
    poses = torch.stack([turning(float(t)) for t in times])
    for t in (0.5, 0.9, 1.4, 2.3):  # in the gap, after the end
        torch.testing.assert_close(P.pose_on_track(times, poses, t, pivot=off), turning(t), atol=1e-9, rtol=0)
    assert float((P.pose_on_track(times, poses, 0.9)[:3, 3] - turning(0.9)[:3, 3]).norm()) > 0.01  # about the origin
    short_way = P.pose_on_track(times, poses, 0.9, baseline=2.0, pivot=off)  # SLERP alone across the gap
    assert float(P.rotation_vector(short_way[:3, :3] @ turning(0.9)[:3, :3].T).norm()) > 1.0

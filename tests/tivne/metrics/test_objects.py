"""Per-object trajectory error on known inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tivne.metrics.objects import first_frame_aligned, object_trajectory_error, rotation_angle_deg


def _rz(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = t
    return T


def _rx(deg: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T[1:3, 1:3] = [[c, -s], [s, c]]
    return T


GT = np.stack([_rz(10 * i, (0.1 * i, 0.2, 1.0 - 0.05 * i)) @ _rx(5 * i) for i in range(6)])


def test_rotation_angle():
    np.testing.assert_allclose(rotation_angle_deg(np.stack([_rz(0)[:3, :3], _rz(30)[:3, :3], _rx(179.5)[:3, :3]])), [0, 30, 179.5], atol=1e-9)


def test_error_is_zero_whatever_the_object_frame_and_the_slam_world():
    X = _rz(33, (0.3, -0.1, 0.05)) @ _rx(-20)  # the tracker's own object frame
    W = _rz(-70, (2.0, 1.0, 0.5))  # SLAM world -> GT world
    est = np.linalg.inv(W)[None] @ GT @ X[None]
    err = object_trajectory_error(est, GT, W)
    assert err.num_poses == 6 and err.ate_max_m < 1e-12 and err.rot_max_deg < 1e-6
    np.testing.assert_allclose(first_frame_aligned(est, GT, W), GT, atol=1e-12)


def test_known_translation_and_rotation_errors():
    est = GT.copy()
    est[3, :3, 3] += [0.03, 0.0, -0.04]  # 5 cm at one frame (the object's origin)
    est[5] = est[5] @ _rz(2.0, (0.0, 0.0, 0.0))  # 2 degrees about its own origin at another
    err = object_trajectory_error(est, GT)
    assert err.ate_max_m == pytest.approx(0.05) and err.ate_rmse_m == pytest.approx(math.sqrt(0.05**2 / 6))
    assert err.rot_max_deg == pytest.approx(2.0) and err.rot_rmse_deg == pytest.approx(math.sqrt(4.0 / 6))
    keys = err.as_metrics("ball")
    assert keys["object_ball_ate_m"] == err.ate_rmse_m and keys["object_ball_rot_deg"] == err.rot_rmse_deg and keys["object_ball_poses"] == 6


def test_the_first_frame_is_the_alignment():
    est = GT.copy()
    est[0, :3, 3] += 1.0  # a wrong first pose: every later motion is measured from it
    err = object_trajectory_error(est, GT)
    assert err.ate_max_m > 0.1  # a wrong first pose is not aligned away by any later frame
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        object_trajectory_error(GT[:2], GT[:3])
